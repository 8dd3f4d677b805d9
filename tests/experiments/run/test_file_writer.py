"""Writing files in worker processes (agsf_torch.experiments.run.file_writer) and reproduce's use of it."""

from __future__ import annotations

import errno
import io
import os
import threading
import time
from pathlib import Path

import pytest
import torch

from agsf_torch.experiments.run.file_writer import FileWriter
from agsf_torch.experiments.run.worker_pool import TaskDied, fork_available
from agsf_torch.experiments.studies.reproduce import reproduce
from agsf_torch.storage.files import write_text
from tests.helpers import EAGER, event_records, file_digests

needs_fork = pytest.mark.skipif(not fork_available(), reason="worker processes are forked (Linux)")


def write_unless_in_a_worker(path: Path, text: str, caller: int) -> None:
    """Write ``text`` to ``path`` in the process ``caller``; in any other process, die without a word."""
    if os.getpid() != caller:
        os._exit(3)
    write_text(path, text)


def write_pid(path: Path) -> None:
    """Write the writing process's id to ``path``."""
    write_text(path, str(os.getpid()))


def write_slowly(path: Path, seconds: float) -> None:
    """Leave ``path``'s temporary file, wait ``seconds``, then write ``path`` (a writer killed meanwhile leaves the
    temporary file behind)."""
    Path(path).with_name(f".{Path(path).name}.0123456789ab.tmp").write_text("partial")
    time.sleep(seconds)
    write_text(path, "slow")


def write_imported(path: Path, module: str) -> None:
    """Write whether ``module`` is imported in the writing process."""
    import sys

    write_text(path, str(module in sys.modules))


def test_without_workers_a_task_runs_when_submitted(tmp_path):
    with FileWriter(0) as writer:
        assert not writer.background
        writer.submit(write_text, tmp_path / "a.txt", "alpha", path=tmp_path / "a.txt")
        assert (tmp_path / "a.txt").read_text() == "alpha"


@needs_fork
def test_workers_write_every_file_by_close(tmp_path):
    files = {tmp_path / f"f{i}.txt": f"text {i}" for i in range(7)}
    writer = FileWriter(2, preload=())
    assert writer.background
    for path, text in files.items():
        writer.submit(write_text, path, text, path=path)
    writer.close()
    assert {p: p.read_text() for p in files} == files


@needs_fork
def test_workers_start_after_a_message_went_through_tqdm(tmp_path):
    """A log message during the command (``tqdm.write``, e.g. the FPKE kernel's compilation) gives tqdm's base class
    its lock; the workers forked after it drop that lock and start (they used to die in their initializer)."""
    from tqdm import tqdm

    tqdm.write("a message", file=io.StringIO())
    files = {tmp_path / f"m{i}.txt": f"text {i}" for i in range(3)}
    with FileWriter(2, preload=()) as writer:
        for path, text in files.items():
            writer.submit(write_text, path, text, path=path)
    assert {p: p.read_text() for p in files} == files


@needs_fork
def test_the_tasks_run_in_the_workers_one_torch_thread_each_and_the_preloaded_modules_imported(tmp_path):
    import sys

    paths = [tmp_path / f"p{i}.txt" for i in range(4)]
    sys.modules.pop("tabnanny", None)
    with FileWriter(2, preload=("tabnanny",)) as writer:
        for path in paths:
            writer.submit(write_pid, path, path=path)
        writer.submit(write_imported, tmp_path / "imported", "tabnanny", path=tmp_path / "imported")
    pids = {int(p.read_text()) for p in paths}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2
    assert (tmp_path / "imported").read_text() == "True" and "tabnanny" not in sys.modules


@needs_fork
def test_a_worker_takes_the_tasks_in_the_order_submitted(tmp_path):
    paths = [tmp_path / f"o{i}.txt" for i in range(5)]
    with FileWriter(1, preload=()) as writer:
        for path in paths:
            writer.submit(write_pid, path, path=path)
    pids = {int(p.read_text()) for p in paths}
    assert len(pids) == 1 and os.getpid() not in pids
    times = [p.stat().st_mtime_ns for p in paths]
    assert times == sorted(times)


def fill_the_disk(path: Path) -> None:
    """Fail as a write to a full disk does."""
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def write_in_thread(path: Path, main: int) -> None:
    """Write whether this runs in the thread ``main`` (``"main"``) or another (``"thread"``), and the process id."""
    write_text(path, f"{'main' if threading.get_ident() == main else 'thread'} {os.getpid()}")


