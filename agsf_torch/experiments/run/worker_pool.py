"""Worker processes forked from this one, through :class:`concurrent.futures.ProcessPoolExecutor`: ``agsf
reproduce``'s cases side by side (:func:`run_forked`) and the files one case writes while the next one runs
(:class:`~agsf_torch.experiments.run.file_writer.FileWriter`).

A case is one thread's work from its first step to its last file, and the cases share nothing but the output
folder's parent: on two CPUs or more they run side by side, each in a worker that writes its own files.  The
workers are forked (they start with this process's imports; Linux's, :func:`fork_available`), each runs one torch
thread (its initializer sets it: OpenMP does not survive a fork), and the executor returns each task's result, or
its exception with the worker's traceback as its cause.

Kept here because the executor does not do it and the commands need it:

* a worker that dies (killed, out of memory) breaks the pool with a ``BrokenProcessPool`` that names neither the
  task nor the exit code: :func:`run_forked` raises :class:`TaskDied` naming both, which ``agsf`` prints as one
  line (exit status 3);
* ``shutdown(cancel_futures=True)`` cancels the tasks not started but lets the running ones run to their end:
  interrupted, :meth:`WorkerPool.stop` also passes the interruption on to the workers.  A worker takes SIGINT,
  SIGTERM and SIGHUP as Ctrl-C, once (a terminal's Ctrl-C reaches the whole process group, then the parent passes
  it on again) and only inside a task (idle, it starts no further task); the task's files are written whole or not
  at all (:func:`~agsf_torch.storage.files.atomic_open` removes its temporary file);
* a worker's progress bars are drawn by the parent, each task's on a line of its own
  (:func:`agsf_torch.experiments.run.progress.report_to`): processes that each redraw a terminal line move one another's cursor;
* this process's objects are frozen (:func:`gc.freeze`) across the fork, so that the workers' collections do not
  copy the pages they share with it (kept because the main job, measured alternately with and without it, was
  slower without).
"""

from __future__ import annotations

import gc
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any

from .progress import ParentBars

__all__ = ["fork_available", "run_forked", "TaskDied", "WorkerPool"]

#: Seconds an interrupted worker has to remove its temporary files before it is killed.
INTERRUPT_GRACE_S = 5.0
#: Seconds between two looks at the workers' progress reports.
WAKE_S = 0.1
#: The signals that interrupt a worker's task: Ctrl-C's, and SIGTERM and SIGHUP, which end the ``agsf`` command as
#: Ctrl-C does (:func:`agsf_torch.experiments.cli.terminal.ending_signals`).
_INTERRUPTING = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


class TaskDied(RuntimeError):
    """A task's worker process ended without a reply (killed, or out of memory)."""


def fork_available() -> bool:
    """Whether tasks can run in forked workers: on Linux (elsewhere fork is absent, or unsafe with the system's
    frameworks), from the main thread (Ctrl-C reaches the main thread, which passes it on to the workers)."""
    return (
        sys.platform.startswith("linux")
        and "fork" in multiprocessing.get_all_start_methods()
        and threading.current_thread() is threading.main_thread()
    )


# In a worker: the signal that interrupted it, whether a task runs, and where its progress reports go.
_interrupted: list[int] = []
_in_task = False
_reports: Any = None


def _on_signal(signum: int, frame: Any) -> None:
    """A worker's handler of :data:`_INTERRUPTING`: the first signal interrupts the running task (and no task starts
    after it); later ones are ignored, so that the task's clean-up is not cut short."""
    if _interrupted:
        return
    _interrupted.append(signum)
    if _in_task:
        raise KeyboardInterrupt


def _start_worker(reports: Any, preload: Sequence[str]) -> None:
    """The workers' initializer: one torch thread, no bars of the parent's, the interrupting signals handled
    (:func:`_on_signal`; a signal the command was started ignoring stays ignored: SIGHUP under nohup), the modules
    ``preload`` imported."""
    import importlib

    import torch

    from .progress import forget_parent_bars

    global _reports
    torch.set_num_threads(1)
    forget_parent_bars()
    _reports = reports
    for signum in _INTERRUPTING:
        if signum == signal.SIGINT or signal.getsignal(signum) is not signal.SIG_IGN:
            signal.signal(signum, _on_signal)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _INTERRUPTING)  # blocked by the parent around the fork
    for module in preload:
        importlib.import_module(module)


def _call(index: int, task: Callable[..., Any], args: tuple) -> Any:
    """Run ``task(*args)`` in a worker; with a report channel, announce it (``("started", index, pid)``) and send
    its progress bars to the parent (``("progress", index, desc, unit, total, n)``)."""
    from .progress import report_to

    global _in_task
    _in_task = True
    try:
        if _interrupted:
            raise KeyboardInterrupt
        if _reports is not None:
            _reports.send(("started", index, os.getpid()))
            report_to(lambda *bar: _reports.send(("progress", index, *bar)))
        return task(*args)
    finally:
        _in_task = False
        report_to(None)


