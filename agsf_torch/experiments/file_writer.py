"""Writing files — an experiment's figures, event files and ``runs.npz`` — beside the caller while it goes on.

Half of ``agsf reproduce``'s wall time on 2 cores went to writing each case's files before the next case could
start (measured on an AMD EPYC VM: 8.8 of 17 s, of which the 12 figures 6.0 s, ``runs.npz`` 1.4 s, the event
files 1.3 s).  Drawing a figure and encoding events are Python (they hold the interpreter lock), so a thread
cannot overlap them with the next case's filters; another process can.  Both are made from small inputs (a case's
summary, each filter's few event series).

:class:`FileWriter` takes *tasks*: a module-level function that writes one file (atomically, as every writer of
the package does, or one TensorBoard run) and its arguments.  With ``workers=0`` each task runs when it is
submitted, in the caller.  With ``workers=k`` they go to ``k`` worker interpreters started at once, which import
matplotlib and TensorBoard's writer while the caller works (:mod:`.writer_tasks`: a new interpreter, not a
multiprocessing child, so the caller's ``__main__`` is not run again; a task travels as a pickle file in a scratch
folder).  Each worker holds one task at a time; the others wait in the caller's queue.  :meth:`FileWriter.close`
first *helps*: the caller, whose own work is done, runs the queued tasks itself beside the workers; then it waits
for every task and raises a failed task's error naming its file, as the caller would have raised it writing the
file itself (:func:`.writer_tasks.raise_first`).  :meth:`FileWriter.wait_for` waits for one folder's tasks.

A task submitted with ``thread=True`` runs in a thread of the caller instead: for a task whose arguments are too
large to hand over (``runs.npz``'s arrays above :data:`HANDOVER_BYTES`: a copy, gigabytes for a large run) and
which spends its time outside the interpreter lock (compression).  A thread competes with the caller's own work for
the CPUs, a worker does not: on 2 cores ``runs.npz`` in the worker left the next case's filters 0.5 s faster than
in a thread.  A job file is removed once its task has written its file.

Nothing is lost: a task that cannot be handed over (arguments that cannot be pickled, no worker alive) and a task
whose worker died before it reported run in the caller instead.  An error leaving the ``with`` block still lets
the tasks finish (then it propagates: an earlier case's files are complete whatever a later case does); an
interruption (Ctrl-C) stops the workers at once, and a file they had not finished is absent, its temporary file
removed (each file, and each TensorBoard run, is renamed into place only when whole); a thread's file (one at a
time) is completed first.  A worker that exits abnormally is announced as a warning with the last line it wrote to stderr.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import logging
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from ..processes import available_cpus, interpreter_env
from ..storage.files import remove_partial
from . import writer_tasks
from .writer_tasks import Failure, describe, raise_first, run_job

__all__ = [
    "FileWriter",
    "HANDOVER_BYTES",
    "PRELOAD_MODULES",
    "WORKER_MEMORY",
    "too_large_to_hand_over",
    "default_writers",
    "check_writers",
    "writing_beside",
]

logger = logging.getLogger(__name__)

#: What a worker imports before its first task (what drawing a figure and writing TensorBoard events need), while
#: the caller works.
PRELOAD_MODULES = (
    "matplotlib.figure",
    "matplotlib.backends.backend_agg",
    "agsf_torch.experiments.figures",
    "torch.utils.tensorboard",
)
#: The writers with workers running, for the fork hook below.
_OPEN: weakref.WeakSet = weakref.WeakSet()


def _after_fork_in_child() -> None:
    for writer in list(_OPEN):
        writer._close_in_forked_child()
    _OPEN.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)

#: The largest arguments a caller hands to a worker, bytes (``runs.npz``'s arrays: larger ones are written by a
#: thread of the caller, as a copy would cost their size again, in memory and in the scratch folder).
HANDOVER_BYTES = 64 * 2**20
#: A worker's resident memory, bytes: an interpreter with torch, matplotlib and TensorBoard's writer imported
#: (~260 MB measured), with room for a figure's drawing and for a task's arguments (:data:`HANDOVER_BYTES`).
WORKER_MEMORY = 320 * 2**20 + HANDOVER_BYTES


class FileWriter:
    """Runs file-writing tasks inline (``workers=0``) or in ``workers`` worker processes (module docstring).

    Args:
        workers: worker processes (0: every task runs in the caller when submitted).
        preload: modules each worker imports when it starts (default :data:`PRELOAD_MODULES`).
        caller_helps: :meth:`close` runs the queued tasks in the caller beside the workers (``False``: it only waits,
            and every task handed over runs in a worker while one is alive).
    """

    def __init__(
        self, workers: int = 0, preload: Sequence[str] = PRELOAD_MODULES, *, caller_helps: bool = True
    ) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise ValueError(f"workers must be a non-negative integer, got {workers!r}")
        self._caller_helps = bool(caller_helps)
        self._lock = threading.Lock()
        self._jobs: dict[str, tuple[Path, int | None]] = {}  # job file → (the file it writes, worker or None: queued)
        self._queue: deque[str] = deque()  # job files no worker holds yet, in the order submitted
        self._in_hand: dict[int, str | None] = {}  # worker → the job it holds
        self._errors: list[Failure] = []
        self._workers: list[tuple[subprocess.Popen, threading.Thread]] = []
        self._threads: list[tuple[threading.Thread, Path]] = []  # the thread task (at most one) and its file
        self._count = itertools.count()
        self._closed = False
        self._scratch = Path(tempfile.mkdtemp(prefix="agsf-writer-")) if workers else None
        if workers:
            try:
                self._start(workers, preload)
            except BaseException:
                self._shutdown()
                raise

    def _start(self, workers: int, preload: Sequence[str]) -> None:
        """Start the workers and their reply readers."""
        env = interpreter_env(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1")  # one thread each, beside the caller's
        for index in range(workers):
            err = open(self._scratch / f"worker{index}.err", "w")  # noqa: SIM115 - the worker's, kept open by it
            try:
                proc = subprocess.Popen(
                    [sys.executable, "-m", writer_tasks.__name__, *preload],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    stderr=err,
                    text=True,
                    env=env,
                    start_new_session=True,  # Ctrl-C at a terminal reaches the caller, which decides for its workers
                )
            finally:
                err.close()
            reader = threading.Thread(target=self._read, args=(index, proc), daemon=True)
            self._workers.append((proc, reader))
            self._in_hand[index] = None
            reader.start()
        _OPEN.add(self)

    @property
    def background(self) -> bool:
        """Whether tasks run beside the caller: while a worker is alive (without one each runs in the caller)."""
        return self._any_worker_alive()

    def submit(self, write: Callable[..., Any], *args: Any, path: str | Path, thread: bool = False) -> None:
        """Run ``write(*args)``, which writes the file ``path`` (named in a failure's message): now, in the caller,
        without workers; else in a worker (the first free one, in the order submitted), or with ``thread`` in a
        thread of the caller (module docstring)."""
        path = Path(path)
        if self._closed:
            raise ValueError(f"cannot write {path}: this FileWriter is closed")
        if not self._workers:
            write(*args)
            return
        if thread:
            self._join_threads()  # one at a time: each holds its arguments (a large case's arrays) until done
            worker = threading.Thread(target=self._write_here, args=(path, write, *args), name=f"writing {path.name}")
            worker.start()
            self._threads = [(worker, path)]
            return
        job = self._scratch / f"job{next(self._count)}.pkl"
        try:
            job.write_bytes(pickle.dumps((write, args), protocol=pickle.HIGHEST_PROTOCOL))
        except Exception:  # noqa: BLE001 - not picklable (a local function, say): written here instead
            job.unlink(missing_ok=True)
            self._write_here(path, write, *args)
            return
        with self._lock:
            self._jobs[str(job)] = (path, None)
            self._queue.append(str(job))
            self._dispatch()
        if not self._any_worker_alive():  # written here, now
            self._help()

    def _dispatch(self) -> None:
        """Hand queued jobs to the workers that hold none (the caller holds the lock)."""
        for index, (proc, _) in enumerate(self._workers):
            if not self._queue:
                return
            if self._in_hand.get(index, "dead") is not None or proc.poll() is not None:
                continue
            job = self._queue.popleft()
            try:
                proc.stdin.write(json.dumps(job) + "\n")
                proc.stdin.flush()
            except (OSError, ValueError):  # the worker has died (or its pipe is closed): the next one
                self._queue.appendleft(job)
                self._in_hand.pop(index, None)
                continue
            self._in_hand[index] = job
            self._jobs[job] = (self._jobs[job][0], index)

    def _help(self) -> None:
        """Run the queued jobs here, one at a time, while the workers run theirs."""
        while True:
            with self._lock:
                if not self._queue or self._scratch is None:  # nothing queued, or shut down
                    return
                job = self._queue.popleft()
                path, _ = self._jobs.pop(job)
            self._write_here(path, self._run_here, job)

    def _wait_for_queue(self) -> None:
        """Until no job waits for a worker, or no worker is alive to take one (then the caller runs the rest)."""
        while self._queue:
            if not self._any_worker_alive():
                self._help()
                return
            time.sleep(0.01)

    def _any_worker_alive(self) -> bool:
        return any(proc.poll() is None for proc, _ in self._workers)

    def _join_threads(self) -> None:
        """Wait for the thread task (at most one runs)."""
        for worker, _ in self._threads:
            worker.join()
        self._threads = []

    def wait_for(self, folder: str | Path) -> None:
        """Until every task writing inside ``folder`` is done, while the others go on: the queued ones run here (the
        caller would only wait), the workers' are waited for (run here if their worker died before it answered), a
        thread task is joined.  Then the error of a task inside ``folder`` that failed, naming its file and how many
        failed (as :meth:`close` raises it, which does not raise them again).  A sweep waits for one configuration's files before it
        records the configuration as done, while the next one's are still being written."""
        folder = Path(folder)

        def inside(path: Path) -> bool:
            return path == folder or folder in path.parents

        if any(inside(path) for _, path in self._threads):
            self._join_threads()
        while True:
            with self._lock:
                queued = next((job for job in self._queue if inside(self._jobs[job][0])), None)
                if queued is not None:
                    self._queue.remove(queued)
                    path, _ = self._jobs.pop(queued)
                held = [(job, path, index) for job, (path, index) in self._jobs.items() if inside(path)]
            if queued is not None:
                self._write_here(path, self._run_here, queued)
                continue
            if not held:
                break
            for job, path, index in held:
                proc, reader = self._workers[index]
                if proc.poll() is None:
                    continue
                reader.join(timeout=5.0)  # the dead worker's last replies are read before its job is taken back
                with self._lock:
                    unanswered = self._jobs.pop(job, None) is not None
                if unanswered:
                    remove_partial(path)
                    self._write_here(path, self._run_here, job)
            time.sleep(0.005)
        with self._lock:
            failed = [e for e in self._errors if inside(e.path)]
            self._errors = [e for e in self._errors if not inside(e.path)]
        raise_first(failed)

    def _write_here(self, path: Path, write: Callable[..., Any], *args: Any) -> None:
        """Run a task in the caller; its failure is recorded with its file and raised by :meth:`close`."""
        try:
            write(*args)
        except Exception as exc:  # noqa: BLE001 - recorded with its file, raised by close()
            with self._lock:
                self._errors.append(Failure(path, **describe(exc)))

    def _read(self, index: int, proc: subprocess.Popen) -> None:
        """A worker's replies (one JSON line per task), until it exits."""
        try:
            for line in proc.stdout:
                self._take(index, line)
        except (OSError, ValueError):  # the pipe closed under the reader (the writer shut down)
            pass

    def _take(self, index: int, line: str) -> None:
        """Note one reply of worker ``index``: the job done, and its error if it failed; hand it the next."""
        try:
            reply = json.loads(line)
            job, error = reply["job"], reply["error"]
            if not isinstance(job, str) or not (error is None or isinstance(error, str)):
                return
        except Exception:  # noqa: BLE001 - not a reply: ignored; the worker's task is taken back if it dies
            return
        with self._lock:
            path, _ = self._jobs.pop(job, (None, None))
            if path is not None and error is not None:
                self._errors.append(Failure.from_reply(path, reply))
            if self._in_hand.get(index) == job:
                self._in_hand[index] = None
                if not self._closed:
                    self._dispatch()
        if path is not None and error is None:  # written: its arguments no longer take room
            Path(job).unlink(missing_ok=True)

    def _run_here(self, job: str) -> None:
        run_job(job)
        Path(job).unlink(missing_ok=True)

    def close(self) -> None:
        """Run the queued tasks here beside the workers, wait for every task; then the error of a task that failed,
        naming its file and how many failed (module docstring)."""
        try:
            if self._caller_helps:
                self._help()
            self._join_threads()
            self._wait_for_queue()
            with self._lock:
                self._closed = True  # no more jobs handed out
            for proc, _ in self._workers:
                with contextlib.suppress(OSError):
                    proc.stdin.close()
            for index, (proc, reader) in enumerate(self._workers):
                proc.wait()
                reader.join(timeout=5.0)  # a process the task forked may hold the reply pipe: not waited for
                if proc.returncode != 0:
                    lines = (self._scratch / f"worker{index}.err").read_text(errors="replace").strip().splitlines()
                    logger.warning(
                        "a file-writing worker exited with code %s (%s); the caller writes what it had not",
                        proc.returncode,
                        lines[-1] if lines else "no message",
                    )
            with self._lock:
                unanswered = list(self._jobs.items())
            for job, (path, _) in unanswered:  # a worker died before it answered: written here, nothing lost
                remove_partial(path)
                self._write_here(path, self._run_here, job)
                with self._lock:
                    self._jobs.pop(job, None)
        finally:
            self._shutdown()
        errors, self._errors = self._errors, []
        raise_first(errors)

    def _close_in_forked_child(self) -> None:
        """In a child forked by the caller: drop the workers' input pipes, which would otherwise keep the workers
        waiting for input after the caller closes its ends."""
        for proc, _ in self._workers:
            with contextlib.suppress(OSError, ValueError):
                os.close(proc.stdin.fileno())

    def _shutdown(self) -> None:
        """Stop the workers (killed if still running), wait for a thread's file, remove the temporary files of the
        tasks the workers had not finished and the scratch folder."""
        with self._lock:
            self._closed = True
        _OPEN.discard(self)
        for proc, reader in self._workers:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
            reader.join(timeout=5.0)  # at the dead worker's end of file
            # a reader still inside a read (a process the task forked holds the pipe) keeps its stream: closing it
            # would block until that process exits; the daemon reader ends with it
            for stream in (proc.stdin,) if reader.is_alive() else (proc.stdin, proc.stdout):
                with contextlib.suppress(OSError):
                    stream.close()
        self._join_threads()  # a file begun by a thread is completed, not left half written
        with self._lock:
            self._workers = []
            unfinished = [path for path, _ in self._jobs.values()]
            self._jobs.clear()
            self._queue.clear()
            scratch, self._scratch = self._scratch, None
        for path in unfinished:
            remove_partial(path)
        if scratch is not None:
            shutil.rmtree(scratch, ignore_errors=True)

    def __enter__(self) -> FileWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        elif issubclass(exc_type, Exception):  # the caller failed: what it handed over is still written
            try:
                self.close()
            except Exception as failed:  # noqa: BLE001 - the caller's error is the one raised
                logger.warning("%s (while handling %s: %s)", failed, exc_type.__name__, exc)
        else:  # interrupted: stop now
            self._shutdown()
            for failure in self._errors:
                logger.warning("could not write %s: %s (while interrupted)", failure.path, failure.error)
            self._errors = []


def too_large_to_hand_over(arrays: Iterable[Any]) -> bool:
    """Whether a task's arrays exceed :data:`HANDOVER_BYTES` (then they are written by the caller, or a thread of
    it, instead of a copy handed to a worker)."""
    return sum(a.nbytes for a in arrays) > HANDOVER_BYTES


def default_writers() -> int:
    """Worker processes of a command that writes files beside its work (:func:`writing_beside`): one where the
    process may use two CPUs or more, else none (a worker on the only CPU would take its time from the filters)."""
    return 1 if available_cpus() >= 2 else 0


def check_writers(writers: int | None, threads: int | None) -> int:
    """Validate :func:`writing_beside`'s arguments (before a command creates anything) and return the number of
    workers (``None``: :func:`default_writers`).

    Raises:
        ValueError: ``writers`` not an integer from 0 to the CPUs this process may use (each worker is a process),
            or ``threads`` neither None nor a positive integer.
    """
    writers, cpus = default_writers() if writers is None else writers, available_cpus()
    if isinstance(writers, bool) or not isinstance(writers, int) or not 0 <= writers <= cpus:
        raise ValueError(f"writers must be an integer from 0 to the {cpus} CPUs this process may use, got {writers!r}")
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValueError(f"threads must be a positive integer or None, got {threads!r}")
    return writers


@contextlib.contextmanager
def writing_beside(writers: int | None = None, threads: int | None = None):
    """A :class:`FileWriter` with ``writers`` workers (:func:`check_writers`), this process running ``threads`` torch
    threads meanwhile (default: torch's, capped so that they and the workers fit the CPUs), restored afterwards.
    ``agsf reproduce`` writes a case's files beside the next case with it, a local sweep a configuration's."""
    import torch

    writers = check_writers(writers, threads)
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(threads or max(1, min(before, available_cpus() - writers)))
        with FileWriter(writers) as writer:
            yield writer
    finally:
        torch.set_num_threads(before)
