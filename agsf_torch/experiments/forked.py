"""Independent experiments side by side, each in a forked process: ``agsf reproduce``'s cases.

A case is one thread's work from its first step to its last file (its filters, then ``runs.npz``, its figures
and events), and the cases share nothing but the output folder's parent.  On a machine of two CPUs or more they
run side by side, each in a child *forked* from this process: a child starts with this process's imports (torch
and the package, 0.8 s of a new interpreter's start), and every child runs one case end to end, writing its own
files.  Three cases on two cores take turns on both (measured on an AMD EPYC VM, 2 cores: the three cases of
``agsf reproduce`` in 5–6 s this way against 9–10 s one after another beside a file-writing worker).

Forking is safe here because the parent forks before it runs anything threaded: torch creates its thread pools
on first parallel use (torch's ``DataLoader`` forks its workers the same way), and the children set their own
thread count.  Fork is Linux's (:func:`fork_available`); elsewhere the cases run one after another.

:func:`run_forked` runs the tasks, returns their results in order and raises the first failure (the child's own
exception, or one naming the task when its child died without a reply) once every other task has ended, so that
an earlier case's files are complete whatever a later one does.  Interrupted (Ctrl-C), the children are
interrupted too (each removes its unfinished temporary files) and the interruption propagates.  A child's progress
bars are drawn by the parent, each child's on a line of its own (:func:`.progress.report_to`): processes that each
redraw a terminal line move one another's cursor.
"""

from __future__ import annotations

import gc
import importlib
import multiprocessing
import multiprocessing.connection
import os
import signal
import sys
from collections.abc import Callable, Sequence
from typing import Any

from .progress import ParentBars

__all__ = ["fork_available", "run_forked", "TaskDied"]

#: Seconds an interrupted child has to remove its temporary files before it is killed.
INTERRUPT_GRACE_S = 5.0


class TaskDied(RuntimeError):
    """A forked task's process ended without a reply (killed, or out of memory)."""


def fork_available() -> bool:
    """Whether tasks can run in forked children: on Linux (elsewhere fork is absent, or unsafe with the system's
    frameworks)."""
    return sys.platform.startswith("linux") and "fork" in multiprocessing.get_all_start_methods()


def _child(conn: Any, index: int, task: Callable[..., Any], args: tuple) -> None:
    """A child's body: run the task, its progress bars reported to the parent (``("progress", desc, unit, total,
    n)``), then send ``("done", True, result)`` or ``("done", False, exception)``."""
    from .progress import report_to

    report_to(lambda *bar: conn.send(("progress", *bar)))
    try:
        reply = ("done", True, task(*args))
    except BaseException as exc:  # noqa: BLE001 - sent to the parent, which raises it
        reply = ("done", False, exc)
    report_to(None)
    try:
        conn.send(reply)
    except Exception as unsent:  # noqa: BLE001 - a result or exception that cannot be pickled
        _, ok, value = reply
        what = "result" if ok else f"{type(value).__name__}: {value}"
        conn.send(
            ("done", False, TaskDied(f"task {index} could not send its {what} ({type(unsent).__name__}: {unsent})"))
        )
    finally:
        conn.close()


def run_forked(
    tasks: Sequence[tuple[Callable[..., Any], tuple]],
    jobs: int,
    names: Sequence[str] | None = None,
    preload: Sequence[str] = (),
) -> list:
    """Run every ``task(*args)`` of ``tasks`` in a forked child, at most ``jobs`` at once in the order given, and
    return their results in that order (module docstring).

    Args:
        tasks: ``(function, arguments)`` pairs; each result and exception must pickle (they return through a pipe).
        jobs: children at once, a positive integer.
        names: what a failure calls each task (default ``task 0``, ``task 1``, …).
        preload: modules imported here first, once, that every child would otherwise import for itself (for
            ``agsf reproduce`` matplotlib and TensorBoard's protocol buffers: 0.3 s a child).

    Raises:
        the first failed task's exception (in task order) once every task has ended; :class:`TaskDied` for a child
        that ended without a reply, naming the task and its exit code.
    """
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    if not fork_available():
        raise RuntimeError("run_forked needs fork (Linux); run the tasks one after another instead")
    names = list(names) if names is not None else [f"task {i}" for i in range(len(tasks))]
    for module in preload:
        importlib.import_module(module)
    context = multiprocessing.get_context("fork")
    results: list[Any] = [None] * len(tasks)
    failures: dict[int, BaseException] = {}
    waiting = list(range(len(tasks)))
    bars = ParentBars()  # the children's progress bars, drawn here on a line each
    running: dict[int, tuple[Any, Any]] = {}  # task → (process, its reply connection)
    for stream in (sys.stdout, sys.stderr):  # a child must not write this process's buffered output again
        stream.flush()
    gc.freeze()  # this process's objects (torch's and matplotlib's modules) left out of the children's collections
    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                index = waiting.pop(0)
                receive, send = context.Pipe(duplex=False)
                process = context.Process(target=_child, args=(send, index, *tasks[index]), name=names[index])
                process.start()
                send.close()
                running[index] = (process, receive)
            ready = multiprocessing.connection.wait([conn for _, conn in running.values()])
            for index in [i for i, (_, conn) in running.items() if conn in ready]:
                process, conn = running[index]
                try:
                    message = conn.recv()
                except (EOFError, OSError):
                    process.join()
                    message = (
                        "done",
                        False,
                        TaskDied(f"{names[index]} ended without a reply (exit code {process.exitcode})"),
                    )
                if message[0] == "progress":
                    bars.update(index, *message[1:])
                    continue
                del running[index]
                conn.close()
                process.join()
                _, ok, value = message
                if ok:
                    results[index] = value
                else:
                    failures[index] = value
    except BaseException:
        _interrupt([process for process, _ in running.values()])
        raise
    finally:
        gc.unfreeze()
        bars.close()
    if failures:
        first = failures[min(failures)]
        if isinstance(first, KeyboardInterrupt):
            raise KeyboardInterrupt
        raise first
    return results


def _interrupt(processes: list) -> None:
    """Interrupt ``processes`` (SIGINT: each removes its temporary files), kill those still running after
    :data:`INTERRUPT_GRACE_S`, and wait for them."""
    for process in processes:
        if process.is_alive() and process.pid is not None:
            try:
                os.kill(process.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
    for process in processes:
        process.join(INTERRUPT_GRACE_S)
        if process.is_alive():
            process.kill()
            process.join()
