"""Writing files in worker processes (agsf_torch.experiments.file_writer) and reproduce's use of it."""

from __future__ import annotations

import errno
import os
import threading
import time
from pathlib import Path

import pytest
import torch

from agsf_torch.experiments.file_writer import FileWriter
from agsf_torch.experiments.reproduce import reproduce
from agsf_torch.storage.files import write_text
from tests.helpers import EAGER, event_records, file_digests


def write_unless_in_a_worker(path: Path, text: str, caller: int) -> None:
    """Write ``text`` to ``path`` in the process ``caller``; in any other process, die without a word."""
    if os.getpid() != caller:
        os._exit(3)
    write_text(path, text)


def write_pid(path: Path, stray: bytes = b"") -> None:
    """Write the writing process's id to ``path``, after writing ``stray`` to file descriptor 1 (as a C library
    or a child process might)."""
    if stray:
        os.write(1, stray)
    write_text(path, str(os.getpid()))


def write_slowly(path: Path, seconds: float) -> None:
    """Leave ``path``'s temporary file, wait ``seconds``, then write ``path`` (a writer killed meanwhile leaves the
    temporary file behind)."""
    Path(path).with_name(f".{Path(path).name}.0123456789ab.tmp").write_text("partial")
    time.sleep(seconds)
    write_text(path, "slow")


def test_without_workers_a_task_runs_when_submitted(tmp_path):
    with FileWriter(0) as writer:
        writer.submit(write_text, tmp_path / "a.txt", "alpha", path=tmp_path / "a.txt")
        assert (tmp_path / "a.txt").read_text() == "alpha"


def test_workers_write_every_file_by_close_and_leave_no_scratch(tmp_path):
    files = {tmp_path / f"f{i}.txt": f"text {i}" for i in range(7)}
    writer = FileWriter(2, preload=())
    scratch = writer._scratch
    for path, text in files.items():
        writer.submit(write_text, path, text, path=path)
    writer.close()
    assert {p: p.read_text() for p in files} == files
    assert not scratch.exists()


def test_the_tasks_run_in_the_workers_whatever_they_write_to_file_descriptor_1(tmp_path):
    strays = [b"", b"3\n", b'{"job": 1}\n', b"not json\n", b"partial, without a newline"]
    paths = [tmp_path / f"p{i}.txt" for i in range(len(strays))]
    with FileWriter(2, preload=(), caller_helps=False) as writer:
        for path, stray in zip(paths, strays):
            writer.submit(write_pid, path, stray, path=path)
    pids = {int(p.read_text()) for p in paths}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2  # written by the workers, none again by the caller


def test_at_close_the_caller_runs_the_queued_tasks_beside_the_workers(tmp_path):
    slow, quick = tmp_path / "slow.txt", [tmp_path / f"q{i}.txt" for i in range(3)]
    with FileWriter(1, preload=()) as writer:
        writer.submit(write_slowly, slow, 1.5, path=slow)  # the worker's one task in hand
        for path in quick:
            writer.submit(write_pid, path, path=path)  # queued in the caller
    assert slow.read_text() == "slow"
    assert [int(p.read_text()) for p in quick] == [os.getpid()] * 3


def test_a_worker_takes_the_queued_tasks_one_at_a_time_in_order(tmp_path):
    paths = [tmp_path / f"o{i}.txt" for i in range(5)]
    with FileWriter(1, preload=(), caller_helps=False) as writer:
        for path in paths:
            writer.submit(write_pid, path, path=path)
        assert len(writer._queue) >= 3 and writer._queue[0].endswith("job1.pkl")  # one in hand, the rest waiting
    pids = {int(p.read_text()) for p in paths}
    assert len(pids) == 1 and os.getpid() not in pids
    times = [p.stat().st_mtime_ns for p in paths]
    assert times == sorted(times)  # in the order submitted


def fill_the_disk(path: Path) -> None:
    """Fail as a write to a full disk does."""
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))


def write_in_thread(path: Path, main: int) -> None:
    """Write whether this runs in the thread ``main`` (``"main"``) or another (``"thread"``), and the process id."""
    write_text(path, f"{'main' if threading.get_ident() == main else 'thread'} {os.getpid()}")


def test_a_thread_task_runs_in_a_thread_of_the_caller_and_is_complete_at_close(tmp_path):
    path, bad = tmp_path / "t.txt", tmp_path / "missing-folder" / "u.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_in_thread, path, threading.get_ident(), path=path, thread=True)
    writer.submit(write_in_thread, bad, threading.get_ident(), path=bad, thread=True)
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*missing-folder/u\.txt"):
        writer.close()
    assert path.read_text() == f"thread {os.getpid()}"