@needs_fork
def test_a_thread_task_runs_in_a_thread_of_the_caller_and_is_complete_at_close(tmp_path):
    path, bad = tmp_path / "t.txt", tmp_path / "missing-folder" / "u.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_in_thread, path, threading.get_ident(), path=path, thread=True)
    writer.submit(write_in_thread, bad, threading.get_ident(), path=bad, thread=True)
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*missing-folder/\.u\.txt\."):
        writer.close()
    assert path.read_text() == f"thread {os.getpid()}"


def test_without_workers_a_thread_task_runs_when_submitted(tmp_path):
    with FileWriter(0) as writer:
        writer.submit(write_in_thread, tmp_path / "v.txt", threading.get_ident(), path=tmp_path / "v.txt", thread=True)
        assert (tmp_path / "v.txt").read_text() == f"main {os.getpid()}"


@needs_fork
def test_an_error_in_the_block_lets_the_workers_finish_what_they_were_handed(tmp_path):
    path = tmp_path / "g.txt"
    with pytest.raises(ZeroDivisionError):
        with FileWriter(1, preload=()) as writer:
            writer.submit(write_slowly, path, 0.5, path=path)
            1 / 0
    assert path.read_text() == "slow"  # an earlier case's files are complete whatever a later case does


@needs_fork
def test_an_interruption_stops_the_workers_and_leaves_no_temporary_file(tmp_path):
    path, queued = tmp_path / "h.txt", tmp_path / "queued.txt"
    with pytest.raises(KeyboardInterrupt):
        with FileWriter(1, preload=()) as writer:
            writer.submit(write_slowly, path, 30.0, path=path)
            for k in range(3):
                writer.submit(write_text, queued, str(k), path=queued)
            deadline = time.monotonic() + 30.0
            while not list(tmp_path.glob(".h.txt.*.tmp")) and time.monotonic() < deadline:
                time.sleep(0.01)  # until the worker has started the file
            assert list(tmp_path.glob(".h.txt.*.tmp"))
            procs = list(writer._pool.processes)
            t0 = time.monotonic()
            raise KeyboardInterrupt
    assert time.monotonic() - t0 < 10  # the running task interrupted, the others not started
    assert sorted(p.name for p in tmp_path.iterdir()) == []
    assert all(proc.exitcode is not None for proc in procs)


@needs_fork
def test_a_worker_that_dies_is_named_with_its_file_and_exit_code(tmp_path):
    path = tmp_path / "i.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_unless_in_a_worker, path, "iota", os.getpid(), path=path)
    with pytest.raises(TaskDied, match=r"^the process writing .*i\.txt ended without a reply \(exit code 3\)$"):
        writer.close()


def fail_to_draw(path: Path) -> None:
    """A task that fails without an I/O error."""
    raise ValueError(f"nothing to draw for {path.name}")


def divide_by_zero(path: Path) -> None:
    """A task that fails with neither an I/O error nor a ValueError."""
    1 / 0


@needs_fork
def test_a_failed_task_is_raised_as_the_caller_would_have_raised_it_the_first_in_order(tmp_path):
    """A ValueError as a ValueError (``agsf``: one line, exit 2, as when the caller draws the figure itself), any
    other failure as itself, the first submitted first, once the others are written."""
    writer = FileWriter(1, preload=())
    writer.submit(fail_to_draw, tmp_path / "n.png", path=tmp_path / "n.png")
    writer.submit(divide_by_zero, tmp_path / "o.png", path=tmp_path / "o.png")
    writer.submit(write_text, tmp_path / "p.txt", "pi", path=tmp_path / "p.txt")
    with pytest.raises(ValueError, match=r"^nothing to draw for n\.png$") as failure:
        writer.close()
    assert "fail_to_draw" in str(failure.value.__cause__)  # the worker's traceback
    assert (tmp_path / "p.txt").read_text() == "pi"
    with pytest.raises(ZeroDivisionError):
        with FileWriter(1, preload=()) as writer:
            writer.submit(divide_by_zero, tmp_path / "r.png", path=tmp_path / "r.png")


@needs_fork
def test_an_io_failure_in_a_worker_is_an_os_error_with_its_errno_as_when_written_here(tmp_path):
    """A full disk in a worker is reported as one (``agsf``: exit 3, "I/O failure"), as a write in the caller is."""
    path = tmp_path / "p.txt"
    with pytest.raises(OSError) as failure:
        with FileWriter(1, preload=()) as writer:
            writer.submit(fill_the_disk, path, path=path)
    assert failure.value.errno == errno.ENOSPC and failure.value.filename == str(path)
    assert failure.value.strerror == os.strerror(errno.ENOSPC)


