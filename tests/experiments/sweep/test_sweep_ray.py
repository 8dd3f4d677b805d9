"""The Ray sweep backend against the local one: the same rows (bit for bit) and per-configuration
files for the same seeds; a failed task keeps every other configuration and a rerun runs only the
failed one; a worker that dies is retried; an interrupted driver keeps what finished, also when Python swallowed the Ctrl-C; CLI checks.

Every Ray check runs inside one test function on one local Ray instance (``num_cpus=2``): under
pytest-xdist the tests of a module may land on different workers, and each would start its own
instance (``xdist_group`` cannot keep them together: pytest-xdist 3.8's ``loadgroup`` has no effect
under pytest 9.2)."""

from __future__ import annotations

import contextlib
import functools
import io
import json
import os
import sys
from pathlib import Path

import numpy as np
import pytest

from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.report.tensorboard import run_name
from agsf_torch.experiments.run.experiment import run_experiment
from agsf_torch.experiments.sweep import RayUnavailable, SweepFailed, parse_grid, run_sweep
from tests.helpers import EAGER

BASE = ["runs=4", "duration=1.0", *EAGER, "components=2", 'filters=["GSF", "AGSF"]']
GRID = ["reg=0.1,1.0", "scaling=trace,none"]


def marking_runner(cfg, out, *, marks: str, fail: str | None = None, crash_once: str | None = None, **kw):
    """``run_experiment`` that leaves a file per call in ``marks`` (the calls happen on Ray workers);
    raises for the digest ``fail``; kills its worker process on the first call for ``crash_once``."""
    folder = Path(marks)
    folder.mkdir(parents=True, exist_ok=True)
    calls = len(list(folder.glob(f"{cfg.digest()}.*")))
    (folder / f"{cfg.digest()}.{calls}").touch()
    if cfg.digest() == fail:
        raise RuntimeError("injected failure")
    if cfg.digest() == crash_once and calls == 0:
        os._exit(1)  # the worker dies: a system failure, retried by Ray
    return run_experiment(cfg, out, **kw)


def calls(marks: Path) -> dict[str, int]:
    found: dict[str, int] = {}
    for p in marks.glob("*.*") if marks.exists() else []:
        found[p.stem] = found.get(p.stem, 0) + 1
    return found


def by_digest(rows):
    return {r["digest"]: r for r in rows}


def metrics(rows):
    """digest → metrics (a sub-grid names fewer params than the local grid, its metrics are the same)"""
    return {r["digest"]: r["metrics"] for r in rows}


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # a swallowed Ctrl-C (checked)
def test_ray_backend(tmp_path, monkeypatch):
    """One local Ray instance for every check below (see the module docstring)."""
    # Ray on Linux puts even a local instance on the machine's network address; this keeps it on loopback
    # (read when ray is imported: this module is the only one that imports it)
    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    ray = pytest.importorskip("ray")  # the ray extra (scripts/setup_env.sh installs it)
    local_out = tmp_path / "local"
    local_rows = by_digest(run_sweep(load_config("case1", BASE), parse_grid(GRID), local_out, progress=False))
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        assert [n["NodeManagerAddress"] for n in ray.nodes()] == ["127.0.0.1"]
        check_rows_and_files_equal_local(local_out, local_rows, tmp_path / "equal")
        check_failed_task_keeps_the_others_and_the_rerun_runs_only_it(local_rows, tmp_path / "failed")
        check_interrupted_driver_keeps_what_finished(ray, local_rows, tmp_path / "interrupted")
        check_a_ctrl_c_swallowed_in_the_driver_still_stops_it(local_rows, tmp_path / "swallowed")
    finally:
        ray.shutdown()


def check_rows_and_files_equal_local(local_out, local_rows, tmp_path):
    out = tmp_path / "sweep"
    rows = run_sweep(load_config("case1", BASE), parse_grid(GRID), out, progress=False, backend="ray")
    assert len(rows) == 4 and len(local_rows) == 4
    # params and every metric, exactly; the local backend reused the GSF (it reads neither reg nor scaling)
    # where the Ray backend ran every configuration whole: the numbers are the same
    assert sum("reused" in r for r in local_rows.values()) == 3 and not any("reused" in r for r in rows)
    whole = {d: {k: v for k, v in r.items() if k != "reused"} for d, r in local_rows.items()}
    assert by_digest(rows) == whole
    assert by_digest(json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()) == whole
    for digest in local_rows:
        mine, theirs = out / "configs" / digest, local_out / "configs" / digest
        names = sorted(
            p.relative_to(mine).as_posix() for p in mine.rglob("*") if p.is_file() and "tensorboard" not in p.parts
        )
        assert names == sorted(
            p.relative_to(theirs).as_posix() for p in theirs.rglob("*") if p.is_file() and "tensorboard" not in p.parts
        )
        ours = json.loads((theirs / "summary.json").read_text())
        ours.pop("reused", None)
        assert ours["label"] == f"case1 {run_name(local_rows[digest]['params'])}"  # the figures' titles name it
        assert json.loads((mine / "summary.json").read_text()) == ours
        a, b = np.load(mine / "runs.npz"), np.load(theirs / "runs.npz")
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
        assert not (mine / "tensorboard").exists()  # its events moved to the run named by its parameters
        assert list((out / "tensorboard" / run_name(local_rows[digest]["params"])).glob("events.out.tfevents.*"))
    # one run (curves + HParams session) per configuration, named by its parameters
    assert {p.name for p in (out / "tensorboard").iterdir()} == {run_name(r["params"]) for r in local_rows.values()}
    assert not list((out / "configs").glob(".*"))  # no staging folder left