def test_without_workers_a_thread_task_runs_when_submitted(tmp_path):
    with FileWriter(0) as writer:
        writer.submit(write_in_thread, tmp_path / "v.txt", threading.get_ident(), path=tmp_path / "v.txt", thread=True)
        assert (tmp_path / "v.txt").read_text() == f"main {os.getpid()}"


def test_an_error_in_the_block_lets_the_workers_finish_what_they_were_handed(tmp_path):
    path = tmp_path / "g.txt"
    with pytest.raises(ZeroDivisionError):
        with FileWriter(1, preload=()) as writer:
            writer.submit(write_slowly, path, 0.5, path=path)
            1 / 0
    assert path.read_text() == "slow"  # an earlier case's files are complete whatever a later case does


def test_an_interruption_stops_the_workers_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "h.txt"
    with pytest.raises(KeyboardInterrupt):
        with FileWriter(1, preload=()) as writer:
            writer.submit(write_slowly, path, 30.0, path=path)
            deadline = time.monotonic() + 30.0
            while not list(tmp_path.glob(".h.txt.*.tmp")) and time.monotonic() < deadline:
                time.sleep(0.01)  # until the worker has started the file
            assert list(tmp_path.glob(".h.txt.*.tmp"))
            raise KeyboardInterrupt
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_tasks_of_a_dead_worker_are_written_by_the_caller_and_each_failure_named(tmp_path):
    good = [tmp_path / "i.txt", tmp_path / "k.txt"]
    bad = tmp_path / "missing-folder" / "j.txt"
    writer = FileWriter(1, preload=())
    for path in (good[0], bad, good[1]):
        writer.submit(write_unless_in_a_worker, path, path.stem, os.getpid(), path=path)
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*missing-folder/j\.txt"):
        writer.close()
    assert [p.read_text() for p in good] == ["i", "k"]


def fail_to_draw(path: Path) -> None:
    """A task that fails without an I/O error."""
    raise ValueError(f"nothing to draw for {path.name}")


def divide_by_zero(path: Path) -> None:
    """A task that fails with neither an I/O error nor a ValueError."""
    1 / 0


def test_a_failed_task_is_raised_as_the_caller_would_have_raised_it_naming_its_file(tmp_path):
    """A ValueError as a ValueError (``agsf``: one line, exit 2, as when the caller draws the figure itself), any
    other failure as RuntimeError, each naming the file and how many failed."""
    paths = [tmp_path / "n.png", tmp_path / "o.png"]
    writer = FileWriter(1, preload=())
    for path in paths:
        writer.submit(fail_to_draw, path, path=path)
    with pytest.raises(
        ValueError,
        match=r"could not write .*([no])\.png: ValueError: nothing to draw for \1\.png \(1 more files failed\)",
    ):
        writer.close()
    with pytest.raises(RuntimeError, match=r"could not write .*r\.png: ZeroDivisionError"):
        with FileWriter(1, preload=(), caller_helps=False) as writer:
            writer.submit(divide_by_zero, tmp_path / "r.png", path=tmp_path / "r.png")


def fail_with(path: Path, code: int, message: str, filename: str | None) -> None:
    raise OSError(code, message, filename)


def test_an_io_failure_keeps_its_message_and_file_and_comes_first_and_a_non_errno_is_not_one(tmp_path):
    """An ``OSError`` keeps its own message and file name (the file written named too where they differ); it is the
    one raised whatever failed before it (a full disk exits 3); an errno 0 or out of range is no I/O failure."""
    out = tmp_path / "s.png"
    style = str(tmp_path / "agsf.mplstyle")
    with pytest.raises(OSError) as failure:
        with FileWriter(1, preload=(), caller_helps=False) as writer:
            writer.submit(fail_to_draw, tmp_path / "q.png", path=tmp_path / "q.png")
            writer.submit(fail_with, out, errno.ENOENT, "the style sheet is missing", style, path=out)
    assert failure.value.errno == errno.ENOENT and failure.value.filename == style
    assert failure.value.strerror == f"the style sheet is missing (1 more files failed), writing {out}"
    for code in (0, 2**40):  # an OSError still (one line from agsf, as in the caller), but no I/O failure's errno
        with pytest.raises(OSError, match=r"could not write .*s\.png: OSError") as failure:
            with FileWriter(1, preload=(), caller_helps=False) as writer:
                writer.submit(fail_with, out, code, "odd", None, path=out)
        assert failure.value.errno is None


