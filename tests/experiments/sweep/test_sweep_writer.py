"""A local sweep writes each configuration's files beside the next configuration's run (agsf_torch.experiments.sweep
with agsf_torch.experiments.run.file_writer, one worker process where there are 2 CPUs or more): the same rows and files
as without a writer, each row appended only once its configuration's files are complete, a reused filter read only
once written."""

from __future__ import annotations

import pytest

from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run import file_writer
from agsf_torch.experiments.run.experiment import run_experiment
from agsf_torch.experiments.run.file_writer import HANDOVER_BYTES, WORKER_MEMORY
from agsf_torch.experiments.run.resources import RETAINED_OVERHEAD, estimated_memory, writer_memory
from agsf_torch.experiments.sweep import run as sweep_run
from agsf_torch.experiments.sweep import run_sweep
from agsf_torch.storage.files import read_json_lines
from tests.helpers import EAGER, event_records, file_digests

TINY = ["runs=2", "duration=0.5", "components=2", *EAGER, 'filters=["EKF","GSF","AGSF"]']
#: Over reg: the EKF and the GSF run once (first configuration), the AGSF for every value.
GRID = {"reg": [0.5, 1.0, 2.0]}


def _writers(monkeypatch, writers: int) -> None:
    """Run the sweeps with ``writers`` worker processes (by default one where there are 2 CPUs or more)."""
    monkeypatch.setattr(file_writer, "default_writers", lambda: writers)


def test_a_sweep_writes_the_same_rows_and_files_with_a_writer_as_without(tmp_path, monkeypatch):
    base = load_config("case1", TINY)
    rows = {}
    for w in (0, 1):
        _writers(monkeypatch, w)
        rows[w] = run_sweep(base, GRID, tmp_path / str(w), progress=False)
    assert rows[0] == rows[1]
    assert read_json_lines(tmp_path / "0" / "results.jsonl") == read_json_lines(tmp_path / "1" / "results.jsonl")
    assert file_digests(tmp_path / "1" / "configs") == file_digests(tmp_path / "0" / "configs")
    assert event_records(tmp_path / "1" / "tensorboard") == event_records(tmp_path / "0" / "tensorboard")


def test_a_row_is_appended_once_its_files_are_complete_and_a_reused_filter_is_read_once_written(tmp_path, monkeypatch):
    base = load_config("case1", TINY)
    out = tmp_path / "sweep"
    appended, started = [], []
    append_line = sweep_run.append_line

    def checked_append(path, line):
        digest = line.split('"digest": "')[1].split('"')[0]
        folder = out / "configs" / digest
        assert {"runs.npz", "summary.json", "rms.png", "axes.png", "weights.png", "fpke.png"} <= {
            p.name for p in folder.iterdir()
        }
        assert not (folder / "tensorboard").exists()  # its events moved to the sweep's TensorBoard run
        assert not list(folder.rglob(".*.tmp"))
        appended.append(digest)
        append_line(path, line)

    def runner(cfg, folder, **kw):
        for source in kw.get("reuse", {}).values():  # what it copies is whole, and recorded
            assert (source / "runs.npz").is_file() and source.name in appended
        started.append(cfg.digest())
        return run_experiment(cfg, folder, **kw)

    monkeypatch.setattr(sweep_run, "append_line", checked_append)
    _writers(monkeypatch, 1)
    run_sweep(base, GRID, out, progress=False, runner=runner)
    assert appended == started and len(appended) == 3


def test_a_configuration_that_fails_leaves_the_previous_one_recorded(tmp_path, monkeypatch):
    base = load_config("case1", TINY)
    _writers(monkeypatch, 1)
    calls = []

    def failing_second(cfg, folder, **kw):
        calls.append(cfg.reg)
        if len(calls) == 2:
            raise ZeroDivisionError("the second configuration fails")
        return run_experiment(cfg, folder, **kw)

    with pytest.raises(ZeroDivisionError):
        run_sweep(base, GRID, tmp_path / "sweep", progress=False, runner=failing_second)
    rows = read_json_lines(tmp_path / "sweep" / "results.jsonl")
    assert [r["params"]["reg"] for r in rows] == [0.5]


def test_the_memory_a_run_shares_with_the_writer():
    small = load_config("case1", TINY)
    assert writer_memory(small, 0) == 0
    assert writer_memory(small, 2) == 2 * WORKER_MEMORY  # its arrays go to a worker
    large = load_config("case1", ["runs=4096", "duration=300"])
    arrays = estimated_memory(large).retained // RETAINED_OVERHEAD
    assert arrays > HANDOVER_BYTES  # so a thread of the caller holds them beside the next run
    assert writer_memory(large, 1) == WORKER_MEMORY + arrays


