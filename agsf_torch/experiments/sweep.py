"""``agsf sweep``: a resumable grid of configurations, each a batched Monte Carlo.

Every finished configuration is appended as one JSON line to ``results.jsonl``
(with the configuration's digest) as soon as it finishes; a rerun with the same
base and grid skips the digests already there, so an interrupted sweep loses
only the configurations that were running.

TensorBoard (``tensorboard --logdir out/tensorboard``) gets one run per
configuration, named by its swept parameters (``reg=0.5,scaling=trace``,
:func:`.tensorboard_log.run_name`; a digest is appended only where two names would
collide).  That run holds both the configuration's time series (simulated time on
the x-axis, see :mod:`.tensorboard_log`) and its HParams session (its parameters,
its metrics, and the sweep's complete grid as the experiment configuration), so the
HParams tab opens onto each configuration's curves::

    out/tensorboard/reg=0.5,scaling=trace/   events: curves + HParams session
    out/tensorboard/reg=1.0,scaling=trace/   ...
    out/configs/<digest>/                    the configuration's experiment folder
                                             (runs.npz, summary.json, figures)

The configuration's events are moved there from its folder when it is recorded,
just before its row is appended (a rerun replaces the run of a configuration
interrupted in between).

Two backends run the pending configurations:

* ``"local"`` (default): one after another in this process.
* ``"ray"``: one Ray task per configuration (``num_cpus=cpus_per_task``), run
  in parallel on a local Ray instance or on an existing cluster.  Each task runs
  the configuration's Monte Carlo into a temporary folder *on its worker* and
  returns the folder's files; the driver (this process) is the only writer of
  ``out``: it unpacks each configuration's folder to ``out/configs/<digest>`` and
  appends its row in the order the tasks finish.  ``out`` therefore needs no
  shared filesystem.  A task whose worker or node dies is retried by Ray
  (``max_retries``); a configuration that still fails does not stop the others:
  the driver records every configuration that finishes, then raises
  :class:`SweepFailed` naming the failed ones, and a rerun runs only those.

Both backends give the same rows for the same seeds: a configuration's numbers
depend only on its fields (counter-based random streams seeded by ``seed``) and
not on the process or the number of torch threads that computes them (tested
bit for bit).  Only the order of the rows in ``results.jsonl`` may differ.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import os
import shutil
import tempfile
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from ..files import append_line, repair_json_lines
from .config import ExperimentConfig, parse_override
from .experiment import prepare_output, run_experiment
from .resources import check_memory
from .tensorboard_log import clear_events, hparam_domains, move_events, run_names, write_hparams_session

__all__ = ["parse_grid", "run_sweep", "results_table", "SweepFailed", "SweepBusy", "RayUnavailable", "BACKENDS"]

BACKENDS = ("local", "ray")
RAY_INSTALL_HINT = (
    "pip install 'agsf-torch[ray]' with the project's constraints.txt "
    "(in a checkout: .venv/bin/pip install -c constraints.txt -e '.[ray]', or bash scripts/setup_env.sh)"
)


class SweepFailed(RuntimeError):
    """Some configurations of a sweep failed; every other one was recorded.

    ``failures`` lists ``(digest, params, message)`` of the failed configurations.
    """

    def __init__(self, failures: list[tuple[str, dict[str, Any], str]], total: int):
        self.failures = failures
        lines = [f"{len(failures)} of {total} sweep configurations failed (the others are recorded; a rerun runs only these):"]
        for digest, params, message in failures:
            first = message.strip().splitlines()[-1] if message.strip() else "(no message)"
            lines.append(f"  {digest} {json.dumps(params, sort_keys=True)}: {first}")
        super().__init__("\n".join(lines))


class RayUnavailable(ImportError):
    """``backend="ray"`` without Ray installed."""


def parse_grid(items: list[str], base: ExperimentConfig | None = None) -> dict[str, list[Any]]:
    """``["key=v1,v2", …]`` → ``{key: [v1, v2]}`` (values parsed as TOML; keys validated).

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
        parsed = [parse_override(f"{key}={v}")[1] for v in values.split(",")]
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


