"""Safe files: atomic writes, complete appended lines, tolerant reading of an interrupted log.

Every file the package writes goes through here, so that an interruption
(Ctrl-C, ``SIGKILL``, a full disk, a power cut) never leaves a torn file behind:

* :func:`atomic_open` / :func:`write_text` / :func:`write_json` write to a hidden
  temporary file in the destination's folder, flush it to disk and rename it into
  place (``os.replace``, atomic on POSIX and Windows): a reader sees the old file
  or the new one, never a mixture.  A failed write removes its temporary file.
* :func:`append_line` appends one complete line with a single ``write`` on a file
  opened for appending, then flushes it to disk.
* :func:`read_json_lines` reads such a log; a torn *last* line (an interruption
  between the two steps above, or a file cut short) is skipped with a warning naming
  the file, and :func:`repair_json_lines` removes it before the next append.  A bad
  line anywhere else is corruption and raises ``ValueError`` naming file and line.
* :func:`read_json` raises ``ValueError`` naming the file for unreadable JSON.
* :func:`json_text` is the one serialiser: strict JSON (RFC 8259), an undefined number
  (NaN, ±inf) written as ``null``, never as the bare ``NaN`` other parsers refuse.
* :func:`files_written` counts the files this process has put into place and the lines it has appended: a
  command that fails tells by it whether it had begun writing (the ``agsf`` command's exit status).
"""

from __future__ import annotations

import glob
import json
import math
import os
import secrets
import shutil
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

__all__ = [
    "temporary_name",
    "remove_partial",
    "atomic_open",
    "write_text",
    "write_json",
    "save_figure",
    "append_line",
    "json_text",
    "read_json",
    "read_json_lines",
    "repair_json_lines",
    "files_written",
]

#: Files :func:`atomic_open` has put into place and lines :func:`append_line` has appended, in this process.
_written = 0


def files_written() -> int:
    """How many files (:func:`atomic_open` and the functions built on it) this process has put into place and how
    many lines (:func:`append_line`) it has appended: a caller compares two counts to tell whether anything was
    written between them."""
    return _written


def _count_written() -> None:
    global _written
    _written += 1


def temporary_name(path: str | Path) -> Path:
    """A hidden name beside ``path`` to write it under until it is whole (``.NAME.{12 hex digits}.tmp``), unique:
    concurrent writers never share one.  :func:`atomic_open` writes files under it, TensorBoard runs are written in
    a folder of that name."""
    path = Path(path)
    return path.with_name(f".{path.name}.{secrets.token_hex(6)}.tmp")


def remove_partial(path: str | Path) -> None:
    """Remove what a killed writer left of ``path``: the file or folder of its :func:`temporary_name` (exactly
    that pattern: ``.data.csv.….tmp`` is not ``data``'s)."""
    path = Path(path)
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.{'[0-9a-f]' * 12}.tmp"):
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            tmp.unlink(missing_ok=True)


@contextmanager
def atomic_open(path: str | Path, mode: str = "wb") -> Iterator[IO]:
    """Open a temporary file beside ``path`` for writing; on a clean exit, move it to ``path``.

    ``mode`` is ``"wb"`` or ``"w"`` (text, UTF-8).  If the block raises, ``path`` is
    left as it was and the temporary file is removed (a killed process may leave a hidden
    ``.NAME.*.tmp`` beside ``path``; ``path`` itself is never torn).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_open writes whole files: mode must be 'wb' or 'w', got {mode!r}")
    path = Path(path)
    tmp = temporary_name(path)
    try:
        with open(tmp, mode.replace("w", "x"), **({"encoding": "utf-8"} if mode == "w" else {})) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        _count_written()
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def write_text(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns ``path``."""
    with atomic_open(path, "w") as fh:
        fh.write(text)
    return Path(path)


def _strict(obj: Any) -> Any:
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_strict(v) for v in obj]
    return obj


