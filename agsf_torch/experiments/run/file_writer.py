"""Writing files — an experiment's figures, event files and ``runs.npz`` — beside the caller while it goes on.

Drawing a figure and encoding events are Python (they hold the interpreter lock), so a thread cannot overlap them
with the next case's filters; another process can.  :class:`FileWriter` takes *tasks*: a module-level function that
writes one file (atomically, as every writer of the package does, or one TensorBoard run) and its arguments.  With
``workers=0`` each task runs when it is submitted, in the caller; with ``workers=k`` in a
:class:`~agsf_torch.experiments.run.worker_pool.WorkerPool` of ``k`` forked workers (one torch thread each, matplotlib and TensorBoard's writer
imported while the caller works), in the order submitted.  :meth:`FileWriter.close` waits for every task and
raises the first failed task's error as the task raised it — what the caller would have raised writing the file
itself; :meth:`FileWriter.wait_for` does the same for one folder's tasks.

Kept beside the executor, because the commands need it:

* a task submitted with ``thread=True`` runs in a thread of the caller instead, one at a time: arguments too large
  to hand over (``runs.npz``'s arrays above :data:`HANDOVER_BYTES`) would cost their size again as a copy;
* an error leaving the ``with`` block still lets the tasks finish (then it propagates: an earlier case's files are
  complete whatever a later case does); an interruption (Ctrl-C) cancels the tasks not started and interrupts the
  running ones (:meth:`~agsf_torch.experiments.run.worker_pool.WorkerPool.stop`), and a file they had not finished is absent, its temporary file
  removed; a thread's file is completed first.  A worker that dies is :class:`~agsf_torch.experiments.run.worker_pool.TaskDied`, naming the file it
  was writing and its exit code.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from ...storage.files import remove_partial
from .worker_pool import WorkerPool, fork_available

__all__ = [
    "FileWriter",
    "HANDOVER_BYTES",
    "PRELOAD_MODULES",
    "WORKER_MEMORY",
    "too_large_to_hand_over",
    "default_writers",
    "check_threads",
    "writing_beside",
]

logger = logging.getLogger(__name__)

#: What a worker imports when it starts (what drawing a figure and writing TensorBoard events need), while the
#: caller works.
PRELOAD_MODULES = (
    "matplotlib.figure",
    "matplotlib.backends.backend_agg",
    "agsf_torch.experiments.report.figures",
    "torch.utils.tensorboard",
)
#: The largest arguments a caller hands to a worker, bytes (``runs.npz``'s arrays: larger ones are written by a
#: thread of the caller, as a copy would cost their size again).
HANDOVER_BYTES = 64 * 2**20
#: A worker's resident memory, bytes: an interpreter with torch, matplotlib and TensorBoard's writer imported
#: (~260 MB measured), with room for a figure's drawing and for a task's arguments (:data:`HANDOVER_BYTES`).
WORKER_MEMORY = 320 * 2**20 + HANDOVER_BYTES


class FileWriter:
    """Runs file-writing tasks inline (``workers=0``, or where fork is not available: :func:`agsf_torch.experiments.run.worker_pool.fork_available`)
    or in ``workers`` worker processes (module docstring).

    Args:
        workers: worker processes (0: every task runs in the caller when submitted).
        preload: modules each worker imports when it starts (default :data:`PRELOAD_MODULES`).
    """

    def __init__(self, workers: int = 0, preload: Sequence[str] = PRELOAD_MODULES) -> None:
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 0:
            raise ValueError(f"workers must be a non-negative integer, got {workers!r}")
        self._pool = WorkerPool(workers, preload=preload) if workers and fork_available() else None
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="agsf-writer") if self._pool else None
        self._tasks: dict[Future, Path] = {}  # every task not yet waited for, in the order submitted
        self._thread_task: Future | None = None
        self._closed = False
        if self._pool is not None:
            self._pool.submit(os.getpid)  # the workers forked now, before the caller runs anything threaded

    @property
    def background(self) -> bool:
        """Whether tasks run beside the caller (without workers each runs in the caller when submitted)."""
        return self._pool is not None

    def submit(self, write: Callable[..., Any], *args: Any, path: str | Path, thread: bool = False) -> None:
        """Run ``write(*args)``, which writes the file ``path``: now, in the caller, without workers; else in a
        worker, or with ``thread`` in a thread of the caller once the previous thread task is done."""
        path = Path(path)
        if self._closed:
            raise ValueError(f"cannot write {path}: this FileWriter is closed")
        if self._pool is None:
            write(*args)
            return
        if thread:
            if self._thread_task is not None:
                wait([self._thread_task])  # one at a time: each holds its arguments (a case's arrays) until done
            future = self._thread_task = self._thread.submit(write, *args)
        else:
            try:
                future = self._pool.submit(write, *args)
            except BrokenProcessPool:
                self._raise_died(path)
        self._tasks[future] = path

    def wait_for(self, folder: str | Path) -> None:
        """Until every task writing inside ``folder`` is done, while the others go on; then the first error of a
        task inside ``folder`` (which :meth:`close` does not raise again).  A sweep waits for one configuration's
        files before it records the configuration as done, while the next one's are still being written."""
        folder = Path(folder)
        self._finish([f for f, path in self._tasks.items() if path == folder or folder in path.parents])

    def _finish(self, futures: list[Future]) -> None:
        """Wait for ``futures``, forget them, and raise the first failed one's error (in the order submitted)."""
        wait(futures)
        failed = [f.exception() for f in futures if f.exception() is not None]
        if any(isinstance(error, BrokenProcessPool) for error in failed):
            self._raise_died()
        for future in futures:
            del self._tasks[future]
        if failed:
            raise failed[0]

    def _raise_died(self, path: Path | None = None) -> None:
        """A worker died: wait for the pool to stop the others, remove what the lost tasks left, and raise
        :class:`~agsf_torch.experiments.run.worker_pool.TaskDied` naming the first lost file (or ``path``)."""
        self._pool.shutdown(wait=True)
        lost = [p for f, p in self._tasks.items() if f.done() and isinstance(f.exception(), BrokenProcessPool)]
        for partial in lost:
            remove_partial(partial)
        self._tasks = {f: p for f, p in self._tasks.items() if p not in lost}
        raise self._pool.died(f"the process writing {lost[0] if lost else path}") from None

    def close(self) -> None:
        """Wait for every task; then the first failed task's error (module docstring).  Closing again does nothing."""
        if self._closed:
            return
        self._closed = True
        try:
            self._finish(list(self._tasks))
        except Exception:
            self._shutdown()
            raise
        except BaseException:
            self.stop()
            raise
        self._shutdown()

    def stop(self) -> None:
        """Interrupted: cancel the tasks not started, interrupt the workers' running ones, complete a thread's file,
        and remove the temporary files of the tasks not finished."""
        self._closed = True
        if self._pool is None:
            return
        self._pool.stop()
        self._thread.shutdown(wait=True, cancel_futures=True)
        for path in self._tasks.values():  # a killed worker's temporary file (a whole file is left as it is)
            remove_partial(path)
        self._tasks.clear()

    def _shutdown(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._thread.shutdown(wait=True)

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
            self.stop()


def too_large_to_hand_over(arrays: Iterable[Any]) -> bool:
    """Whether a task's arrays exceed :data:`HANDOVER_BYTES` (then they are written by the caller, or a thread of
    it, instead of a copy handed to a worker)."""
    return sum(a.nbytes for a in arrays) > HANDOVER_BYTES


def default_writers() -> int:
    """Worker processes of a command that writes files beside its work (:func:`writing_beside`): one where fork is
    available and the process may use two CPUs or more, else none (a worker on the only CPU would take its time from
    the filters)."""
    import joblib

    return 1 if joblib.cpu_count(only_physical_cores=False) >= 2 and fork_available() else 0


def check_threads(threads: int | None) -> None:
    """Refuse ``threads`` (torch threads of a command) that is neither None nor a positive integer."""
    if threads is not None and (isinstance(threads, bool) or not isinstance(threads, int) or threads < 1):
        raise ValueError(f"threads must be a positive integer or None, got {threads!r}")


@contextlib.contextmanager
def writing_beside(threads: int | None = None):
    """A :class:`FileWriter` with :func:`default_writers` workers, this process running ``threads`` torch threads
    meanwhile (default: torch's, capped so that they and the workers fit the CPUs), restored afterwards.  ``agsf
    reproduce --jobs 1`` writes a case's files beside the next case with it, a local sweep a configuration's."""
    import torch

    check_threads(threads)
    writers = default_writers()
    import joblib

    before = torch.get_num_threads()
    with FileWriter(writers) as writer:
        try:
            torch.set_num_threads(threads or max(1, min(before, joblib.cpu_count(only_physical_cores=False) - writers)))
            yield writer
        finally:
            torch.set_num_threads(before)