@needs_fork
def test_a_task_that_cannot_be_handed_over_fails_and_the_others_are_written(tmp_path):
    writer = FileWriter(1, preload=())
    writer.submit(lambda p: write_text(p, "lambda"), tmp_path / "l.txt", path=tmp_path / "l.txt")
    writer.submit(write_text, tmp_path / "m.txt", "mu", path=tmp_path / "m.txt")
    with pytest.raises(Exception, match="pickle"):
        writer.close()
    assert (tmp_path / "m.txt").read_text() == "mu" and not (tmp_path / "l.txt").exists()


@pytest.mark.parametrize("workers", [0, 1])
def test_a_closed_writer_refuses_tasks(tmp_path, workers):
    writer = FileWriter(workers, preload=())
    writer.close()
    writer.close()  # closing again does nothing
    with pytest.raises(ValueError, match=r"cannot write .*f\.txt: this FileWriter is closed"):
        writer.submit(write_text, tmp_path / "f.txt", "zeta", path=tmp_path / "f.txt")
    assert not (tmp_path / "f.txt").exists()


@pytest.mark.parametrize("workers", [-1, 1.5, True, "2"])
def test_bad_worker_counts_are_refused(workers):
    with pytest.raises(ValueError, match="workers must be a non-negative integer"):
        FileWriter(workers)


@needs_fork
def test_reproduce_writes_the_same_files_with_a_writer_as_without_and_restores_the_threads(tmp_path, monkeypatch):
    from agsf_torch.experiments.run import file_writer

    overrides = ["runs=3", "duration=2.0", "components=2", *EAGER]
    threads = torch.get_num_threads()
    tables = {}
    for writers in (0, 1):
        monkeypatch.setattr(file_writer, "default_writers", lambda: writers)
        tables[writers] = reproduce(
            [1, 3], tmp_path / str(writers), overrides, progress=False, jobs=1, threads=threads + 1
        )
        assert torch.get_num_threads() == threads
    assert tables[0] == tables[1]
    inline, written = file_digests(tmp_path / "0"), file_digests(tmp_path / "1")
    for case in ("case1", "case3"):
        assert {f"{case}/{name}" for name in ("runs.npz", "rms.png", "axes.png", "weights.png", "fpke.png")} <= set(
            inline
        )
    assert written == inline
    assert event_records(tmp_path / "1") == event_records(tmp_path / "0")


@pytest.mark.parametrize("value", [0, 1.5, True])
def test_reproduce_refuses_bad_thread_counts_before_creating_anything(tmp_path, value):
    with pytest.raises(ValueError, match="threads must be"):
        reproduce([1], tmp_path / "out", list(EAGER), progress=False, jobs=1, threads=value)
    assert not (tmp_path / "out").exists()


class _Submissions:
    """A stand-in for a FileWriter that records how each task was submitted."""

    def __init__(self):
        self.calls = []

    def submit(self, write, *args, path, thread=False):
        self.calls.append((Path(path).name, thread))


@pytest.mark.parametrize(("limit", "thread"), [(2**40, False), (1, True)])
def test_runs_npz_goes_to_a_worker_unless_its_arrays_exceed_the_handover_limit(tmp_path, monkeypatch, limit, thread):
    import numpy as np

    from agsf_torch.experiments.run import file_writer, outputs

    reused = {
        "GSF": ({"time": np.arange(3.0), "star_frame": np.zeros(3, bool), "GSF/error_angle": np.ones((2, 3))}, {})
    }
    monkeypatch.setattr(file_writer, "HANDOVER_BYTES", limit)
    writer = _Submissions()
    data = outputs.save_runs(tmp_path / "runs.npz", None, reused, writer)
    assert writer.calls == [("runs.npz", thread)] and set(data) == {"time", "star_frame", "GSF/error_angle"}
    assert not (tmp_path / "runs.npz").exists()  # the writer's to write


@needs_fork
def test_an_interrupted_close_stops_the_workers_and_closing_again_does_nothing(tmp_path, monkeypatch):
    paths = [tmp_path / f"y{i}.txt" for i in range(3)]
    writer = FileWriter(1, preload=())
    writer.submit(write_slowly, paths[0], 30.0, path=paths[0])
    for path in paths[1:]:
        writer.submit(write_text, path, "queued", path=path)

    def interrupted(self, futures):
        raise KeyboardInterrupt

    monkeypatch.setattr(FileWriter, "_finish", interrupted)
    procs = list(writer._pool.processes)
    with pytest.raises(KeyboardInterrupt):
        writer.close()  # the caller is interrupted while it waits
    writer.close()
    assert all(proc.exitcode is not None for proc in procs)
    assert not any(p.exists() for p in paths) and not list(tmp_path.glob(".*.tmp"))