def _metrics(summary: dict[str, Any]) -> dict[str, float]:
    m: dict[str, float] = {}
    for name, f in summary["filters"].items():
        if "between_updates" in f:
            m[f"{name}/mean_rms_between_updates_deg"] = f["between_updates"]["mean_rms_deg"]
        m[f"{name}/time_averaged_nees"] = f["time_averaged_nees"]
    d = summary.get("agsf_minus_gsf", {}).get("between_updates")
    if d:
        m["agsf_minus_gsf_deg"] = d["mean_deg"]
    return m


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
) -> list[dict[str, Any]]:
    """Run every combination of ``grid`` on top of ``base``; returns all result rows.

    Every configuration (and its memory estimate, :func:`.resources.check_memory`, unless
    ``force``) is validated before any work starts or anything is created.  ``out`` holds
    ``experiment.json``, ``results.jsonl`` (one row ``{"digest", "params",
    "metrics"}`` per finished configuration), ``configs/<digest>/`` (that
    configuration's experiment folder, its events moved out) and ``tensorboard/<params>/``
    (its curves and HParams session, see the module docstring).  Digests
    already in ``results.jsonl`` are skipped; its rows are appended as complete lines,
    and a torn last line (an interrupted write) is dropped with a warning and rerun.
    One sweep at a time may write ``out``: a second one raises :class:`SweepBusy`.

    Args:
        runner: runs one configuration, ``runner(cfg, out, progress=, kind=)`` →
            summary (:func:`run_experiment`; tests inject failures through it).
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
    if backend == "ray":
        _import_ray()  # fail before any work or folder if the extra is missing
    grid = {key: [getattr(base.replace(**{key: v}), key) for v in values] for key, values in grid.items()}  # 1 ≡ 1.0
    configs, digests = [], set()
    for values in itertools.product(*grid.values()):
        params = dict(zip(grid, values))
        cfg = base.replace(**params)  # validates every configuration first
        check_memory(cfg, force=force)
        if cfg.digest() not in digests:  # grid values the configuration stores alike: run once
            digests.add(cfg.digest())
            configs.append((params, cfg))
    digest = hashlib.sha256(json.dumps({"base": base.digest(), "grid": grid}, sort_keys=True).encode()).hexdigest()[:16]
    out = prepare_output(Path(out), "sweep", digest, {"base": base.to_dict(), "grid": grid})
    with _sweep_lock(out):
        return _run_pending(configs, out, progress, runner, backend, address, cpus_per_task, max_retries)


@contextmanager
def _sweep_lock(out: Path):
    """Hold ``out/.sweep.lock`` (:mod:`filelock`) for the sweep; refuse if another sweep holds it."""
    from filelock import FileLock, Timeout

    lock = FileLock(str(out / ".sweep.lock"))
    try:
        lock.acquire(timeout=0)
    except Timeout:
        raise SweepBusy(f"another agsf sweep is writing {out}; wait for it to finish (or rerun it later to resume)") from None
    try:
        yield
    finally:
        lock.release()


def _run_pending(configs, out, progress, runner, backend, address, cpus_per_task, max_retries) -> list[dict[str, Any]]:
    """Run the configurations without a row in ``results.jsonl`` (the lock held); returns all rows."""
    results = out / "results.jsonl"
    rows = repair_json_lines(results)
    done = {r["digest"] for r in rows}
    pending = [(params, cfg) for params, cfg in configs if cfg.digest() not in done]
    # names and domains from every configuration of the sweep: the same on every (resumed) run
    names = run_names((params, cfg.digest()) for params, cfg in configs)
    domains = hparam_domains(params for params, _ in configs)
    _upgrade_tensorboard(out, rows, names, domains)

    def record(params: dict[str, Any], cfg: ExperimentConfig, summary_metrics: dict[str, float]) -> None:
        run_dir = out / "tensorboard" / names[cfg.digest()]
        move_events(out / "configs" / cfg.digest() / "tensorboard", run_dir)
        write_hparams_session(run_dir, params, summary_metrics, domains)
        row = {"digest": cfg.digest(), "params": params, "metrics": summary_metrics}
        append_line(results, json.dumps(row))
        rows.append(row)

    if backend == "local":
        for params, cfg in pending:
            summary = runner(cfg, out / "configs" / cfg.digest(), progress=progress, kind="sweep-config")
            record(params, cfg, _metrics(summary))
    elif pending:
        _run_on_ray(pending, out, record, runner, address, cpus_per_task, max_retries, progress, len(configs))
    return rows


def _upgrade_tensorboard(out: Path, rows: list[dict[str, Any]], names: dict[str, str], domains) -> None:
    """Give every recorded configuration its named run, from a sweep folder of an earlier layout
    (a digest-named HParams run per configuration, an events file at the root, the curves in
    ``configs/<digest>/tensorboard``): resuming such a sweep then shows each configuration once."""
    tb = out / "tensorboard"
    for row in rows:
        digest = row.get("digest")
        if digest not in names:
            continue
        if (tb / digest).is_dir():
            shutil.rmtree(tb / digest)
        curves = out / "configs" / digest / "tensorboard"
        if not (tb / names[digest]).exists() or curves.is_dir():
            move_events(curves, tb / names[digest])
            write_hparams_session(tb / names[digest], row["params"], row["metrics"], domains)
    clear_events(tb)  # the root run of the earlier layout


# ----------------------------------------------------------------------------
# Ray backend


def _import_ray():
    try:
        import ray
    except ImportError as exc:
        raise RayUnavailable(f"the Ray sweep backend needs Ray: {RAY_INSTALL_HINT} ({exc})") from None
    return ray


def _config_on_worker(runner: Callable[..., dict[str, Any]], cfg: ExperimentConfig, threads: int) -> dict[str, Any]:
    """Body of one Ray task: run ``cfg`` into a temporary folder on the worker.

    Returns the row's metrics and the folder's files (relative path → bytes), so
    that the driver writes them: the worker needs no access to the output folder.
    """
    import torch

    torch.set_num_threads(threads)  # the task's CPUs: no oversubscription by parallel tasks
    with tempfile.TemporaryDirectory(prefix="agsf-sweep-") as tmp:
        folder = Path(tmp) / cfg.digest()
        summary = runner(cfg, folder, progress=False, kind="sweep-config")
        files = {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
    return {"metrics": _metrics(summary), "files": files}


def _write_config_folder(configs_dir: Path, digest: str, files: dict[str, bytes]) -> None:
    """Write a configuration's files to ``configs_dir/digest``, replacing a leftover of an interrupted run."""
    target = configs_dir / digest
    staging = configs_dir / f".{digest}.partial"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    for rel, data in files.items():
        if Path(rel).is_absolute() or ".." in Path(rel).parts:
            raise ValueError(f"refusing to write {rel!r} outside {target}")
        path = staging / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
    if target.exists():  # a folder without a results row: left by an interrupted run
        shutil.rmtree(target)
    staging.rename(target)