class WorkerPool(ProcessPoolExecutor):
    """A :class:`~concurrent.futures.ProcessPoolExecutor` of ``workers`` processes forked from this one (one torch
    thread each; every task run through :func:`_call`, numbered in the order submitted), that knows its processes: to
    pass an interruption on (:meth:`stop`) and to name a dead worker's exit code (:meth:`died`).  ``reports``: the
    sending end of a pipe for :func:`_call`'s reports (or None); ``preload``: modules each worker imports when it
    starts."""

    def __init__(self, workers: int, reports: Any = None, preload: Sequence[str] = ()) -> None:
        context = multiprocessing.get_context("fork")
        super().__init__(workers, mp_context=context, initializer=_start_worker, initargs=(reports, tuple(preload)))
        self.processes: list[multiprocessing.Process] = []
        self._submitted = 0

    def submit(self, fn, /, *args):
        before = set(multiprocessing.active_children())
        # the interrupting signals held back across the fork: a worker handles them once its initializer has run
        # (one meanwhile is delivered here once unblocked, and passed on)
        mask = signal.pthread_sigmask(signal.SIG_BLOCK, _INTERRUPTING)
        frozen = gc.get_freeze_count() > 0
        gc.freeze()  # this process's objects left out of the workers' collections, which would copy their pages
        try:
            future = super().submit(_call, self._submitted, fn, args)
        finally:
            if not frozen:  # a caller's own freeze is left as it was
                gc.unfreeze()
            signal.pthread_sigmask(signal.SIG_SETMASK, mask)
        self._submitted += 1
        self.processes += [p for p in multiprocessing.active_children() if p not in before]
        return future

    def stop(self) -> None:
        """Interrupted: cancel the tasks not started, interrupt the running ones (one SIGINT each: a task removes
        its temporary files), kill a worker still running :data:`INTERRUPT_GRACE_S` after, and wait for them."""
        self.shutdown(wait=False, cancel_futures=True)
        for process in self._running():
            try:
                os.kill(process.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + INTERRUPT_GRACE_S
        while (running := self._running()) and (left := deadline - time.monotonic()) > 0:
            multiprocessing.connection.wait([p.sentinel for p in running], timeout=left)
        for process in running:
            process.kill()
        for process in self.processes:
            process.join()

    def _running(self) -> list[multiprocessing.Process]:
        ended = set(multiprocessing.connection.wait([p.sentinel for p in self.processes], timeout=0))
        return [p for p in self.processes if p.sentinel not in ended]

    def died(self, what: str, started: dict[int, str] | None = None) -> TaskDied:
        """The error of a broken pool (call after ``shutdown``): ``what`` (or the task ``started`` on the dead
        worker, by process id) ended without a reply, with the dead worker's exit code."""
        dead = sorted(
            (p for p in self.processes if p.exitcode not in (None, 0)),
            key=lambda p: p.exitcode == -signal.SIGTERM,  # the pool terminates the other workers when one dies
        )
        if not dead:
            return TaskDied(f"{what} ended without a reply (its reply could not be read)")
        started = started or {}
        culprit = next((p for p in dead if p.pid in started), dead[0])
        return TaskDied(f"{started.get(culprit.pid, what)} ended without a reply (exit code {culprit.exitcode})")


def run_forked(
    tasks: Sequence[tuple[Callable[..., Any], tuple]],
    jobs: int,
    names: Sequence[str] | None = None,
    on_result: Callable[[int, Any], None] | None = None,
) -> list:
    """Run every ``task(*args)`` of ``tasks`` in a :class:`WorkerPool` of ``jobs`` workers, in the order given, and
    return their results in that order (module docstring).  Call it from the main thread (:func:`fork_available`).

    Args:
        tasks: ``(function, arguments)`` pairs; each result must pickle (it returns through a pipe).
        jobs: workers, a positive integer.
        names: what a failure calls each task (default ``task 0``, ``task 1``, …).
        on_result: called here with ``(task index, result)`` as each task succeeds (``agsf reproduce`` writes the
            case's HParams session then, so that a later case's failure leaves the earlier ones complete).

    Raises:
        the first failed task's exception (in task order; the worker's traceback as its ``__cause__``) once every
        task has ended; :class:`TaskDied` for a worker that died, naming its task and exit code.
    """
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    if not fork_available():
        raise RuntimeError("run_forked needs fork (Linux) and the main thread; run the tasks one after another instead")
    names = list(names) if names is not None else [f"task {i}" for i in range(len(tasks))]
    receive, send = multiprocessing.get_context("fork").Pipe(duplex=False)
    bars = ParentBars()
    started: dict[int, str] = {}  # worker pid → the task it started last

    def relay() -> None:
        while receive.poll():
            kind, index, *rest = receive.recv()
            if kind == "started":
                started[rest[0]] = names[index]
            else:
                bars.update(index, *rest)

    results: list[Any] = [None] * len(tasks)
    failures: dict[int, BaseException] = {}
    pool = WorkerPool(jobs, reports=send)
    try:
        futures = {pool.submit(task, *args): i for i, (task, args) in enumerate(tasks)}
        pending = set(futures)
        while pending:
            done, pending = wait(pending, timeout=WAKE_S, return_when=FIRST_COMPLETED)
            relay()
            for future in sorted(done, key=futures.get):
                index = futures[future]
                if future.exception() is not None:
                    failures[index] = future.exception()
                else:
                    results[index] = future.result()
                    if on_result is not None:
                        on_result(index, results[index])
        pool.shutdown(wait=True)
    except BaseException:
        pool.stop()
        raise
    finally:
        relay()
        bars.close()
        receive.close()
        send.close()
    if failures:
        index = min(failures)
        first = failures[index]
        if isinstance(first, KeyboardInterrupt):
            raise KeyboardInterrupt
        if isinstance(first, BrokenProcessPool):
            raise pool.died(names[index], started) from None
        raise first
    return results