def test_a_reply_with_foreign_fields_is_taken_as_a_failure_of_unknown_kind_not_dropped(tmp_path):
    """A worker's reply whose errno is not a number still reports its job done (a dropped reply left the job held
    by a live worker, and wait_for waiting for ever)."""
    import json

    path = tmp_path / "t.png"
    writer = FileWriter(1, preload=(), caller_helps=False)
    try:
        with writer._lock:
            writer._jobs["job-x"] = (path, 0)
            writer._in_hand[0] = "job-x"
        writer._take(0, json.dumps({"job": "job-x", "error": "OSError: full", "kind": "os", "errno": "ENOSPC"}))
        assert "job-x" not in writer._jobs
        with pytest.raises(OSError, match=r"could not write .*t\.png: OSError: full") as failure:
            writer.wait_for(tmp_path)
        assert failure.value.errno is None
    finally:
        writer.close()


def test_a_dead_workers_leftovers_are_its_own_file_only_and_background_ends_with_the_workers(tmp_path):
    from agsf_torch.storage.files import remove_partial

    mine, other = tmp_path / ".data.0123456789ab.tmp", tmp_path / ".data.csv.0123456789ab.tmp"
    mine.write_text("partial")
    other.write_text("another task's, being written")
    remove_partial(tmp_path / "data")
    assert not mine.exists() and other.exists()
    writer = FileWriter(1, preload=())
    assert writer.background
    for proc, _ in writer._workers:
        proc.kill()
        proc.wait()
    assert not writer.background  # every task now runs in the caller
    writer.close()


def test_an_io_failure_in_a_worker_is_an_os_error_with_its_errno_as_when_written_here(tmp_path):
    """A full disk in a worker is reported as one (``agsf``: exit 3, "I/O failure"), as a write in the caller is."""
    path = tmp_path / "p.txt"
    with pytest.raises(OSError) as failure:
        with FileWriter(1, preload=(), caller_helps=False) as writer:
            writer.submit(fill_the_disk, path, path=path)
    assert failure.value.errno == errno.ENOSPC and failure.value.filename == str(path)
    assert failure.value.strerror == os.strerror(errno.ENOSPC)


def test_a_failed_task_is_an_error_naming_its_file_after_the_others_are_written(tmp_path):
    bad = tmp_path / "missing-folder" / "b.txt"
    good = tmp_path / "c.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_text, bad, "beta", path=bad)
    writer.submit(write_text, good, "gamma", path=good)
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*missing-folder/b\.txt"):
        writer.close()
    assert good.read_text() == "gamma"


def test_a_task_written_by_the_caller_that_fails_is_named_when_the_writer_closes(tmp_path):
    bad = tmp_path / "missing-folder" / "l.txt"
    writer = FileWriter(1, preload=())
    writer.submit(lambda p: write_text(p, "lambda"), bad, path=bad)  # cannot be pickled: run here, and fails
    writer.submit(write_text, tmp_path / "m.txt", "mu", path=tmp_path / "m.txt")
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*missing-folder/l\.txt"):
        writer.close()
    assert (tmp_path / "m.txt").read_text() == "mu"


def test_a_task_that_cannot_be_sent_runs_in_the_caller(tmp_path):
    written = []
    with FileWriter(1, preload=()) as writer:
        writer.submit(lambda p: written.append(write_text(p, "delta")), tmp_path / "d.txt", path=tmp_path / "d.txt")
        assert written == [tmp_path / "d.txt"]  # at once: a lambda cannot be pickled


def test_a_task_whose_worker_died_is_written_by_the_caller(tmp_path):
    path = tmp_path / "e.txt"
    with FileWriter(1, preload=()) as writer:
        writer.submit(write_unless_in_a_worker, path, "epsilon", os.getpid(), path=path)
    assert path.read_text() == "epsilon"  # nothing lost


def test_an_interruption_in_the_block_stops_the_workers_and_removes_the_scratch_folder(tmp_path):
    with pytest.raises(KeyboardInterrupt):
        with FileWriter(2, preload=()) as writer:
            procs = [proc for proc, _ in writer._workers]
            scratch = writer._scratch
            raise KeyboardInterrupt
    assert all(proc.poll() is not None for proc in procs)
    assert not scratch.exists()