def write_slowly_here(path: Path, seconds: float) -> None:
    """Wait ``seconds``, then write ``path``."""
    time.sleep(seconds)
    write_text(path, "slow")


@needs_fork
def test_thread_tasks_run_one_at_a_time_and_an_interruption_completes_the_one_running(tmp_path):
    first, second = tmp_path / "z1.txt", tmp_path / "z2.txt"
    with pytest.raises(KeyboardInterrupt):
        with FileWriter(1, preload=()) as writer:
            writer.submit(write_slowly_here, first, 0.5, path=first, thread=True)
            writer.submit(write_slowly_here, second, 0.5, path=second, thread=True)
            assert first.read_text() == "slow"  # the second waited for the first: one case's arrays held at a time
            raise KeyboardInterrupt
    assert second.read_text() == "slow"  # completed, not left half written


def write_when_opened(path: Path, gate: Path) -> None:
    """Write ``path`` once the file ``gate`` exists (at most a minute later)."""
    deadline = time.monotonic() + 60.0
    while not gate.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    write_text(path, "gated")


@needs_fork
def test_wait_for_a_folder_leaves_the_other_tasks_running_and_raises_only_its_own_failures(tmp_path):
    """A sweep records one configuration (its folder complete) while the next one's files are still written."""
    mine, other = tmp_path / "a", tmp_path / "b"
    mine.mkdir()
    other.mkdir()
    bad_other = other / "missing-folder" / "x.txt"
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*b/missing-folder/\.x\.txt\."):
        with FileWriter(2, preload=()) as writer:
            gate = tmp_path / "gate"
            writer.submit(write_when_opened, other / "slow.txt", gate, path=other / "slow.txt")
            writer.submit(write_text, bad_other, "x", path=bad_other)
            for i in range(3):
                writer.submit(write_text, mine / f"{i}.txt", str(i), path=mine / f"{i}.txt")
            writer.wait_for(mine)
            assert [(mine / f"{i}.txt").read_text() for i in range(3)] == ["0", "1", "2"]
            assert not (other / "slow.txt").exists()  # still being written: wait_for(a) did not wait for it
            writer.wait_for(other / "nothing-here")  # no task: returns at once
            gate.touch()
    assert (other / "slow.txt").read_text() == "gated"


@needs_fork
def test_wait_for_raises_a_failure_inside_its_folder_and_close_does_not_raise_it_again(tmp_path):
    bad = tmp_path / "a" / "missing-folder" / "y.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_text, bad, "y", path=bad)
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*a/missing-folder/\.y\.txt\."):
        writer.wait_for(tmp_path / "a")
    writer.close()  # the failure was raised once


@needs_fork
def test_wait_for_joins_a_thread_task(tmp_path):
    folder = tmp_path / "c"
    folder.mkdir()
    with FileWriter(1, preload=()) as writer:
        writer.submit(write_slowly_here, folder / "t.txt", 0.3, path=folder / "t.txt", thread=True)
        writer.wait_for(folder)
        assert (folder / "t.txt").read_text() == "slow"


def die_halfway_in_a_worker(path: Path, caller: int) -> None:
    """Leave ``path``'s temporary file and die, in a worker; in the caller, write ``path``."""
    if os.getpid() != caller:
        Path(path).with_name(f".{Path(path).name}.0123456789ab.tmp").write_text("partial")
        os._exit(9)
    write_text(path, "whole")


@needs_fork
@pytest.mark.parametrize("wait", [True, False])
def test_a_worker_that_dies_halfway_leaves_no_temporary_file(tmp_path, wait):
    path = tmp_path / "q.txt"
    with pytest.raises(TaskDied, match=r"q\.txt ended without a reply \(exit code 9\)"):
        with FileWriter(1, preload=()) as writer:
            writer.submit(die_halfway_in_a_worker, path, os.getpid(), path=path)
            if wait:
                writer.wait_for(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_remove_partial_removes_its_own_file_only(tmp_path):
    from agsf_torch.storage.files import remove_partial

    mine, other = tmp_path / ".data.0123456789ab.tmp", tmp_path / ".data.csv.0123456789ab.tmp"
    mine.write_text("partial")
    other.write_text("another task's, being written")
    remove_partial(tmp_path / "data")
    assert not mine.exists() and other.exists()