def check_failed_task_keeps_the_others_and_the_rerun_runs_only_it(local_rows, tmp_path):
    base, grid = load_config("case1", BASE), parse_grid(["reg=0.1,1.0"])  # two of the local configurations
    digests = [base.replace(reg=r).digest() for r in (0.1, 1.0)]
    failing, crashing = digests
    out, first, second = tmp_path / "sweep", tmp_path / "marks1", tmp_path / "marks2"
    runner = functools.partial(marking_runner, marks=str(first), fail=failing, crash_once=crashing)
    with pytest.raises(SweepFailed) as err:
        run_sweep(base, grid, out, progress=False, backend="ray", runner=runner)
    assert [f[0] for f in err.value.failures] == [failing]
    assert failing in str(err.value) and "injected failure" in str(err.value) and '"reg": 0.1' in str(err.value)
    assert calls(first) == {failing: 1, crashing: 2}  # the dead worker's task ran again
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert metrics(rows) == {crashing: local_rows[crashing]["metrics"]}
    assert sorted(p.name for p in (out / "configs").iterdir()) == [crashing]

    rerun = run_sweep(
        base, grid, out, progress=False, backend="ray", runner=functools.partial(marking_runner, marks=str(second))
    )
    assert calls(second) == {failing: 1}
    assert len(rerun) == 2 and metrics(rerun) == {d: local_rows[d]["metrics"] for d in digests}


def check_interrupted_driver_keeps_what_finished(ray, local_rows, tmp_path):
    base, grid = load_config("case1", BASE), parse_grid(["scaling=trace,none"])
    out = tmp_path / "sweep"
    waits = []

    def interrupted_wait(*args, **kwargs):  # Ctrl-C in the driver after the first configuration is in
        if waits:
            raise KeyboardInterrupt
        waits.append(1)
        return real_wait(*args, **kwargs)

    real_wait = ray.wait
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ray, "wait", interrupted_wait)
        with pytest.raises(KeyboardInterrupt):
            run_sweep(base, grid, out, progress=False, backend="ray")
    assert len((out / "results.jsonl").read_text().splitlines()) == 1
    assert len(list((out / "configs").iterdir())) == 1  # the cancelled configuration left no folder
    # through the CLI (on the running Ray instance): Ctrl-C again at once, then the rerun
    args = ["sweep", "case1", *sum((["--set", s] for s in BASE), []), "--grid", "scaling=trace,none"]
    args += ["--out", str(out), "--backend", "ray", "--quiet"]
    stderr = io.StringIO()
    with pytest.MonkeyPatch.context() as mp, contextlib.redirect_stderr(stderr):
        mp.setattr(ray, "wait", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt))
        assert cli.main(args) == 130
    assert "1 finished configurations" in stderr.getvalue() and "rerun the same command" in stderr.getvalue()
    assert cli.main(args) == 0  # adds only the missing configuration
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    digests = [base.replace(scaling=s).digest() for s in ("trace", "none")]
    assert len(rows) == 2 and metrics(rows) == {d: local_rows[d]["metrics"] for d in digests}


def test_cli_address_needs_ray_backend(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert cli.main(["sweep", "case1", "--grid", "reg=0.1,1.0", "--address", "auto", "--out", str(out)]) == 2
    assert "--address needs --backend ray" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(ValueError, match="backend"):
        run_sweep(load_config("case1", BASE), parse_grid(["reg=0.1"]), out, backend="dask")
    with pytest.raises(ValueError, match="backend='ray'"):
        run_sweep(load_config("case1", BASE), parse_grid(["reg=0.1"]), out, address="auto")
    assert not out.exists()


def test_missing_ray_names_the_extra(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` raises ImportError
    out = tmp_path / "sweep"
    with pytest.raises(RayUnavailable, match=r"agsf-torch\[ray\]"):
        run_sweep(load_config("case1", BASE), parse_grid(["reg=0.1"]), out, backend="ray")
    assert cli.main(["sweep", "case1", "--grid", "reg=0.1", "--backend", "ray", "--out", str(out)]) == 1
    assert "agsf-torch[ray]" in capsys.readouterr().err
    assert not out.exists()


def check_a_ctrl_c_swallowed_in_the_driver_still_stops_it(local_rows, tmp_path):
    """A Ctrl-C delivered while a finaliser runs in the driver is dropped by Python ("Exception ignored
    in: …"); the sweep's latch stops the driver after the row it was recording, as the local backend does."""
    import signal

    from agsf_torch.experiments.sweep import ray_backend

    class Finaliser:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)  # delivered while __del__ runs: the KeyboardInterrupt is dropped

    real_write = ray_backend._write_config_folder

    def write_then_swallow(*args, **kwargs):
        real_write(*args, **kwargs)
        obj = Finaliser()
        del obj

    base, grid = load_config("case1", BASE), parse_grid(["scaling=trace,none"])
    out = tmp_path / "sweep"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(ray_backend, "_write_config_folder", write_then_swallow)
        with pytest.raises(KeyboardInterrupt):
            run_sweep(base, grid, out, progress=False, backend="ray")
    rows = [json.loads(line) for line in (out / "results.jsonl").read_text().splitlines()]
    assert len(rows) == 1 and rows[0]["metrics"] == local_rows[rows[0]["digest"]]["metrics"]
    rerun = run_sweep(base, grid, out, progress=False, backend="ray")  # the latch is gone: the rest runs
    digests = [base.replace(scaling=s).digest() for s in ("trace", "none")]
    assert metrics(rerun) == {d: local_rows[d]["metrics"] for d in digests}
