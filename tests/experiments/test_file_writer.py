"""Writing files in worker processes (agsf_torch.experiments.file_writer) and reproduce's use of it."""

from __future__ import annotations

import hashlib
import os
import time
from pathlib import Path

import pytest
import torch

from agsf_torch.experiments.file_writer import FileWriter
from agsf_torch.experiments.reproduce import reproduce
from agsf_torch.storage.files import write_text
from tests.helpers import EAGER


def _digests(root: Path) -> dict[str, str]:
    """Every file under ``root`` (but the TensorBoard events, whose names hold a time) and a digest of its bytes."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file() and "tfevents" not in p.name and p.name != ".agsf.lock"
    }


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
    with FileWriter(2, preload=()) as writer:
        for path, stray in zip(paths, strays):
            writer.submit(write_pid, path, stray, path=path)
    pids = {int(p.read_text()) for p in paths}
    assert os.getpid() not in pids and 1 <= len(pids) <= 2  # written by the workers, none again by the caller


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
    with pytest.raises(RuntimeError, match=r"could not write .*missing-folder/j\.txt: FileNotFoundError"):
        writer.close()
    assert [p.read_text() for p in good] == ["i", "k"]


def test_a_failed_task_is_an_error_naming_its_file_after_the_others_are_written(tmp_path):
    bad = tmp_path / "missing-folder" / "b.txt"
    good = tmp_path / "c.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_text, bad, "beta", path=bad)
    writer.submit(write_text, good, "gamma", path=good)
    with pytest.raises(RuntimeError, match=r"could not write .*missing-folder/b\.txt: FileNotFoundError"):
        writer.close()
    assert good.read_text() == "gamma"


def test_a_task_written_by_the_caller_that_fails_is_named_when_the_writer_closes(tmp_path):
    bad = tmp_path / "missing-folder" / "l.txt"
    writer = FileWriter(1, preload=())
    writer.submit(lambda p: write_text(p, "lambda"), bad, path=bad)  # cannot be pickled: run here, and fails
    writer.submit(write_text, tmp_path / "m.txt", "mu", path=tmp_path / "m.txt")
    with pytest.raises(RuntimeError, match=r"could not write .*missing-folder/l\.txt: FileNotFoundError"):
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
    # with a writer every figure is drawn by its worker, none by the caller
    monkeypatch.setattr(FileWriter, "_write_here", lambda *a: pytest.fail("a figure was drawn in the caller"))
    overrides = ["runs=3", "duration=2.0", "components=2", *EAGER]
    threads = torch.get_num_threads()
    tables = {}
    for writers in (0, 1):
        tables[writers] = reproduce(
            [1, 3], tmp_path / str(writers), overrides, progress=False, writers=writers, threads=threads + 1
        )
        assert torch.get_num_threads() == threads
    assert tables[0] == tables[1]
    inline, written = _digests(tmp_path / "0"), _digests(tmp_path / "1")
    for case in ("case1", "case3"):
        assert {f"{case}/{name}" for name in ("runs.npz", "rms.png", "axes.png", "weights.png", "fpke.png")} <= set(
            inline
        )
    assert written == inline


@pytest.mark.parametrize(("option", "value"), [("writers", -1), ("writers", True), ("threads", 0), ("threads", 1.5)])
def test_reproduce_refuses_bad_writer_and_thread_counts_before_creating_anything(tmp_path, option, value):
    with pytest.raises(ValueError, match=f"{option} must be"):
        reproduce([1], tmp_path / "out", list(EAGER), progress=False, **{option: value})
    assert not (tmp_path / "out").exists()