@pytest.mark.parametrize("workers", [0, 1])
def test_a_closed_writer_refuses_tasks(tmp_path, workers):
    writer = FileWriter(workers, preload=())
    writer.close()
    with pytest.raises(ValueError, match=r"cannot write .*f\.txt: this FileWriter is closed"):
        writer.submit(write_text, tmp_path / "f.txt", "zeta", path=tmp_path / "f.txt")
    assert not (tmp_path / "f.txt").exists()


@pytest.mark.parametrize("workers", [-1, 1.5, True, "2"])
def test_bad_worker_counts_are_refused(workers):
    with pytest.raises(ValueError, match="workers must be a non-negative integer"):
        FileWriter(workers)


def test_reproduce_writes_the_same_files_with_a_writer_as_without_and_restores_the_threads(tmp_path, monkeypatch):
    here = []  # what the caller wrote itself: what it took of the queue at close
    write_here = FileWriter._write_here
    monkeypatch.setattr(
        FileWriter, "_write_here", lambda self, path, *a: (here.append(path), write_here(self, path, *a))
    )
    overrides = ["runs=3", "duration=2.0", "components=2", *EAGER]
    threads = torch.get_num_threads()
    tables = {}
    for writers in (0, 1):
        tables[writers] = reproduce(
            [1, 3], tmp_path / str(writers), overrides, progress=False, writers=writers, threads=threads + 1
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
    here = {str(p.relative_to(tmp_path / "1")) for p in here}
    assert "case1/runs.npz" not in here  # case 1's first file went to the idle worker when submitted


@pytest.mark.parametrize(("option", "value"), [("writers", -1), ("writers", True), ("threads", 0), ("threads", 1.5)])
def test_reproduce_refuses_bad_writer_and_thread_counts_before_creating_anything(tmp_path, option, value):
    with pytest.raises(ValueError, match=f"{option} must be"):
        reproduce([1], tmp_path / "out", list(EAGER), progress=False, **{option: value})
    assert not (tmp_path / "out").exists()


def test_more_writers_than_cpus_are_refused_naming_the_cpus(tmp_path):
    """More worker processes than CPUs had been refused as a memory shortfall with a negative budget."""
    from agsf_torch.processes import available_cpus

    cpus = available_cpus()
    with pytest.raises(
        ValueError, match=f"writers must be an integer from 0 to the {cpus} CPUs this process may use, got {cpus + 1}"
    ):
        reproduce([1], tmp_path / "out", list(EAGER), progress=False, writers=cpus + 1)
    assert not (tmp_path / "out").exists()


def test_a_job_file_is_removed_once_its_task_has_written_its_file(tmp_path):
    path = tmp_path / "w.txt"
    with FileWriter(1, preload=()) as writer:
        writer.submit(write_text, path, "omega", path=path)
        deadline = time.monotonic() + 60.0
        while (list(writer._scratch.glob("job*.pkl")) or writer._jobs) and time.monotonic() < deadline:
            time.sleep(0.01)
        assert path.read_text() == "omega"
        assert not list(writer._scratch.glob("job*.pkl"))  # its arguments no longer take room while the writer runs


class _Submissions:
    """A stand-in for a FileWriter that records how each task was submitted."""

    def __init__(self):
        self.calls = []

    def submit(self, write, *args, path, thread=False):
        self.calls.append((Path(path).name, thread))


@pytest.mark.parametrize(("limit", "thread"), [(2**40, False), (1, True)])
def test_runs_npz_goes_to_a_worker_unless_its_arrays_exceed_the_handover_limit(tmp_path, monkeypatch, limit, thread):
    import numpy as np

    from agsf_torch.experiments import file_writer, outputs

    reused = {
        "GSF": ({"time": np.arange(3.0), "star_frame": np.zeros(3, bool), "GSF/error_angle": np.ones((2, 3))}, {})
    }
    monkeypatch.setattr(file_writer, "HANDOVER_BYTES", limit)
    writer = _Submissions()
    data = outputs.save_runs(tmp_path / "runs.npz", None, reused, writer)
    assert writer.calls == [("runs.npz", thread)] and set(data) == {"time", "star_frame", "GSF/error_angle"}
    assert not (tmp_path / "runs.npz").exists()  # the writer's to write


def write_then_die_in_a_worker(path: Path, text: str, caller: int) -> None:
    """Write ``text`` to ``path``; then, in any process but ``caller``, die before replying."""
    write_text(path, text)
    if os.getpid() != caller:
        os._exit(3)


def test_a_task_whose_worker_died_after_writing_is_written_again_without_an_error(tmp_path):
    path = tmp_path / "x.txt"
    with FileWriter(1, preload=()) as writer:
        writer.submit(write_then_die_in_a_worker, path, "xi", os.getpid(), path=path)
    assert path.read_text() == "xi"  # the job file was kept until a reply: the caller could run it again


def test_closing_again_after_an_interrupted_close_does_nothing(tmp_path, monkeypatch):
    paths = [tmp_path / f"y{i}.txt" for i in range(3)]
    writer = FileWriter(1, preload=())
    writer.submit(write_slowly, paths[0], 1.0, path=paths[0])
    for path in paths[1:]:
        writer.submit(write_text, path, "queued", path=path)

    def interrupted(self, job):
        raise KeyboardInterrupt

    monkeypatch.setattr(FileWriter, "_run_here", interrupted)
    procs = [proc for proc, _ in writer._workers]
    with pytest.raises(KeyboardInterrupt):
        writer.close()  # the caller is interrupted while it runs the queue
    writer.close()
    assert all(proc.poll() is not None for proc in procs)
    assert not any(p.exists() for p in paths[1:]) and not list(tmp_path.glob(".*.tmp"))


def write_slowly_here(path: Path, seconds: float) -> None:
    """Wait ``seconds``, then write ``path``."""
    time.sleep(seconds)
    write_text(path, "slow")


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


def test_wait_for_a_folder_leaves_the_other_tasks_running_and_raises_only_its_own_failures(tmp_path):
    """A sweep records one configuration (its folder complete) while the next one's files are still written."""
    mine, other = tmp_path / "a", tmp_path / "b"
    mine.mkdir()
    other.mkdir()
    bad_other = other / "missing-folder" / "x.txt"
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*b/missing-folder/x\.txt") as failure:
        with FileWriter(1, preload=()) as writer:
            gate = tmp_path / "gate"
            writer.submit(write_when_opened, other / "slow.txt", gate, path=other / "slow.txt")  # the worker's
            writer.submit(write_text, bad_other, "x", path=bad_other)
            for i in range(3):  # queued behind the worker's task: run here by wait_for
                writer.submit(write_text, mine / f"{i}.txt", str(i), path=mine / f"{i}.txt")
            writer.wait_for(mine)
            assert [(mine / f"{i}.txt").read_text() for i in range(3)] == ["0", "1", "2"]
            assert not (other / "slow.txt").exists()  # still being written: wait_for(a) did not wait for it
            writer.wait_for(other / "nothing-here")  # no task: returns at once
            gate.touch()
    assert "more files" not in str(failure.value)  # raised by close, once
    assert (other / "slow.txt").read_text() == "gated"


def test_wait_for_raises_a_failure_inside_its_folder_and_close_does_not_raise_it_again(tmp_path):
    bad = tmp_path / "a" / "missing-folder" / "y.txt"
    writer = FileWriter(1, preload=(), caller_helps=False)
    writer.submit(write_text, bad, "y", path=bad)
    with pytest.raises(FileNotFoundError, match=r"No such file or directory.*a/missing-folder/y\.txt"):
        writer.wait_for(tmp_path / "a")
    writer.close()  # the failure was raised once


def test_wait_for_takes_back_the_task_of_a_worker_that_died_and_joins_a_thread_task(tmp_path):
    folder = tmp_path / "c"
    folder.mkdir()
    with FileWriter(1, preload=(), caller_helps=False) as writer:
        writer.submit(write_unless_in_a_worker, folder / "z.txt", "zeta", os.getpid(), path=folder / "z.txt")
        writer.submit(write_slowly_here, folder / "t.txt", 0.3, path=folder / "t.txt", thread=True)
        writer.wait_for(folder)
        assert (folder / "z.txt").read_text() == "zeta"  # the worker died holding it: written here
        assert (folder / "t.txt").read_text() == "slow"


def die_halfway_in_a_worker(path: Path, caller: int) -> None:
    """Leave ``path``'s temporary file and die, in a worker; in the caller, write ``path``."""
    if os.getpid() != caller:
        Path(path).with_name(f".{Path(path).name}.0123456789ab.tmp").write_text("partial")
        os._exit(9)
    write_text(path, "whole")


@pytest.mark.parametrize("wait", [True, False])
def test_a_task_taken_back_from_a_dead_worker_leaves_no_temporary_file(tmp_path, wait):
    path = tmp_path / "q.txt"
    with FileWriter(1, preload=(), caller_helps=False) as writer:
        writer.submit(die_halfway_in_a_worker, path, os.getpid(), path=path)
        if wait:
            writer.wait_for(tmp_path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["q.txt"] and path.read_text() == "whole"
