"""``agsf sweep``: the grid of configurations, their validation, the output folder's lock and the local backend.

See :mod:`agsf_torch.experiments.sweep` for the folder layout and the two backends.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import signal
import threading
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ...storage.files import append_line, json_text, repair_json_lines
from ..config.loader import ExperimentConfig, parse_override
from ..report.tensorboard import hparam_domains, move_events, run_names, write_hparams_session
from ..run.experiment import prepare_output, run_experiment
from ..run.file_writer import check_threads, default_writers, writing_beside
from ..run.resources import available_memory, check_memory, writer_memory
from .ray_backend import import_ray, run_on_ray
from .rows import config_metrics

__all__ = ["parse_grid", "run_sweep", "SweepBusy", "BACKENDS"]

BACKENDS = ("local", "ray")

logger = logging.getLogger(__name__)


def _split_values(text: str) -> list[str]:
    """``"v1,v2,…"`` split at the commas outside brackets, braces and quotes, so that a list- or
    table-valued key sweeps whole values (``rate_axes=[1,0,0],[0,1,0]`` → two axes)."""
    parts, depth, quote, start = [], 0, "", 0
    for i, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "\"'":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append(text[start:i])
            start = i + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def parse_grid(items: list[str], base: ExperimentConfig | None = None) -> dict[str, list[Any]]:
    """``["key=v1,v2", …]`` → ``{key: [v1, v2]}`` (values parsed as TOML, split at the commas outside
    brackets and quotes, so list values sweep whole: ``rate_axes=[1,0,0],[0,1,0]``; keys validated).

    With ``base``, each value is normalised as the configuration stores it (``1`` and
    ``1.0`` of a float key are the same value), so a grid names each experiment once.

    Raises:
        ValueError: a malformed entry, a key given twice, an unsweepable key, a value the
            configuration refuses, or a value listed twice (after normalisation).
    """
    grid: dict[str, list[Any]] = {}
    for item in items:
        if "=" not in item:
            raise ValueError(f"grid entry {item!r} must look like key=v1,v2,...")
        key, values = (part.strip() for part in item.split("=", 1))
        if key in ("runs", "filters"):
            raise ValueError(f"config key '{key}' cannot be swept")
        if key in grid:
            raise ValueError(f"grid key '{key}' is given twice; list all its values in one --grid {key}=v1,v2,...")
        parsed = [parse_override(f"{key}={v}")[1] for v in _split_values(values)]
        if base is not None:
            parsed = [getattr(base.replace(**{key: v}), key) for v in parsed]
        seen: list[Any] = []
        for v in parsed:
            if v in seen:
                raise ValueError(f"grid key '{key}' lists the value {v!r} twice")
            seen.append(v)
        grid[key] = parsed
    if not grid:
        raise ValueError("a sweep needs at least one --grid key=v1,v2,...")
    return grid


class SweepBusy(ValueError):
    """Another sweep is writing the same output folder."""


def run_sweep(
    base: ExperimentConfig,
    grid: dict[str, list[Any]],
    out: Path,
    *,
    progress: bool = True,
    runner: Callable[..., dict[str, Any]] = run_experiment,
    backend: str = "local",
    address: str | None = None,
    cpus_per_task: int = 1,
    max_retries: int = 3,
    force: bool = False,
    threads: int | None = None,
) -> list[dict[str, Any]]:
    """Run every combination of ``grid`` on top of ``base``; returns all result rows.

    Every configuration (and its memory estimate, :func:`agsf_torch.experiments.run.resources.check_memory`, unless
    ``force``) is validated before any work starts or anything is created.  ``out`` holds
    ``experiment.json``, ``results.jsonl`` (one row ``{"digest", "params",
    "metrics"}`` per finished configuration), ``configs/<digest>/`` (that
    configuration's experiment folder, its events moved out) and ``tensorboard/<params>/``
    (its curves and HParams session, see the module docstring).  Digests
    already in ``results.jsonl`` are skipped; its rows are appended as complete lines,
    and a torn last line (an interrupted write) is dropped with a warning and rerun.
    One sweep at a time may write ``out``: a second one raises :class:`SweepBusy`.

    Args:
        runner: runs one configuration, ``runner(cfg, out, progress=, kind=, label=, writer=[, reuse=])`` →
            summary (:func:`run_experiment`; tests inject failures through it); ``label`` (local
            backend) names the configuration on its progress bar: its preset and parameters; ``writer`` (local
            backend) writes its files; ``reuse`` (local backend) names the folders of filters it copies.
            With ``backend="ray"`` it runs on the workers, so it must be picklable.
        backend: ``"local"`` (in this process, one configuration after another)
            or ``"ray"`` (one Ray task per configuration, see the module docstring).
        address: Ray only.  ``None``: the cluster named by ``RAY_ADDRESS`` if set,
            else a new local Ray instance (shut down at the end); ``"auto"``: the
            cluster this machine belongs to (``ray start``); ``"ray://HOST:10001"``:
            a remote cluster through Ray Client.  If Ray is already initialised in
            this process, that connection is used and ``address`` is ignored.
        cpus_per_task: Ray only: CPUs each task reserves; its torch threads are set
            to the same number.
        max_retries: Ray only: retries of a task whose worker or node died
            (exceptions raised by the runner are not retried: they are deterministic).
        threads: local only: torch threads (default: torch's, capped so that they and the writer fit the CPUs).
            Locally a worker process writes a configuration's figures, event files and ``runs.npz`` while the next
            configuration runs where the process may use two CPUs or more (:func:`~agsf_torch.experiments.run.file_writer.writing_beside`).  A
            configuration is recorded (its events moved, its row appended) once its files are complete; one that
            reuses a filter of the configuration before it starts once that one is recorded.

    Raises:
        SweepFailed: (Ray) some configurations failed; all others were recorded.
        RayUnavailable: ``backend="ray"`` without Ray installed.
        SweepBusy: another sweep holds ``out``'s lock.
    """
    if backend not in BACKENDS:
        raise ValueError(f"unknown sweep backend {backend!r}; choose from {', '.join(BACKENDS)}")
    if address is not None and backend != "ray":
        raise ValueError("a Ray address needs backend='ray' (--backend ray)")
    if cpus_per_task < 1:
        raise ValueError(f"cpus_per_task must be ≥ 1, got {cpus_per_task}")
    if backend == "ray" and threads:
        raise ValueError("threads are the local backend's (Ray tasks take cpus_per_task)")
    check_threads(threads)
    writers = default_writers() if backend == "local" else 0
    if backend == "ray":
        import_ray()  # fail before any work or folder if the extra is missing
    grid = {key: [getattr(base.replace(**{key: v}), key) for v in values] for key, values in grid.items()}  # 1 ≡ 1.0
    configs, digests = [], set()
    for values in itertools.product(*grid.values()):
        params = dict(zip(grid, values))
        cfg = base.replace(**params)  # validates every configuration first
        check_memory(cfg, force=force, budget=available_memory() - writer_memory(cfg, writers))
        if cfg.digest() not in digests:  # grid values the configuration stores alike: run once
            digests.add(cfg.digest())
            configs.append((params, cfg))
    digest = hashlib.sha256(json.dumps({"base": base.digest(), "grid": grid}, sort_keys=True).encode()).hexdigest()[:16]
    out = prepare_output(Path(out), "sweep", digest, {"base": base.to_dict(), "grid": grid})
    with _sweep_lock(out):
        if backend == "local":
            with writing_beside(threads) as writer:
                return _run_pending(
                    configs, out, progress, runner, backend, address, cpus_per_task, max_retries, writer
                )
        return _run_pending(configs, out, progress, runner, backend, address, cpus_per_task, max_retries)


@contextmanager
def _sweep_lock(out: Path):
    """Hold ``out/.sweep.lock`` (:mod:`filelock`) for the sweep; refuse if another sweep holds it."""
    from filelock import FileLock, Timeout

    lock = FileLock(str(out / ".sweep.lock"))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise SweepBusy(
            f"another agsf sweep is writing {out}; wait for it to finish (or rerun it later to resume)"
        ) from None
    try:
        yield
    finally:
        lock.release()


@contextmanager
def _interrupt_latch():
    """Remember every Ctrl-C (SIGINT) while the sweep runs, besides raising ``KeyboardInterrupt`` as usual:
    Python drops an exception raised while a finaliser or weak-reference callback runs ("Exception
    ignored in: …"), and the sweep would then run to its end; the latch stops it after the current row."""
    latch = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield latch
        return

    def on_sigint(signum, frame):
        latch.set()
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield latch
    finally:
        signal.signal(signal.SIGINT, previous)


def _run_pending(
    configs, out, progress, runner, backend, address, cpus_per_task, max_retries, writer=None
) -> list[dict[str, Any]]:
    """Run the configurations without a row in ``results.jsonl`` (the lock held); returns all rows.  Locally a
    configuration's files are written by ``writer`` while the next one runs, and it is recorded once they are
    complete (:meth:`~agsf_torch.experiments.run.file_writer.FileWriter.wait_for`)."""
    results = out / "results.jsonl"
    rows = repair_json_lines(results)
    done = {r["digest"] for r in rows}
    pending = [(params, cfg) for params, cfg in configs if cfg.digest() not in done]
    # names and domains from every configuration of the sweep: the same on every (resumed) run
    names = run_names((params, cfg.digest()) for params, cfg in configs)
    #: each configuration's label: its progress bar's and its figures' title (the preset's name and the parameters)
    labels = {cfg.digest(): f"{cfg.name} {names[cfg.digest()]}" for _, cfg in configs}
    domains = hparam_domains(params for params, _ in configs)

    # every filter's results by its own digest (the options it reads): the configuration folder that holds them
    sources: dict[str, Path] = {}
    for _, cfg in configs:
        if cfg.digest() in done and (out / "configs" / cfg.digest() / "runs.npz").is_file():
            for name in cfg.filters:
                sources.setdefault(cfg.filter_digest(name), out / "configs" / cfg.digest())

    def record(
        params: dict[str, Any], cfg: ExperimentConfig, summary_metrics: dict[str, float], reused: dict[str, str]
    ) -> None:
        run_dir = out / "tensorboard" / names[cfg.digest()]
        move_events(out / "configs" / cfg.digest() / "tensorboard", run_dir)
        write_hparams_session(run_dir, params, summary_metrics, domains)
        row = {"digest": cfg.digest(), "params": params, "metrics": summary_metrics}
        if reused:
            row["reused"] = reused
        append_line(results, json_text(row))
        rows.append(row)

    def finish(params, cfg, summary, reuse) -> None:
        """Record a configuration run locally, once its files are complete; its filters can then be reused."""
        folder = out / "configs" / cfg.digest()
        writer.wait_for(folder)
        record(params, cfg, config_metrics(summary), {n: p.name for n, p in reuse.items()})
        for name in cfg.filters:
            sources.setdefault(cfg.filter_digest(name), folder)

    with _interrupt_latch() as interrupted:
        if backend == "local":
            previous = None  # the configuration whose files are being written
            for params, cfg in pending:
                folder = out / "configs" / cfg.digest()
                label = labels[cfg.digest()]  # the bar names the configuration, not only its preset
                digests = {cfg.filter_digest(n) for n in cfg.filters}
                if previous is not None and (digests - set(sources)) & {
                    previous[1].filter_digest(n) for n in previous[1].filters
                }:  # it reuses a filter of the previous configuration: that one is complete and recorded first
                    finish(*previous)
                    previous = None
                    if interrupted.is_set():  # a Ctrl-C swallowed while its files were written
                        raise KeyboardInterrupt
                reuse = {n: sources[d] for n in cfg.filters if (d := cfg.filter_digest(n)) in sources}
                kwargs = {"reuse": reuse} if reuse else {}
                try:
                    summary = runner(
                        cfg, folder, progress=progress, kind="sweep-config", label=label, writer=writer, **kwargs
                    )
                except BaseException:  # failed or interrupted: the previous configuration ran to its end, so it is
                    # recorded once its files are written (a second Ctrl-C meanwhile stops the writer); its own
                    # failure to write is logged, and this failure (or the interruption) is the one raised
                    if previous is not None:
                        try:
                            finish(*previous)
                        except Exception as failed:  # noqa: BLE001
                            logger.warning("%s (while the next configuration failed or was interrupted)", failed)
                    raise
                if previous is not None:
                    finish(*previous)
                previous = (params, cfg, summary, reuse)
                if not writer.background:  # nothing is being written: recorded at once
                    finish(*previous)
                    previous = None
                if interrupted.is_set():  # a Ctrl-C that Python swallowed (e.g. raised inside a finaliser): this
                    if previous is not None:  # configuration ran to its end, so it is recorded (once its files are)
                        finish(*previous)
                    raise KeyboardInterrupt
            if previous is not None:  # a Ctrl-C swallowed while its files are written finds the sweep complete:
                finish(*previous)  # it ends as it would have a moment later

        elif pending:
            run_on_ray(
                pending,
                out,
                record,
                runner,
                address,
                cpus_per_task,
                max_retries,
                progress,
                len(configs),
                interrupted,
                labels,
            )
    return rows
