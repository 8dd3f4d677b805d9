"""Writing files in worker processes (agsf_torch.experiments.file_writer) and reproduce's use of it."""

from __future__ import annotations

import hashlib
import os
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


def test_a_failed_task_is_an_error_naming_its_file_after_the_others_are_written(tmp_path):
    bad = tmp_path / "missing-folder" / "b.txt"
    good = tmp_path / "c.txt"
    writer = FileWriter(1, preload=())
    writer.submit(write_text, bad, "beta", path=bad)
    writer.submit(write_text, good, "gamma", path=good)
    with pytest.raises(RuntimeError, match=r"could not write .*missing-folder/b\.txt: FileNotFoundError"):
        writer.close()
    assert good.read_text() == "gamma"


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


def test_an_exception_in_the_block_stops_the_workers(tmp_path):
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


def test_reproduce_writes_the_same_files_with_a_writer_as_without_and_restores_the_threads(tmp_path):
    overrides = ["runs=3", "duration=2.0", "components=2", *EAGER]
    threads = torch.get_num_threads()
    tables = {}
    for writers in (0, 1):
        tables[writers] = reproduce([1, 3], tmp_path / str(writers), overrides, progress=False, writers=writers)
        assert torch.get_num_threads() == threads
    assert tables[0] == tables[1]
    inline, written = _digests(tmp_path / "0"), _digests(tmp_path / "1")
    for case in ("case1", "case3"):
        assert {f"{case}/{name}" for name in ("runs.npz", "rms.png", "axes.png", "weights.png", "fpke.png")} <= set(
            inline
        )
    assert written == inline