def _run_on_ray(
    pending: list[tuple[dict[str, Any], ExperimentConfig]],
    out: Path,
    record: Callable[[dict[str, Any], ExperimentConfig, dict[str, float]], None],
    runner: Callable[..., dict[str, Any]],
    address: str | None,
    cpus_per_task: int,
    max_retries: int,
    progress: bool,
    total: int,
) -> None:
    ray = _import_ray()
    from tqdm.auto import tqdm

    started = not ray.is_initialized()
    if started:
        if address is None and not os.environ.get("RAY_ADDRESS"):
            ray.init(address="local", include_dashboard=False)  # a fresh instance, never someone else's cluster
        else:
            ray.init(address=address)
    try:
        task = ray.remote(num_cpus=cpus_per_task, max_retries=max_retries, retry_exceptions=False)(_config_on_worker)
        runner_ref = ray.put(runner)
        submitted: dict[Any, tuple[dict[str, Any], ExperimentConfig]] = {}
        seen: set[str] = set()
        for params, cfg in pending:
            if cfg.digest() in seen:
                continue  # the same configuration twice in the grid: run it once
            seen.add(cfg.digest())
            submitted[task.remote(runner_ref, cfg, cpus_per_task)] = (params, cfg)
        failures: list[tuple[str, dict[str, Any], str]] = []
        waiting = list(submitted)
        bar = tqdm(total=len(waiting), desc="sweep (ray)", unit="config", disable=not progress)
        try:
            while waiting:
                ready, waiting = ray.wait(waiting, num_returns=1)
                for ref in ready:
                    params, cfg = submitted[ref]
                    try:
                        result = ray.get(ref)
                    except ray.exceptions.RayError as exc:  # the runner raised, or the worker died past its retries
                        failures.append((cfg.digest(), params, str(exc)))
                    else:
                        _write_config_folder(out / "configs", cfg.digest(), result["files"])
                        record(params, cfg, result["metrics"])
                    bar.update(1)
        finally:
            bar.close()
            for ref in waiting:  # interrupted driver: stop what is still running (a rerun redoes it)
                try:
                    ray.cancel(ref, force=True)
                except Exception:  # noqa: BLE001 - best effort; the interruption itself propagates
                    pass
        if failures:
            raise SweepFailed(failures, total)
    finally:
        if started:
            ray.shutdown()


