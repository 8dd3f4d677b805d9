"""Progress bars on stderr that also read well in a log file.

On a terminal a bar redraws itself in place (``tqdm``).  When stderr is a file or a pipe (``main.sh | tee``,
CI), redrawing in place writes thousands of carriage-return-separated updates into one line; there the bar
writes a plain line instead, at most every :data:`LOG_INTERVAL_S` seconds or :data:`LOG_FRACTION` of the
work, whichever comes first, plus the last one.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable
from typing import Any

__all__ = ["progress_bar", "bars_side_by_side", "at_position", "LOG_INTERVAL_S", "LOG_FRACTION"]

#: Seconds between two progress lines when stderr is not a terminal.
LOG_INTERVAL_S = 10.0
#: Fraction of the work between two progress lines when stderr is not a terminal.
LOG_FRACTION = 0.05
#: The terminal line (0: the first) of this process's bars, when processes show bars side by side.
_position: int | None = None


def bars_side_by_side() -> None:
    """Prepare this process's children to draw bars at once (:func:`at_position`): tqdm's lock, created here, is the
    one every forked child then takes to move the cursor, so that their redraws do not cut into each other."""
    from tqdm.auto import tqdm

    tqdm.get_lock()


def at_position(position: int) -> None:
    """Draw this process's bars on terminal line ``position`` (a forked child's, beside its siblings': tqdm's
    ``position``; elsewhere each line is whole and names its bar)."""
    global _position
    _position = position


class _Lines:
    """A file for tqdm that writes a redraw as one line on ``sys.stderr`` (read at write time, so that
    redirections made after the bar was created are honoured) when ``every`` units or
    :data:`LOG_INTERVAL_S` seconds have passed since the last line, and at the end."""

    def __init__(self, every: int):
        self.every = every
        self.bar = None
        self.last_n: float | None = None
        self.last_time = 0.0

    def write(self, text: str) -> None:
        text = text.replace("\r", "").strip("\n").rstrip()
        if not text.strip():
            return
        bar = self.bar
        now = time.monotonic()
        if bar is not None and self.last_n is not None:
            done = bar.total is not None and bar.n >= bar.total
            due = bar.n - self.last_n >= self.every or now - self.last_time >= LOG_INTERVAL_S
            if bar.n == self.last_n or not (done or due):
                return
        if bar is not None:
            self.last_n, self.last_time = bar.n, now
        sys.stderr.write(text + "\n")

    def flush(self) -> None:
        sys.stderr.flush()


def _is_terminal() -> bool:
    isatty = getattr(sys.stderr, "isatty", None)
    try:
        return bool(isatty and isatty())
    except ValueError:  # a closed stream
        return False


def progress_bar(
    iterable: Iterable[Any] | None = None,
    *,
    desc: str,
    unit: str,
    total: int | None = None,
    disable: bool = False,
    leave: bool = True,
):
    """A ``tqdm`` progress bar over ``iterable`` (or updated by hand) on stderr: redrawn in place on a
    terminal; otherwise one line at most every :data:`LOG_INTERVAL_S` s or :data:`LOG_FRACTION` of ``total``
    (module docstring)."""
    from tqdm.auto import tqdm

    if disable or _is_terminal():
        return tqdm(iterable, desc=desc, unit=unit, total=total, disable=disable, leave=leave, position=_position)
    lines = _Lines(max(1, int(LOG_FRACTION * total)) if total else 1)
    bar = tqdm(
        iterable,
        desc=desc,
        unit=unit,
        total=total,
        leave=True,
        file=lines,
        bar_format="{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}, {rate_fmt}]"
        if total
        else None,
        mininterval=0.0,
        miniters=1,
    )
    lines.bar = bar
    return bar