def test_threads_are_the_local_backends(tmp_path):
    """(The ``--writers`` flag is gone: ``test_reproduce_jobs``.)"""
    base = load_config("case1", TINY)
    with pytest.raises(ValueError, match="local backend"):
        run_sweep(base, GRID, tmp_path / "r", progress=False, backend="ray", threads=2)
    with pytest.raises(ValueError, match="threads must be a positive integer or None, got -1"):
        run_sweep(base, GRID, tmp_path / "w", progress=False, threads=-1)
    assert not any((tmp_path / name).exists() for name in ("r", "w"))


def test_without_a_worker_a_configuration_is_recorded_before_the_next_one_runs(tmp_path, monkeypatch):
    """Nothing is written in the background: a crash in the next configuration loses nothing recorded."""
    base = load_config("case1", TINY)
    _writers(monkeypatch, 0)
    out = tmp_path / "sweep"
    rows_seen = []

    def runner(cfg, folder, **kw):
        rows_seen.append(len(read_json_lines(out / "results.jsonl")) if (out / "results.jsonl").exists() else 0)
        return run_experiment(cfg, folder, **kw)

    run_sweep(base, GRID, out, progress=False, runner=runner)
    assert rows_seen == [0, 1, 2]


def _latched_sweep(tmp_path, monkeypatch, on_wait):
    """Run the sweep of ``GRID`` with a latch (a Ctrl-C Python dropped inside a finaliser) that ``on_wait(folder,
    latch)`` may set after each wait for a configuration's files; return the runner's calls."""
    import threading
    from contextlib import contextmanager

    from agsf_torch.experiments.run.file_writer import FileWriter

    latch, calls = threading.Event(), []

    @contextmanager
    def fake_latch():
        yield latch

    wait_for = FileWriter.wait_for

    def waiting(self, folder):
        wait_for(self, folder)
        on_wait(folder, latch)

    def runner(cfg, folder, **kw):
        calls.append(cfg.reg)
        return run_experiment(cfg, folder, **kw)

    monkeypatch.setattr(sweep_run, "_interrupt_latch", fake_latch)
    monkeypatch.setattr(FileWriter, "wait_for", waiting)
    _writers(monkeypatch, 1)
    run_sweep(load_config("case1", TINY), GRID, tmp_path / "sweep", progress=False, runner=runner)
    return calls


def test_a_ctrl_c_swallowed_while_a_reused_configuration_is_recorded_stops_the_sweep_before_the_next(
    tmp_path, monkeypatch
):
    """The second configuration reuses the first's filters, so it waits for the first's files: a Ctrl-C dropped
    meanwhile stops the sweep there, the second never started."""
    calls = []
    with pytest.raises(KeyboardInterrupt):
        calls = _latched_sweep(tmp_path, monkeypatch, lambda folder, latch: latch.set())
    rows = read_json_lines(tmp_path / "sweep" / "results.jsonl")
    assert [r["params"]["reg"] for r in rows] == [0.5] and calls == []  # (the runner's calls are lost with the raise)
    assert len(list((tmp_path / "sweep" / "configs").iterdir())) == 1


def test_a_ctrl_c_swallowed_while_the_last_files_are_written_finds_the_sweep_complete(tmp_path, monkeypatch):
    """Every configuration has run and is recorded: the sweep ends as it would have a moment later."""
    waits = []

    def late(folder, latch):
        waits.append(folder)
        if len(waits) == 3:  # the first (reused by the second), the second (after the third ran), the third: the last
            latch.set()

    calls = _latched_sweep(tmp_path, monkeypatch, late)
    assert calls == [0.5, 1.0, 2.0] and len(waits) == 3
    assert len(read_json_lines(tmp_path / "sweep" / "results.jsonl")) == 3


def test_the_previous_configurations_failed_files_do_not_hide_the_failure_of_the_next(tmp_path, monkeypatch, caplog):
    from agsf_torch.experiments.run.file_writer import FileWriter

    def failing_wait(self, folder):
        raise OSError(28, "No space left on device", str(folder / "rms.png"))

    def runner(cfg, folder, **kw):
        if cfg.reg == 1.0:
            raise KeyboardInterrupt
        return run_experiment(cfg, folder, **kw)

    monkeypatch.setattr(FileWriter, "wait_for", failing_wait)
    _writers(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt):
        base = load_config("case1", [*TINY[:-1], 'filters=["AGSF"]'])  # nothing reused: the next one runs at once
        run_sweep(base, {"reg": [0.5, 1.0]}, tmp_path / "sweep", progress=False, runner=runner)
    assert "No space left on device" in caplog.text  # logged, not raised over the interruption
    assert not (tmp_path / "sweep" / "results.jsonl").exists()  # its files failed: not recorded
