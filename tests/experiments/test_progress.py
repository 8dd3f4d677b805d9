"""Progress on stderr: lines a log file can hold when stderr is not a terminal, and bars that name what runs."""

from __future__ import annotations

import io
import re
from contextlib import redirect_stderr

from agsf_torch.experiments import progress
from agsf_torch.experiments.config import load_config
from agsf_torch.experiments.progress import progress_bar
from agsf_torch.experiments.sweep import parse_grid, run_sweep


def test_piped_progress_is_a_few_whole_lines(monkeypatch):
    """Not a terminal: one line per 5 % of the work (or 10 s), each a whole line, and the last one at 100 %."""
    err = io.StringIO()
    with redirect_stderr(err):
        for _ in progress_bar(range(1000), desc="case1", unit="step", total=1000):
            pass
    text = err.getvalue()
    assert "\r" not in text
    lines = text.splitlines()
    assert 2 <= len(lines) <= 1 / progress.LOG_FRACTION + 3  # the start, every 5 %, the end
    assert all(line.startswith("case1: ") for line in lines)
    assert re.search(r"100% 1000/1000 step", lines[-1])


def test_piped_progress_also_writes_a_line_after_the_interval(monkeypatch):
    clock = iter(range(0, 10_000, 11))  # every redraw 11 s after the last
    monkeypatch.setattr(progress.time, "monotonic", lambda: float(next(clock)))
    err = io.StringIO()
    with redirect_stderr(err):
        for _ in progress_bar(range(10), desc="slow", unit="step", total=1000):  # 1 % of the work, 11 s apart
            pass
    assert len(err.getvalue().splitlines()) >= 10


def test_sweep_progress_names_each_configuration(tmp_path):
    base = load_config("case1", ["runs=2", "duration=0.3", 'filters=["EKF"]', "compile_fused=false"])
    err = io.StringIO()
    with redirect_stderr(err):
        run_sweep(base, parse_grid(["seed=3,5"], base), tmp_path / "sweep", progress=True)
    names = {line.split(":")[0] for line in err.getvalue().splitlines() if "%" in line}
    assert names == {"case1 seed=3", "case1 seed=5"}
