"""Tasks in forked worker processes (:mod:`agsf_torch.experiments.run.worker_pool`, a ProcessPoolExecutor): results in order,
every task run to its end before the first failure is raised as the task raised it, a worker that dies named with its
exit code, an interruption passed on."""

from __future__ import annotations

import gc
import os
import signal
import sys
import threading
import time
from pathlib import Path

import pytest

from agsf_torch.experiments.run.worker_pool import TaskDied, fork_available, run_forked

pytestmark = pytest.mark.skipif(not fork_available(), reason="forked tasks need fork (Linux)")


def _square(x: int) -> tuple[int, int]:
    return x * x, os.getpid()


def _write_then(path: str, error: BaseException | None) -> str:
    time.sleep(0.05)
    Path(path).write_text("done")
    if error is not None:
        raise error
    return path


def _die(code: int) -> None:
    os._exit(code)


def _unpicklable() -> object:
    return lambda: None


def _slow(path: str) -> None:
    Path(path).write_text(str(os.getpid()))
    while True:
        time.sleep(0.01)


@pytest.mark.parametrize("jobs", [1, 2, 5])
def test_results_come_back_in_task_order_each_from_a_child(jobs):
    results = run_forked([(_square, (k,)) for k in range(5)], jobs)
    assert [r[0] for r in results] == [0, 1, 4, 9, 16]
    assert os.getpid() not in {pid for _, pid in results}
    assert len({pid for _, pid in results}) <= jobs
    assert gc.get_freeze_count() == 0  # frozen across the fork only: this process's objects are collected again


def _threads() -> int:
    import torch

    return torch.get_num_threads()


def test_each_worker_runs_one_torch_thread():
    assert run_forked([(_threads, ())], 1) == [1]


def test_a_failure_is_raised_as_the_task_raised_it_once_every_other_task_has_ended(tmp_path):
    tasks = [
        (_write_then, (str(tmp_path / "a"), None)),
        (_write_then, (str(tmp_path / "b"), ValueError("bad input in b"))),
        (_write_then, (str(tmp_path / "c"), OSError(28, "No space left on device", "c.npz"))),
        (_write_then, (str(tmp_path / "d"), None)),
    ]
    with pytest.raises(ValueError, match="^bad input in b$"):  # the first failure in task order
        run_forked(tasks, 2)
    assert all((tmp_path / name).read_text() == "done" for name in "abcd")


def test_an_os_error_keeps_its_errno_and_file():
    with pytest.raises(OSError) as info:
        run_forked([(_write_then, ("/dev/null", OSError(28, "No space left on device", "runs.npz")))], 1)
    assert (info.value.errno, info.value.filename) == (28, "runs.npz")


def test_a_child_that_dies_without_a_reply_is_named_with_its_exit_code():
    with pytest.raises(TaskDied, match=r"^case2 ended without a reply \(exit code 9\)$"):
        run_forked([(_square, (1,)), (_die, (9,))], 2, names=["case1", "case2"])


def test_a_result_that_cannot_be_sent_is_a_failure():
    with pytest.raises(Exception, match="pickle"):
        run_forked([(_unpicklable, ())], 1)


@pytest.mark.parametrize("jobs", [0, -1, 1.5, True, "2"])
def test_bad_job_counts_are_refused(jobs):
    with pytest.raises(ValueError, match="jobs must be a positive integer"):
        run_forked([(_square, (1,))], jobs)


def _slow_clean(path: str) -> None:
    """Loop until interrupted, then take 0.3 s to clean up (a second SIGINT must not cut it short)."""
    Path(path).write_text(str(os.getpid()))
    try:
        while True:
            time.sleep(0.01)
    finally:
        time.sleep(0.3)
        Path(path + ".cleaned").write_text("yes")


@pytest.mark.parametrize("whole_group", [False, True])
def test_an_interruption_interrupts_the_children_once_and_propagates(tmp_path, whole_group):
    """Ctrl-C: to the parent alone, or at a terminal to the whole process group (each child then gets it twice: the
    terminal's and the parent's); each child's clean-up runs to its end and none outlives the call."""
    marks = [tmp_path / f"child{k}" for k in range(2)]

    def interrupt_when_started() -> None:
        # a child creates its mark before it writes its pid there: wait for the pid itself
        while not all(m.exists() and m.read_text().strip() for m in marks):
            time.sleep(0.01)
        if whole_group:
            for m in marks:
                os.kill(int(m.read_text()), signal.SIGINT)
        os.kill(os.getpid(), signal.SIGINT)

    threading.Thread(target=interrupt_when_started, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        run_forked([(_slow_clean, (str(m),)) for m in marks], 2)
    for mark in marks:
        assert Path(str(mark) + ".cleaned").read_text() == "yes"
        with pytest.raises(ProcessLookupError):  # reaped: no such process any more
            os.kill(int(mark.read_text()), 0)


def _counting(total: int) -> int:
    from agsf_torch.experiments.run.progress import progress_bar

    return sum(1 for _ in progress_bar(range(total), desc=f"count{total}", unit="step", total=total))


def test_the_childrens_progress_bars_are_drawn_by_the_parent_on_a_line_each(monkeypatch):
    from agsf_torch.experiments.run import worker_pool as forked

    seen = []

    class Recorder:
        def update(self, child, desc, unit, total, n):
            seen.append((child, desc, total, n))

        def close(self):
            seen.append("closed")

    monkeypatch.setattr(forked, "ParentBars", Recorder)
    assert run_forked([(_counting, (100,)), (_counting, (300,))], 2) == [100, 300]
    assert seen[-1] == "closed"
    for child, total in ((0, 100), (1, 300)):
        mine = [n for c, desc, t, n in seen[:-1] if c == child and desc == f"count{total}" and t == total]
        assert mine[0] == 0 and mine[-1] == total and mine == sorted(mine)


def _raise_value_error() -> None:
    raise ValueError("case2.npz: unreadable")


def test_a_failure_carries_the_workers_traceback_as_its_cause():
    with pytest.raises(ValueError, match="^case2.npz: unreadable$") as info:
        run_forked([(_raise_value_error, ())], 1)
    assert "_raise_value_error" in str(info.value.__cause__)


def test_each_result_is_handed_over_as_its_task_succeeds_and_a_callers_freeze_is_kept():
    got = []
    gc.freeze()
    try:
        run_forked([(_square, (k,)) for k in range(3)], 3, on_result=lambda i, r: got.append((i, r[0])))
        assert gc.get_freeze_count() > 0  # the caller's freeze left as it was
    finally:
        gc.unfreeze()
    assert sorted(got) == [(0, 0), (1, 1), (2, 4)]


def test_closed_standard_streams_are_skipped(monkeypatch):
    monkeypatch.setattr(sys, "stdout", None)
    assert run_forked([(_square, (3,))], 1)[0][0] == 9


def test_from_another_thread_tasks_are_refused():
    errors = []

    def call():
        try:
            run_forked([(_square, (1,))], 1)
        except RuntimeError as exc:
            errors.append(str(exc))

    worker = threading.Thread(target=call)
    worker.start()
    worker.join()
    assert errors and "the main thread" in errors[0]
