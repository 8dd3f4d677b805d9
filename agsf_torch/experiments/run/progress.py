"""Progress bars on stderr that also read well in a log file.

On a terminal a bar redraws itself in place (``tqdm``).  When stderr is a file or a pipe (``main.sh | tee``,
CI), redrawing in place writes thousands of carriage-return-separated updates into one line; there the bar
writes a plain line instead, at most every :data:`LOG_INTERVAL_S` seconds or :data:`LOG_FRACTION` of the
work, whichever comes first, plus the last one.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Iterable
from typing import Any

__all__ = [
    "progress_bar",
    "report_to",
    "forget_parent_bars",
    "ParentBars",
    "LOG_INTERVAL_S",
    "LOG_FRACTION",
    "REPORT_FRACTION",
]

#: Seconds between two progress lines when stderr is not a terminal.
LOG_INTERVAL_S = 10.0
#: Fraction of the work between two progress lines when stderr is not a terminal.
LOG_FRACTION = 0.05
#: Where this process's bars go instead of stderr: a forked child's reports to its parent (:func:`report_to`).
_report: Callable[[str, str, int | None, int], None] | None = None


def report_to(send: Callable[[str, str, int | None, int], None] | None) -> None:
    """Make this process's bars (a forked child's, :mod:`agsf_torch.experiments.run.worker_pool`) call ``send(desc, unit, total, n)`` as they advance
    (at most every :data:`REPORT_FRACTION` of the work, and at the end) instead of drawing on stderr: their parent
    draws them all (:class:`ParentBars`), since processes that each redraw a terminal line of their own move one
    another's cursor.  ``None``: draw them here again."""
    global _report
    _report = send


#: Fraction of the work between two reports of a forked child's bar.
REPORT_FRACTION = 0.01


def forget_parent_bars() -> None:
    """In a forked child: drop the bars and the lock its parent's tqdm held at the fork (a child forked while the
    parent draws its siblings' bars would otherwise redraw copies of them, or wait on a lock held at the fork)."""
    from tqdm.auto import tqdm

    tqdm._instances.clear()
    for cls in tqdm.__mro__:  # the lock lives on the class that first took it: tqdm.write sets it on tqdm.std's
        if "_lock" in vars(cls):
            delattr(cls, "_lock")


class _Reported:
    """A bar that reports its progress (:func:`report_to`): iterates over ``iterable``, or is advanced by
    :meth:`update`, and reports when closed."""

    def __init__(self, iterable, desc: str, unit: str, total: int | None, send) -> None:
        self.iterable, self.desc, self.unit, self.total, self.n = iterable, desc, unit, total, 0
        self._send, self._every, self._last = send, max(1, int(REPORT_FRACTION * total)) if total else 1, 0
        self._report(force=True)  # the parent's bar starts when the work does

    def _report(self, force: bool = False) -> None:
        if force or self.n - self._last >= self._every:
            self._last = self.n
            self._send(self.desc, self.unit, self.total, self.n)

    def __iter__(self):
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def update(self, n: int = 1) -> None:
        self.n += n
        self._report()

    def close(self) -> None:
        if self.n != self._last:
            self._report(force=True)

    def __enter__(self) -> _Reported:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class ParentBars:
    """The bars of forked children, drawn by their parent: one per child and description, on the child's line
    (``position``), from the reports :func:`report_to` sends."""

    def __init__(self) -> None:
        self._bars: dict[tuple[int, str], Any] = {}

    def update(self, child: int, desc: str, unit: str, total: int | None, n: int) -> None:
        """Child ``child``'s bar ``desc`` has done ``n`` of ``total`` ``unit``."""
        key = (child, desc)
        if key not in self._bars:
            self._bars[key] = progress_bar(desc=desc, unit=unit, total=total, position=child)
        bar = self._bars[key]
        bar.update(n - bar.n)

    def close(self) -> None:
        """Close every bar, the first child's first (each is left on its line)."""
        for key in sorted(self._bars):
            self._bars[key].close()
        self._bars = {}


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
    position: int | None = None,
):
    """A ``tqdm`` progress bar over ``iterable`` (or updated by hand) on stderr: redrawn in place on a
    terminal (on line ``position`` of the bars this process draws); otherwise one line at most every
    :data:`LOG_INTERVAL_S` s or :data:`LOG_FRACTION` of ``total`` (module docstring).  In a forked child that
    reports to its parent (:func:`report_to`) the bar is the parent's to draw."""
    from tqdm.auto import tqdm

    if _report is not None and not disable:
        return _Reported(iterable, desc, unit, total, _report)
    if disable or _is_terminal():
        return tqdm(iterable, desc=desc, unit=unit, total=total, disable=disable, leave=leave, position=position)
    lines = _Lines(max(1, int(LOG_FRACTION * total)) if total else 1)
    bar = tqdm(
        iterable,
        desc=desc,
        unit=unit,
        total=total,
        leave=True,
        file=lines,
        position=0,  # whole lines, never a cursor move, however many bars are open
        bar_format="{desc}: {percentage:3.0f}% {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}, {rate_fmt}]"
        if total
        else None,
        mininterval=0.0,
        miniters=1,
    )
    lines.bar = bar
    return bar
