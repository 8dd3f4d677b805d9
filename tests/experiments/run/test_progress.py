"""Progress on stderr: lines a log file can hold when stderr is not a terminal, and bars that name what runs."""

from __future__ import annotations

import io
import re
from contextlib import redirect_stderr

from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run import progress
from agsf_torch.experiments.run.progress import progress_bar
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


def test_a_forked_childs_bars_are_reported_and_its_parent_draws_each_childs_on_its_own_line(monkeypatch):
    """``report_to``: a child's bar sends ``(desc, unit, total, n)`` when it starts, every 1 % of the work and at the
    end instead of drawing; ``ParentBars`` draws child ``k``'s bar on line ``k`` (tqdm's ``position``)."""
    import tqdm.auto

    sent = []
    progress.report_to(lambda *bar: sent.append(bar))
    try:
        assert list(progress_bar(range(250), desc="case2", unit="step", total=250)) == list(range(250))
    finally:
        progress.report_to(None)
    assert sent[0] == ("case2", "step", 250, 0) and sent[-1] == ("case2", "step", 250, 250)
    assert [n for *_, n in sent] == sorted({n for *_, n in sent}) and len(sent) == 2 + 250 // 2 - 1
    made = []

    class Bar:
        def __init__(self, *a, **kw):
            made.append(kw)
            self.n, self.closed = 0, False

        def update(self, k):
            self.n += k

        def close(self):
            self.closed = True

    monkeypatch.setattr(tqdm.auto, "tqdm", Bar)
    monkeypatch.setattr(progress, "_is_terminal", lambda: True)
    bars = progress.ParentBars()
    for child, desc, n in ((2, "case3", 0), (0, "case1", 0), (2, "case3", 40), (0, "case1", 10)):
        bars.update(child, desc, "step", 300, n)
    assert [kw["position"] for kw in made] == [2, 0]
    assert {key: bar.n for key, bar in bars._bars.items()} == {(2, "case3"): 40, (0, "case1"): 10}
    drawn = list(bars._bars.values())
    bars.close()
    assert all(bar.closed for bar in drawn)


def test_a_forked_child_forgets_the_lock_its_parent_took_on_any_bar_class():
    """``tqdm.write`` takes its lock on ``tqdm.std.tqdm``, the bars of ``tqdm.auto`` inherit it: the child drops it
    where it lives, and the next bar takes a new one."""
    from tqdm.auto import tqdm as auto_tqdm
    from tqdm.std import tqdm as std_tqdm

    std_tqdm.write("a message", file=io.StringIO())
    held = vars(std_tqdm)["_lock"]
    progress.forget_parent_bars()
    assert not any("_lock" in vars(cls) for cls in auto_tqdm.__mro__)
    assert auto_tqdm.get_lock() is not held