# ----------------------------------------------------------------------------
# Results table

_RMS_SUFFIX = "/mean_rms_between_updates_deg"
_NEES_SUFFIX = "/time_averaged_nees"
_DIFFERENCE_KEY = "agsf_minus_gsf_deg"


def _table_cell(value: Any) -> str:
    """A parameter or metric as table text: strings as they are, floats in 4 significant digits,
    anything else as JSON; ``|`` escaped for Markdown."""
    if value is None:
        text = "—"
    elif isinstance(value, str):
        text = value
    elif isinstance(value, float):
        text = f"{value:.4g}"
    else:
        text = json.dumps(value)
    return text.replace("|", "\\|")


def results_table(rows: list[dict[str, Any]]) -> str:
    """A sweep's rows (``{"digest", "params", "metrics"}``, as in ``results.jsonl``) as one
    Markdown table, one line per configuration in the order of ``rows``.

    Columns: the configuration's digest (its folder ``configs/<digest>/``), every swept
    parameter, then per filter its mean RMS between star frames (deg) and its time-averaged
    NEES (dimensionless), and ``AGSF − GSF`` (deg, the paired difference of the mean RMS
    between frames) when any row has it.  A metric a row lacks is shown as ``—``.  Cells are
    padded so that the table also reads as plain text.

    Raises:
        ValueError: a row without a ``params`` or ``metrics`` mapping (named by its index).
    """
    if not rows:
        return "no finished configurations"
    for i, row in enumerate(rows):
        if not isinstance(row, dict) or not isinstance(row.get("params"), dict) or not isinstance(row.get("metrics"), dict):
            raise ValueError(f"sweep row {i} must be a mapping with 'params' and 'metrics' mappings, got {row!r}")
    params = list(dict.fromkeys(k for row in rows for k in row["params"]))
    filters = list(dict.fromkeys(
        k.split("/", 1)[0] for row in rows for k in row["metrics"] if k.endswith((_RMS_SUFFIX, _NEES_SUFFIX))
    ))
    difference = any(_DIFFERENCE_KEY in row["metrics"] for row in rows)
    header = ["config", *params]
    for name in filters:
        header += [f"{name} RMS (deg)", f"{name} NEES"]
    if difference:
        header.append("AGSF − GSF (deg)")
    body = []
    for row in rows:
        m = row["metrics"]
        cells = [_table_cell(row.get("digest")), *(_table_cell(row["params"].get(k)) for k in params)]
        for name in filters:
            cells += [_table_cell(m.get(name + _RMS_SUFFIX)), _table_cell(m.get(name + _NEES_SUFFIX))]
        if difference:
            cells.append(_table_cell(m.get(_DIFFERENCE_KEY)))
        body.append(cells)
    widths = [max(len(r[i]) for r in [header, *body]) for i in range(len(header))]

    def line(cells: list[str]) -> str:
        return "| " + " | ".join(c.ljust(w) for c, w in zip(cells, widths)) + " |"

    return "\n".join([line(header), line(["-" * w for w in widths]), *(line(r) for r in body)])
