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
interrupted too (each removes its unfinished temporary files) and the interruption propagates.  A child takes
SIGTERM and SIGHUP as it takes Ctrl-C (``timeout`` and a service manager signal every process of the command).
A child's progress bars are drawn by the parent, each child's on a line of its own (:func:`.progress.report_to`):
processes that each redraw a terminal line move one another's cursor.
"""

from __future__ import annotations

import gc
import importlib
import multiprocessing
import multiprocessing.connection
import os
import pickle
import signal
import sys
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any

from .progress import ParentBars

__all__ = ["fork_available", "run_forked", "TaskDied"]

#: Seconds an interrupted child has to remove its temporary files before it is killed.
INTERRUPT_GRACE_S = 5.0
#: Seconds between two looks at pending signals while the children run.
WAKE_S = 0.1


class TaskDied(RuntimeError):
    """A forked task's process ended without a reply (killed, or out of memory), or its reply could not be read."""


class ChildTraceback(Exception):
    """The traceback of a task's exception in its child (the ``__cause__`` of the exception :func:`run_forked`
    raises, as :mod:`concurrent.futures` attaches it)."""


def fork_available() -> bool:
    """Whether tasks can run in forked children: on Linux (elsewhere fork is absent, or unsafe with the system's
    frameworks), from the main thread (Ctrl-C reaches the main thread, which passes it on to the children)."""
    return (
        sys.platform.startswith("linux")
        and "fork" in multiprocessing.get_all_start_methods()
        and threading.current_thread() is threading.main_thread()
    )


#: The signals that interrupt a child's task: Ctrl-C's, and SIGTERM and SIGHUP, which end the ``agsf`` command as
#: Ctrl-C does (:func:`.cli_terminal.ending_signals`).
_INTERRUPTING = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
#: In a child, the signal that interrupted its task (empty in the parent, so every child starts without one).
_interrupted_by: list[int] = []


def _interrupted_once(signum: int, frame: Any) -> None:
    """A child's handler of :data:`_INTERRUPTING`: the first signal interrupts the task; later ones (a terminal's
    Ctrl-C, or ``timeout``'s SIGTERM, reaches the whole process group, then the parent passes it on) are ignored,
    so that the task's clean-up is not cut short.  Ignored here rather than by ``SIG_IGN``: a signal already pending
    when its handler is set to ``SIG_IGN`` is reported by Python as one "ignored due to race condition"."""
    if _interrupted_by:
        return
    _interrupted_by.append(signum)
    raise KeyboardInterrupt


def _sendable(exc: BaseException) -> BaseException:
    """``exc`` if it survives a pickle round trip, else the nearest builtin exception with its message (an
    ``OSError`` keeps its errno, message and file name), so that the parent raises what the task raised."""
    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - any failure to pickle or to rebuild it
        pass
    text = f"{type(exc).__name__}: {exc}"
    if isinstance(exc, OSError):
        return OSError(exc.errno, exc.strerror or str(exc), exc.filename) if exc.errno else OSError(text)
    for kind in (ValueError, KeyboardInterrupt):
        if isinstance(exc, kind):
            return kind(str(exc))
    return RuntimeError(text)


def _child(conn: Any, index: int, task: Callable[..., Any], args: tuple) -> None:
    """A child's body: run the task, its progress bars reported to the parent (``("progress", desc, unit, total,
    n)``), then send ``("done", True, result, None)`` or ``("done", False, exception, traceback text)``."""
    from .progress import forget_parent_bars, report_to

    for interrupting in _INTERRUPTING:
        # a signal the command was started ignoring stays ignored (SIGHUP under nohup)
        if interrupting == signal.SIGINT or signal.getsignal(interrupting) is not signal.SIG_IGN:
            signal.signal(interrupting, _interrupted_once)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _INTERRUPTING)  # blocked by the parent around the fork
    forget_parent_bars()
    report_to(lambda *bar: conn.send(("progress", *bar)))
    try:
        reply = ("done", True, task(*args), None)
    except BaseException as exc:  # noqa: BLE001 - sent to the parent, which raises it
        reply = ("done", False, _sendable(exc), traceback.format_exc())
    report_to(None)
    try:
        conn.send(reply)
    except Exception as unsent:  # noqa: BLE001 - a result that cannot be pickled
        conn.send(
            (
                "done",
                False,
                TaskDied(f"task {index} could not send its result ({type(unsent).__name__}: {unsent})"),
                None,
            )
        )
    finally:
        conn.close()