def json_text(obj: Any, **dumps_kwargs: Any) -> str:
    """``json.dumps(obj, **dumps_kwargs)`` as strict JSON: every non-finite float (NaN, ±inf; also inside
    dicts, lists and tuples) becomes ``null``, and ``allow_nan=False`` refuses any left (e.g. from a
    ``default=`` hook)."""
    return json.dumps(_strict(obj), allow_nan=False, **dumps_kwargs)


def write_json(path: str | Path, obj: Any, **dumps_kwargs: Any) -> Path:
    """Write :func:`json_text` of ``obj`` to ``path`` atomically; returns ``path``."""
    return write_text(path, json_text(obj, **dumps_kwargs))


def save_figure(fig: Any, path: str | Path, **savefig_kwargs: Any) -> Path:
    """``fig.savefig`` (a matplotlib figure) written atomically, in the format of ``path``'s suffix."""
    path = Path(path)
    with atomic_open(path) as fh:
        fig.savefig(fh, format=path.suffix.lstrip(".") or "png", **savefig_kwargs)
    return path


def append_line(path: str | Path, line: str) -> None:
    """Append ``line`` and a newline to ``path`` as one write, flushed to disk.

    Raises:
        ValueError: ``line`` contains a newline (it would read back as two records).
    """
    if "\n" in line or "\r" in line:
        raise ValueError("append_line: the line must not contain a newline")
    data = (line + "\n").encode("utf-8")
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
    try:
        written = os.write(fd, data)
        if written != len(data):  # a short write (full disk): the reader treats it as a torn last line
            raise OSError(f"{path}: short write ({written} of {len(data)} bytes)")
        os.fsync(fd)
        _count_written()
    finally:
        os.close(fd)


def read_json(path: str | Path, what: str = "file") -> Any:
    """Parse the JSON file ``path``.

    Raises:
        ValueError: naming ``what`` and ``path`` if it is not valid UTF-8 JSON (e.g. truncated).
    """
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{what} {path} is corrupt ({exc})") from None


def _split_records(path: Path) -> tuple[list[Any], bool]:
    """``(records, torn)``: the parsed complete lines, and whether a torn last line was found."""
    text = path.read_bytes().decode("utf-8", errors="replace")
    lines = text.split("\n")
    complete, tail = lines[:-1], lines[-1]  # ``tail`` is what follows the last newline
    records, torn = [], bool(tail.strip())
    for number, line in enumerate(complete, 1):
        if not line.strip():
            continue
        try:
            records.append(json.loads(line))
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: line {number} is not valid JSON ({exc}); the file is corrupt") from None
    if torn:
        try:
            records.append(json.loads(tail))  # a complete record missing only its newline
            torn = False
        except json.JSONDecodeError:
            pass
    return records, torn


def read_json_lines(path: str | Path) -> list[Any]:
    """Records of a JSON-lines file (``[]`` if it does not exist).

    A torn last line is skipped with a ``RuntimeWarning`` naming the file.

    Raises:
        ValueError: a line other than the last is not valid JSON.
    """
    path = Path(path)
    if not path.exists():
        return []
    records, torn = _split_records(path)
    if torn:
        warnings.warn(f"{path}: skipped a torn last line (an interrupted write)", RuntimeWarning, stacklevel=2)
    return records


def repair_json_lines(path: str | Path) -> list[Any]:
    """:func:`read_json_lines`, then rewrite the file (atomically) without a torn last line and
    with a newline after the last record, so that :func:`append_line` can follow."""
    path = Path(path)
    if not path.exists():
        return []
    raw = path.read_bytes()
    records, torn = _split_records(path)
    if torn:
        warnings.warn(f"{path}: removed a torn last line (an interrupted write)", RuntimeWarning, stacklevel=2)
    if torn or (raw and not raw.endswith(b"\n")):
        write_text(path, "".join(json_text(r) + "\n" for r in records))
    return records
