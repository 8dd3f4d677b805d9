"""The Ray backend of ``agsf sweep``: one Ray task per configuration, the driver the only writer of the folder."""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ...allocator import set_mmap_threshold
from ..config.loader import ExperimentConfig
from .rows import config_metrics

__all__ = ["SweepFailed", "RayUnavailable", "RAY_INSTALL_HINT", "import_ray", "run_on_ray"]

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
        lines = [
            f"{len(failures)} of {total} sweep configurations failed (the others are recorded; a rerun runs only these):"
        ]
        for digest, params, message in failures:
            first = message.strip().splitlines()[-1] if message.strip() else "(no message)"
            lines.append(f"  {digest} {json.dumps(params, sort_keys=True)}: {first}")
        super().__init__("\n".join(lines))


class RayUnavailable(ImportError):
    """``backend="ray"`` without Ray installed."""


def import_ray():
    try:
        import ray
    except ImportError as exc:
        raise RayUnavailable(f"the Ray sweep backend needs Ray: {RAY_INSTALL_HINT} ({exc})") from None
    return ray


def _config_on_worker(
    runner: Callable[..., dict[str, Any]], cfg: ExperimentConfig, threads: int, label: str | None = None
) -> dict[str, Any]:
    """Body of one Ray task: run ``cfg`` into a temporary folder on the worker.

    Returns the row's metrics and the folder's files (relative path → bytes), so
    that the driver writes them: the worker needs no access to the output folder.
    """
    import torch

    from ..run.outputs import release_outputs

    torch.set_num_threads(threads)  # the task's CPUs: no oversubscription by parallel tasks
    set_mmap_threshold()  # as the agsf command does: a step's buffers reused from the heap
    with tempfile.TemporaryDirectory(prefix="agsf-sweep-") as tmp:
        folder = Path(tmp) / cfg.digest()
        try:
            summary = runner(cfg, folder, progress=False, kind="sweep-config", label=label)
        finally:
            release_outputs()  # the worker process outlives the task: let go of the folder
        files = {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}
    return {"metrics": config_metrics(summary), "files": files}


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


def run_on_ray(
    pending: list[tuple[dict[str, Any], ExperimentConfig]],
    out: Path,
    record: Callable[[dict[str, Any], ExperimentConfig, dict[str, float]], None],
    runner: Callable[..., dict[str, Any]],
    address: str | None,
    cpus_per_task: int,
    max_retries: int,
    progress: bool,
    total: int,
    interrupted: threading.Event | None = None,
    labels: dict[str, str] | None = None,
) -> None:
    """Run ``pending`` as one Ray task per distinct configuration, ``record`` each result as it arrives.

    ``interrupted``: a latch of Ctrl-C (set by the caller's SIGINT handler); checked after every
    recorded row, so that a ``KeyboardInterrupt`` Python swallowed (raised inside a finaliser) still
    stops the driver — the tasks still running are cancelled, what finished is kept.  ``labels``: each
    configuration's label by digest (the runner's ``label``: its figures' title).

    Raises:
        SweepFailed: some configurations failed (every other one is recorded).
        KeyboardInterrupt: Ctrl-C in the driver.
    """
    ray = import_ray()
    from ..run.progress import progress_bar

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
            label = (labels or {}).get(cfg.digest())
            submitted[task.remote(runner_ref, cfg, cpus_per_task, label)] = (params, cfg)
        failures: list[tuple[str, dict[str, Any], str]] = []
        waiting = list(submitted)
        bar = progress_bar(desc="sweep (ray)", unit="config", total=len(waiting), disable=not progress)
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
                        record(params, cfg, result["metrics"], {})  # every task runs its configuration whole
                    bar.update(1)
                if interrupted is not None and interrupted.is_set():
                    raise KeyboardInterrupt
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
