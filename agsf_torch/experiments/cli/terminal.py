"""The ``agsf`` command's terminal: argument types, one-line errors, messages and the TensorBoard hint.

Argument types refuse bad values with argparse's one-line error; :class:`Parser` prints
every argument error as one line (exit 2), like every other refusal; :func:`one_line`
folds an exception into one line naming the file; :func:`messages` shows the package's
INFO messages on stderr (through ``tqdm.write``, so progress bars stay intact) and
filters the dependencies' warnings that are not the user's concern; :func:`ending_signals` makes SIGTERM and
SIGHUP end a command as Ctrl-C does, and :func:`interruption` says which of them ended it.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import signal
import sys
import threading
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from ...torch_internals import torch_internal_deprecations_hidden

__all__ = [
    "FORCE_HELP",
    "Parser",
    "integer",
    "positive_int",
    "positive_float",
    "nonnegative_float",
    "seed",
    "one_line",
    "messages",
    "tensorboard_command",
    "ENDING_SIGNALS",
    "ending_signals",
    "interruption",
]


def _parse(text: str, kind: type, what: str):
    """``kind(text)``, or argparse's one-line error saying it ``must be {what}``."""
    try:
        return kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be {what}, got {text!r}") from None


def integer(text: str) -> int:
    """An integer argument."""
    return _parse(text, int, "an integer")


def positive_int(text: str) -> int:
    """An integer argument ≥ 1."""
    value = integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be a positive integer, got {text}")
    return value


def nonnegative_int(text: str) -> int:
    """An integer argument ≥ 0."""
    value = integer(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be an integer ≥ 0, got {text}")
    return value


def positive_float(text: str) -> float:
    """A finite number argument > 0."""
    value = _parse(text, float, "a number")
    if not np.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite positive number, got {text}")
    return value


def nonnegative_float(text: str) -> float:
    """A finite number argument ≥ 0."""
    value = _parse(text, float, "a number")
    if not np.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number ≥ 0, got {text}")
    return value


def seed(text: str) -> int:
    """A run seed argument in ``[0, MAX_SEED]`` (:data:`agsf_torch.experiments.config.loader.MAX_SEED`)."""
    from ..config.loader import MAX_SEED

    value = integer(text)
    if not 0 <= value <= MAX_SEED:
        raise argparse.ArgumentTypeError(f"must be an integer in [0, {MAX_SEED}], got {text}")
    return value


def tensorboard_command(logdir: str | Path) -> str:
    """The shell command that opens TensorBoard on ``logdir`` with the ``tensorboard`` of this
    Python's environment: the executable next to ``sys.executable`` (e.g. ``.venv/bin/tensorboard``,
    which need not be on ``PATH``) if it exists, else ``python -m tensorboard.main``."""
    exe = Path(sys.executable).parent / "tensorboard"
    program = [str(exe)] if exe.is_file() else [sys.executable, "-m", "tensorboard.main"]
    return shlex.join([*program, "--logdir", str(logdir)])


FORCE_HELP = "run even if the memory estimate exceeds the memory available"


def key_value(option: str, example: str):
    """An argparse ``type`` for ``option KEY=VALUE``: a word without ``=`` (``--set runs 8``, whose ``8``
    argparse would only call an unrecognized argument) is refused naming the form, e.g. ``--set runs=8``."""

    def parse(text: str) -> str:
        if "=" not in text:
            key = text.strip() or "KEY"
            raise argparse.ArgumentTypeError(
                f"{text!r} is not KEY=VALUE: write the key, '=' and the value as one argument, e.g. {option} {key}={example}"
            )
        return text

    return parse


class Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line (``agsf run: error: …``, exit 2), like every other refusal."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def one_line(exc: BaseException) -> str:
    """An error as one line; file errors name the file."""
    if isinstance(exc, OSError) and exc.filename is not None:
        text = f"{exc.filename}: {exc.strerror or exc}"
    else:
        text = str(exc) or type(exc).__name__
    return " ".join(text.split())


class _TqdmHandler(logging.Handler):
    """Log records as lines on stderr, written through ``tqdm.write`` so that they do not break
    a progress bar that is being drawn."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=sys.stderr)
        except Exception:  # noqa: BLE001 - logging must never raise
            self.handleError(record)


@contextmanager
def messages(quiet: bool):
    """While the command runs: the package's INFO messages (``agsf_torch`` logger, e.g. the
    FPKE kernel's compilation) on stderr as ``agsf: …`` unless ``quiet``, every warning as one line
    ``agsf: warning: …`` (also with ``quiet``; not Python's ``file:line: Category: …`` form, whose location
    is the package's, not the user's), and the dependencies' warnings that are not the user's concern
    filtered out (precisely, by message and module)."""
    import warnings

    logger = logging.getLogger("agsf_torch")
    handler = _TqdmHandler()
    handler.setFormatter(logging.Formatter("agsf: %(message)s"))
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.WARNING if quiet else logging.INFO)
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = " ".join(str(message).split())
        handler.emit(logging.LogRecord("agsf_torch", logging.WARNING, filename, lineno, f"warning: {text}", None, None))

    warnings.showwarning = show
    try:
        with torch_internal_deprecations_hidden():
            yield
    finally:
        warnings.showwarning = shown
        logger.removeHandler(handler)
        logger.setLevel(level)


#: Signals that end a command as Ctrl-C does: SIGTERM (what ``timeout``, a CI cancellation and a service manager
#: send) and SIGHUP (a closed terminal).
ENDING_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
#: The ending signal the running command received first, if any (:func:`interruption`).
_received: list[int] = []


def _interrupt_as_ctrl_c(signum: int, frame) -> None:
    """An ending signal's handler: the first runs this process's Ctrl-C handler (the default raises
    ``KeyboardInterrupt``; a sweep's also latches it), so that the command ends by the one path Ctrl-C takes
    (case processes interrupted, unfinished files removed, the output folder let go).  Later ones are ignored:
    ``timeout`` signals the command and then its whole process group, and a second interruption would cut the
    first one's clean-up short (the sender's next step is SIGKILL; Ctrl-C still interrupts it)."""
    if _received:
        return
    _received.append(signum)
    handler = signal.getsignal(signal.SIGINT)
    if callable(handler):
        handler(signal.SIGINT, frame)
    raise KeyboardInterrupt  # SIGINT ignored (a background job of a shell) or a handler that returned


@contextmanager
def ending_signals():
    """While the command runs, SIGTERM and SIGHUP raise ``KeyboardInterrupt`` as Ctrl-C does (remembered for
    :func:`interruption`); their handlers are restored afterwards.  A signal the process was started ignoring
    stays ignored (``nohup agsf …`` outlives its terminal), and outside the main thread, where Python runs no
    signal handler, nothing changes."""
    _received.clear()
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    try:
        for signum in ENDING_SIGNALS:
            if signal.getsignal(signum) is not signal.SIG_IGN:
                previous[signum] = signal.signal(signum, _interrupt_as_ctrl_c)
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)  # None: set outside Python


def interruption() -> tuple[int, str]:
    """The exit status and the words of the interruption that ended the command (its ``KeyboardInterrupt``): 130
    and ``interrupted`` for Ctrl-C, 128 + the signal and ``stopped by SIGTERM`` (143) or ``stopped by SIGHUP`` (129)
    for an ending signal (:func:`ending_signals`), the conventional statuses of a command ended by a signal."""
    if not _received:
        return 128 + signal.SIGINT, "interrupted"
    return 128 + _received[0], f"stopped by {signal.Signals(_received[0]).name}"
