"""The tasks of :class:`~.file_writer.FileWriter`: a task's job file run by a worker interpreter, and its reply —
success, or a failure described so that the caller re-raises it as it would have seen it writing the file itself.

A job file holds a pickled ``(write, args)``.  A worker (``python -m agsf_torch.experiments.writer_tasks
MODULE…``) imports the modules named, then runs the job named on each line of its stdin and answers with one JSON
line on its original stdout: ``{"job": file, "error": null}``, or the failure's :func:`describe` fields.  The
caller rebuilds a :class:`Failure` from a reply (a field of the wrong type dropped, so an older or foreign reply is
still an answer) and raises the first with :func:`raise_first`.
"""

from __future__ import annotations

import dataclasses
import json
import os
import pickle
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = ["Failure", "describe", "raise_first", "run_job", "serve"]


@dataclasses.dataclass(frozen=True)
class Failure:
    """A task that failed: the file it writes, ``"Type: message"``, and what re-raises it as the caller would have
    seen it had it written the file itself: ``kind`` (``"os"`` an ``OSError`` with ``errno``, ``strerror`` and
    ``filename``; ``"value"`` a ``ValueError``; ``"other"``)."""

    path: Path
    error: str
    kind: str = "other"
    errno: int | None = None
    strerror: str | None = None
    filename: str | None = None

    @classmethod
    def from_reply(cls, path: Path, reply: dict) -> Failure:
        """From a worker's reply (:func:`describe`'s fields); a field of the wrong type is dropped."""
        fields = _describe_fields(reply)
        return cls(path, str(reply["error"]), **fields)


def describe(exc: BaseException) -> dict[str, Any]:
    """What :class:`Failure` keeps of an exception (a worker sends it in its reply)."""
    if isinstance(exc, OSError) and _valid_errno(exc.errno):
        return {
            "error": f"{type(exc).__name__}: {exc}",
            "kind": "os",
            "errno": exc.errno,
            "strerror": exc.strerror if isinstance(exc.strerror, str) else None,
            "filename": os.fsdecode(exc.filename) if isinstance(exc.filename, (str, bytes)) else None,
        }
    kind = "os" if isinstance(exc, OSError) else "value" if isinstance(exc, ValueError) else "other"
    return {"error": f"{type(exc).__name__}: {exc}", "kind": kind}  # an OSError without a usable errno: "os" alone


def _describe_fields(reply: dict) -> dict[str, Any]:
    """The re-raising fields of a reply, each kept only if it has its type (an older or foreign worker's reply
    lacks them: the failure is then reported as one of an unknown kind)."""
    kind = reply.get("kind") if reply.get("kind") in ("os", "value", "other") else "other"
    errno_ = reply.get("errno") if kind == "os" and _valid_errno(reply.get("errno")) else None
    text = {k: reply.get(k) if isinstance(reply.get(k), str) else None for k in ("strerror", "filename")}
    return {"kind": kind, "errno": errno_, **text}


def _valid_errno(code: Any) -> bool:
    """An errno a system call can report: a positive C int."""
    return isinstance(code, int) and not isinstance(code, bool) and 0 < code < 2**31


def raise_first(failures: list[Failure]) -> None:
    """Raise a failed task's error, naming its file and how many more failed, if any did, as the caller would have
    raised it writing the file itself: an ``OSError`` with its errno, message and file name (the first such, so that
    a full disk is reported as one whatever failed before it), else an ``OSError`` without an errno (errno 0 or
    none), a ``ValueError``, or ``RuntimeError`` for anything else, each naming the file."""
    if not failures:
        return
    first = next((f for f in failures if f.errno is not None), failures[0])
    more = f" ({len(failures) - 1} more files failed)" if len(failures) > 1 else ""
    if first.errno is not None:
        message = f"{first.strerror or os.strerror(first.errno)}{more}"
        if first.filename is not None and Path(first.filename) != first.path:
            message = f"{message}, writing {first.path}"
        raise OSError(first.errno, message, first.filename if first.filename is not None else str(first.path))
    if first.kind == "os":
        raise OSError(f"could not write {first.path}: {first.error}{more}")
    if first.kind == "value":
        raise ValueError(f"could not write {first.path}: {first.error}{more}")
    raise RuntimeError(f"could not write {first.path}: {first.error}{more}")


def run_job(job: str) -> None:
    """Run the task of a job file (the caller removes the file once the task is known to have succeeded: until then
    it may run it again)."""
    write, args = pickle.loads(Path(job).read_bytes())
    write(*args)
    del write, args  # a large task's arguments are freed before the next job is read


def serve(preload: Sequence[str]) -> None:
    """A worker: import ``preload``, then run the task of every job file named on stdin (a JSON string per line),
    one JSON reply per line
    (``{"job": file, "error": null | "Type: message"}``, a failure with :func:`describe`'s fields) on the original
    stdout; anything a task prints goes to
    stderr."""
    import importlib

    replies = os.fdopen(os.dup(1), "w")  # the reply channel; file descriptor 1 (anything a library or a child
    os.dup2(2, 1)  # process writes there) and Python's stdout go to stderr
    sys.stdout = sys.stderr
    if hasattr(os, "register_at_fork"):  # a process a task forks does not hold the reply channel open
        os.register_at_fork(after_in_child=replies.close)
    for module in preload:
        importlib.import_module(module)
    for line in sys.stdin:
        try:
            job = json.loads(line)
        except ValueError:
            continue
        try:
            run_job(job)
            reply = {"job": job, "error": None}
        except Exception as exc:  # noqa: BLE001 - reported to the caller, which raises it naming the file
            reply = {"job": job, **describe(exc)}
        replies.write(json.dumps(reply) + "\n")
        replies.flush()
    # every task answered and its file complete: leave without the interpreter's teardown (half a second with torch
    # and matplotlib loaded, which the caller's close() would wait for)
    for stream in (sys.stderr, sys.__stdout__):
        stream.flush()
    os._exit(0)


if __name__ == "__main__":
    serve(sys.argv[1:])
