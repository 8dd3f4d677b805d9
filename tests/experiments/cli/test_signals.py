"""SIGTERM and SIGHUP end an ``agsf`` command as Ctrl-C does: the case processes interrupted and their clean-up run,
whole files only, the output folder's lock released, one line on stderr and the conventional status 128 + signal
(143, 129).  What ``timeout``, a CI cancellation and a service manager send, and a closed terminal."""

from __future__ import annotations

import io
import os
import signal
import subprocess
import sys
import textwrap
import time
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import pytest

from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.run.worker_pool import fork_available
from tests.experiments.run.test_worker_pool import _slow_clean

ROOT = Path(__file__).resolve().parents[3]

#: ``agsf reproduce`` in a new interpreter, each case's work replaced by one that marks its process, begins a file
#: and waits to be interrupted, then takes 0.3 s to clean up (a second signal must not cut that short).
_STUCK_REPRODUCE = textwrap.dedent(
    """
    import os, sys, time
    from pathlib import Path

    from agsf_torch.experiments.cli import main as cli
    from agsf_torch.experiments.studies import reproduce
    from agsf_torch.storage.files import atomic_open

    marks = Path(sys.argv[1])

    def stuck(cfg, out, **kwargs):
        out.mkdir(parents=True, exist_ok=True)
        try:
            with atomic_open(out / "runs.npz") as fh:  # a file begun, never finished: it must not appear
                fh.write(b"half a file")
                (marks / f"{out.name}.pid").write_text(str(os.getpid()))
                while True:
                    time.sleep(0.01)
        finally:
            time.sleep(0.3)
            (marks / f"{out.name}.cleaned").write_text("yes")

    reproduce.run_experiment = stuck
    reproduce.make_filters = lambda cfg: None
    sys.argv = ["agsf", *sys.argv[2:]]
    cli.entry()
    """
)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _hangup_by_default() -> None:
    """In the child before it runs: SIGHUP at its default action (a terminal's process), whatever started the suite."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


@pytest.mark.skipif(not fork_available(), reason="cases side by side need fork (Linux)")
@pytest.mark.parametrize(
    ("signum", "whole_group"),
    [(signal.SIGTERM, True), (signal.SIGHUP, False)],
    ids=["SIGTERM-as-timeout-sends-it", "SIGHUP-to-the-command-alone"],
)
def test_a_terminating_signal_ends_reproduce_as_ctrl_c_does(tmp_path, signum, whole_group):
    """``timeout`` signals the command and then its whole process group (the command twice, each case's process
    once); a service manager or a closed terminal the command alone, which passes it on to its cases."""
    from filelock import FileLock

    marks, out = tmp_path / "marks", tmp_path / "out"
    marks.mkdir()
    argv = ["reproduce", "--case", "all", "--jobs", "3", "--runs", "2", "--duration", "1", "--quiet", "--out", str(out)]
    argv += ["--set", "compile=false", "--set", "compile_fused=false"]
    proc = subprocess.Popen(
        [sys.executable, "-c", _STUCK_REPRODUCE, str(marks), *argv],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,  # its own process group, as under `timeout`
        # a terminal's process, whatever started the suite: under nohup SIGHUP is inherited ignored, and a command
        # started ignoring it keeps it ignored (by design), so the test would wait for nothing
        preexec_fn=_hangup_by_default,
    )
    cases = [f"case{k}" for k in (1, 2, 3)]
    try:
        deadline = time.monotonic() + 120
        while not all((marks / f"{case}.pid").exists() and (marks / f"{case}.pid").read_text() for case in cases):
            assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
            time.sleep(0.05)
        pids = [int((marks / f"{case}.pid").read_text()) for case in cases]
        os.kill(proc.pid, signum)
        if whole_group:
            os.killpg(proc.pid, signum)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
        for pid_file in marks.glob("*.pid"):  # a case process left running by a failed command
            try:
                os.kill(int(pid_file.read_text()), signal.SIGKILL)
            except (ProcessLookupError, ValueError):
                pass
    name = signal.Signals(signum).name
    assert proc.returncode == 128 + signum, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"agsf: stopped by {name}"), err
    assert str(out) in lines[0]
    for case, pid in zip(cases, pids):
        assert (marks / f"{case}.cleaned").read_text() == "yes"  # each case's clean-up ran to its end
        assert not _alive(pid)
        assert sorted(p.name for p in (out / case).iterdir()) == []  # no half-written file, no temporary file
    assert not (out / "summary.json").exists() and not (out / "results.md").exists()
    FileLock(str(out / ".agsf.lock")).acquire(timeout=0)  # released: a rerun may write the folder


def _agsf(argv: list[str]) -> tuple[int, str]:
    """``(exit code, stderr)`` of ``agsf argv`` in this process."""
    err = io.StringIO()
    with redirect_stdout(io.StringIO()), redirect_stderr(err):
        code = cli.main(argv)
    return code, err.getvalue()


@pytest.fixture
def safety_net():
    """SIGTERM and SIGHUP caught here around the test, so that a command that does not handle them returns (and the
    test fails) instead of ending the test process; the handlers are checked to be back afterwards."""
    seen: list[int] = []

    def caught(signum, frame):
        seen.append(signum)

    previous = {s: signal.signal(s, caught) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield caught
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _signalled(signum: int):
    """A step of a command that receives ``signum`` and would then run on for 5 s."""

    def step(*args, **kwargs):
        os.kill(os.getpid(), signum)
        time.sleep(5)
        raise AssertionError("the signal did not end the command")

    return step


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP])
def test_a_command_ends_with_one_line_and_128_plus_the_signal(tmp_path, monkeypatch, safety_net, signum):
    from agsf_torch.experiments.run import recorded

    monkeypatch.setattr(recorded, "record_environment", _signalled(signum))
    out = tmp_path / "s"
    t0 = time.monotonic()
    code, err = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(out)])
    assert code == 128 + signum and time.monotonic() - t0 < 4
    name = signal.Signals(signum).name
    assert err.strip().count("\n") == 0 and err.strip().startswith(f"agsf: stopped by {name}; what was written is in")
    assert signal.getsignal(signal.SIGTERM) is safety_net and signal.getsignal(signal.SIGHUP) is safety_net
    assert sorted(p.name for p in out.iterdir()) == [".agsf.lock", "experiment.json"]


def test_an_interrupted_sweep_says_what_stopped_it_and_how_to_resume(tmp_path, monkeypatch, safety_net):
    from agsf_torch.experiments import sweep

    monkeypatch.setattr(sweep, "run_sweep", _signalled(signal.SIGTERM))
    argv = ["sweep", "case1", "--grid", "reg=0.1,1", "--quiet", "--out", str(tmp_path / "sw")]
    code, err = _agsf(argv + ["--set", "compile=false", "--set", "compile_fused=false"])
    assert code == 143
    assert err.strip().count("\n") == 0 and err.strip().startswith(
        "agsf: stopped by SIGTERM; 0 finished configurations"
    )
    assert "rerun the same command to resume" in err


def test_a_signal_the_command_was_started_ignoring_stays_ignored(tmp_path, monkeypatch):
    """``nohup agsf …`` starts the command with SIGHUP ignored: a closed terminal must not end it."""
    from agsf_torch.experiments.run import recorded

    seen = []

    def record(*args, **kwargs):
        seen.append(signal.getsignal(signal.SIGHUP))
        raise KeyboardInterrupt

    monkeypatch.setattr(recorded, "record_environment", record)
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        code, _ = _agsf(["simulate", "--runs", "2", "--steps", "3", "--quiet", "--out", str(tmp_path / "s")])
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)
    assert code == 130 and seen == [signal.SIG_IGN]


@pytest.mark.skipif(not fork_available(), reason="forked tasks need fork (Linux)")
def test_a_forked_task_takes_sigterm_as_ctrl_c(tmp_path):
    """A service manager signals every process of the command: each child is interrupted (twice here, the second
    ignored), runs its clean-up to its end and reports the interruption, which the caller raises."""
    import threading

    from agsf_torch.experiments.run.worker_pool import run_forked

    marks = [tmp_path / f"child{k}" for k in range(2)]

    def terminate_when_started() -> None:
        while not all(m.exists() and m.read_text() for m in marks):
            time.sleep(0.01)
        for _ in range(2):
            for m in marks:
                os.kill(int(m.read_text()), signal.SIGTERM)
            time.sleep(0.05)

    threading.Thread(target=terminate_when_started, daemon=True).start()
    with pytest.raises(KeyboardInterrupt):
        run_forked([(_slow_clean, (str(m),)) for m in marks], 2)
    for mark in marks:
        assert Path(str(mark) + ".cleaned").read_text() == "yes"
        assert not _alive(int(mark.read_text()))