def run_forked(
    tasks: Sequence[tuple[Callable[..., Any], tuple]],
    jobs: int,
    names: Sequence[str] | None = None,
    preload: Sequence[str] = (),
    on_result: Callable[[int, Any], None] | None = None,
) -> list:
    """Run every ``task(*args)`` of ``tasks`` in a forked child, at most ``jobs`` at once in the order given, and
    return their results in that order (module docstring).  Call it from the main thread (:func:`fork_available`)
    before this process has run a parallel torch operation: a child inherits OpenMP's state without its threads,
    so a task should run one torch thread (``agsf reproduce`` sets that in each case's process).

    Args:
        tasks: ``(function, arguments)`` pairs; each result must pickle (it returns through a pipe); an exception
            that does not is raised as the nearest builtin exception with its message.
        jobs: children at once, a positive integer.
        names: what a failure calls each task (default ``task 0``, ``task 1``, …).
        preload: modules imported here first, once, that every child would otherwise import for itself (for
            ``agsf reproduce`` matplotlib and TensorBoard's protocol buffers: 0.3 s a child).
        on_result: called here with ``(task index, result)`` as each task succeeds (``agsf reproduce`` writes the
            case's HParams session then, so that a later case's failure leaves the earlier ones complete).

    Raises:
        the first failed task's exception (in task order; its traceback in the child as its ``__cause__``) once
        every task has ended; :class:`TaskDied` for a child that ended without a reply, naming the task and its
        exit code.
    """
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise ValueError(f"jobs must be a positive integer, got {jobs!r}")
    if not fork_available():
        raise RuntimeError("run_forked needs fork (Linux) and the main thread; run the tasks one after another instead")
    names = list(names) if names is not None else [f"task {i}" for i in range(len(tasks))]
    for module in preload:
        importlib.import_module(module)
    context = multiprocessing.get_context("fork")
    results: list[Any] = [None] * len(tasks)
    failures: dict[int, tuple[BaseException, str | None]] = {}
    waiting = list(range(len(tasks)))
    bars = ParentBars()  # the children's progress bars, drawn here on a line each
    running: dict[int, tuple[Any, Any]] = {}  # task → (process, its reply connection)
    _flush_standard_streams()  # a child must not write this process's buffered output again
    frozen_before = gc.get_freeze_count() > 0
    gc.freeze()  # this process's objects (torch's and matplotlib's modules) left out of the children's collections
    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                index = waiting.pop(0)
                receive, send = context.Pipe(duplex=False)
                process = context.Process(target=_child, args=(send, index, *tasks[index]), name=names[index])
                # the interrupting signals held back across the fork: the child installs its own handlers first (a
                # signal meanwhile is delivered here once unblocked, and passed on)
                signal.pthread_sigmask(signal.SIG_BLOCK, _INTERRUPTING)
                try:
                    process.start()
                finally:
                    signal.pthread_sigmask(signal.SIG_UNBLOCK, _INTERRUPTING)
                send.close()
                running[index] = (process, receive)
            # with a timeout: a Ctrl-C that the kernel hands to another thread of this process is raised here only
            # when this thread runs Python again (a wait without one would sleep through it)
            ready = multiprocessing.connection.wait([conn for _, conn in running.values()], timeout=WAKE_S)
            for index in [i for i, (_, conn) in running.items() if conn in ready]:
                process, conn = running[index]
                try:
                    message = conn.recv()
                except Exception as exc:  # noqa: BLE001 - no reply (EOF), or one that cannot be read
                    process.join()
                    why = (
                        "ended without a reply"
                        if isinstance(exc, EOFError)
                        else f"sent a reply that cannot be read ({type(exc).__name__}: {exc})"
                    )
                    message = ("done", False, TaskDied(f"{names[index]} {why} (exit code {process.exitcode})"), None)
                if message[0] == "progress":
                    bars.update(index, *message[1:])
                    continue
                del running[index]
                conn.close()
                process.join()
                _, ok, value, trace = message
                if ok:
                    results[index] = value
                    if on_result is not None:
                        on_result(index, value)
                else:
                    failures[index] = (value, trace)
    except BaseException:
        _interrupt([process for process, _ in running.values()])
        raise
    finally:
        if not frozen_before:  # a caller's own freeze is left as it was
            gc.unfreeze()
        bars.close()
    if failures:
        first, trace = failures[min(failures)]
        if isinstance(first, KeyboardInterrupt):
            raise KeyboardInterrupt
        raise first from (ChildTraceback(f"in {names[min(failures)]}'s process:\n{trace}") if trace else None)
    return results


def _flush_standard_streams() -> None:
    """Flush stdout and stderr where they are open (a closed stream, or one whose reader is gone, is skipped)."""
    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            try:
                stream.flush()
            except (OSError, ValueError):
                pass


def _interrupt(processes: list) -> None:
    """Interrupt ``processes`` (one SIGINT: each removes its temporary files), kill those still running
    :data:`INTERRUPT_GRACE_S` after, and wait for them."""
    for process in processes:
        if process.is_alive() and process.pid is not None:
            try:
                os.kill(process.pid, signal.SIGINT)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + INTERRUPT_GRACE_S
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join()
