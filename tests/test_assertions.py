"""The test suite's own rule: every accuracy assertion goes through :func:`tests.helpers.assert_within` (or, for a
statistic, :func:`tests.helpers.assert_statistic`), so that its bound is checked (not negative, finite, not zero
where the values are not) and jittered under ``pytest --jitter-ulps``; and the helpers do what they say."""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest
import torch

from tests import helpers
from tests.helpers import InvalidBound, assert_statistic, assert_within

TESTS = Path(__file__).parent

#: Comparisons with a tolerance of their own: the ones the helpers replace.
_TOLERANCE_CALLS = {
    "assert_close",
    "allclose",
    "isclose",
    "assert_allclose",
    "assert_array_almost_equal",
    "assert_almost_equal",
    "assert_approx_equal",
    "approx",
}


def _differences(node: ast.AST) -> bool:
    """Whether ``node`` holds ``abs``/``.abs()``/a norm of a subtraction: a hand-made distance between two values."""
    for sub in ast.walk(node):
        if not isinstance(sub, ast.Call):
            continue
        f = sub.func
        name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        if name not in {"abs", "fabs", "norm", "vector_norm", "matrix_norm"}:
            continue
        inner = [*sub.args, f.value] if isinstance(f, ast.Attribute) else list(sub.args)
        if any(isinstance(n, ast.BinOp) and isinstance(n.op, ast.Sub) for a in inner for n in ast.walk(a)):
            return True
    return False


def _residuals(node: ast.AST) -> bool:
    """Whether ``node`` reads a residual or an error angle (a distance the code under test computed: a KKT
    residual, ``attitude_error_angle``), which a bound compares like a hand-made difference."""
    for sub in ast.walk(node):
        name = ""
        if isinstance(sub, ast.Call):
            f = sub.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
        elif isinstance(sub, ast.Attribute):
            name = sub.attr
        elif isinstance(sub, ast.Constant) and isinstance(sub.value, str):
            name = sub.value
        if "residual" in name or name.endswith("error_angle"):
            return True
    return False


def _offences(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    found = []
    for func in [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))] + [tree]:
        distances = set()  # names bound to a hand-made distance in this function
        body = list(ast.walk(func)) if func is not tree else list(tree.body)
        for node in body:
            if isinstance(node, ast.Assign) and _differences(node.value):
                distances |= {t.id for t in node.targets if isinstance(t, ast.Name)}
        for node in body:
            if isinstance(node, ast.Call):
                f = node.func
                name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
                if name in _TOLERANCE_CALLS:
                    found.append(f"{path.relative_to(TESTS.parent)}:{node.lineno} calls {name}")
            # every comparison in an assert: at its top, inside ``and``, inside ``bool((…).all())``
            tests = (
                [n for n in ast.walk(node.test) if isinstance(n, ast.Compare)] if isinstance(node, ast.Assert) else []
            )
            for test in tests:
                if not isinstance(test, ast.Compare):
                    continue
                # a distance on the small side of the comparison: ``d < b``, ``d <= b``, ``b > d`` (``d > b`` asserts
                # that two values differ, which is no accuracy claim)
                sides = [test.left, *test.comparators]
                for left, op, right in zip(sides[:-1], test.ops, sides[1:], strict=True):
                    small = (
                        left
                        if isinstance(op, (ast.Lt, ast.LtE))
                        else right
                        if isinstance(op, (ast.Gt, ast.GtE))
                        else None
                    )
                    if small is None:
                        continue
                    named = any(isinstance(n, ast.Name) and n.id in distances for n in ast.walk(small))
                    if named or _differences(small):
                        found.append(f"{path.relative_to(TESTS.parent)}:{node.lineno} compares a difference by hand")
                    elif _residuals(small):
                        found.append(f"{path.relative_to(TESTS.parent)}:{node.lineno} bounds a residual by hand")
    return sorted(set(found))


def test_no_accuracy_assertion_bypasses_the_helpers():
    mine = {"helpers.py", Path(__file__).name}  # the helpers and their own tests
    offences = [o for p in sorted(TESTS.rglob("*.py")) if p.name not in mine for o in _offences(p)]
    assert not offences, "use tests.helpers.assert_within (or assert_statistic):\n" + "\n".join(offences)


def test_the_check_finds_each_kind_of_bypass(tmp_path):
    sample = TESTS / "_sample_offences.py"
    sample.write_text(
        "import torch, math\n"
        "def test_a(x, y):\n"
        "    torch.testing.assert_close(x, y)\n"
        "    assert torch.allclose(x, y)\n"
        "    assert (x - y).abs().max() <= 1e-12\n"
        "    assert abs(x - y) < 1e-3\n"
        "    err = torch.linalg.norm(x - y)\n"
        "    assert float(err) < 1e-9\n"
        "    assert math.isclose(x, y)\n"
        "    assert x.shape == y.shape\n"
        "    assert (x > 0).all()\n"
        "    assert float(res.kkt_residual.max()) < 1e-12\n"
        "    assert attitude_error_angle(x, y).max() < 1e-9\n"
        "    assert ok and d['qp_kkt_residual'].max() < 1e-9\n"
        "    assert bool(((x - y).abs() <= 1e-9).all())\n"
        "    assert 1e-9 > abs(x - y)\n"
        "    assert (x - y).norm() > 1e-3\n"
    )
    try:
        found = _offences(sample)
    finally:
        sample.unlink()
    assert sorted(int(o.split(":")[1].split()[0]) for o in found) == [3, 4, 5, 6, 8, 9, 12, 13, 14, 15, 16]


def test_a_bound_is_refused_where_it_vanishes_and_the_values_do_not():
    with pytest.raises(InvalidBound, match="bound is 0 at \\(1,\\)"):
        assert_within(torch.tensor([0.0, 2.0]), torch.tensor([0.0, 2.0]), torch.tensor([0.0, 0.0]), "rates")
    assert_within(torch.zeros(3), torch.zeros(3), 0.0, "structural zeros")  # 0 where both are 0: allowed
    with pytest.raises(InvalidBound, match="negative"):
        assert_within(1.0, 1.0, -1e-16, "x")
    for bad in (float("nan"), float("inf")):
        with pytest.raises(InvalidBound, match="not finite"):
            assert_within(1.0, 1.0, bad, "x")


def test_a_failure_names_the_worst_entry(monkeypatch):
    monkeypatch.setattr(helpers.JITTER, "ulps", 0)  # the message's digits, as given
    got = torch.tensor([[1.0, 2.0], [3.0, 4.5]], dtype=torch.float64)
    want = torch.tensor([[1.0, 2.0 + 1e-3], [3.0, 4.0]], dtype=torch.float64)
    with pytest.raises(AssertionError, match=r"covariance: 2 of 4 entries .* worst at \(1, 1\): actual 4\.5, "):
        assert_within(got, want, 1e-6, "covariance")
    with pytest.raises(AssertionError, match="at \\(0,\\) actual nan"):
        assert_within(torch.tensor([float("nan")]), torch.tensor([1.0]), 1.0, "x")
    assert_within(torch.tensor([float("inf"), float("nan")]), torch.tensor([float("inf"), float("nan")]), 0.0, "x")


def test_the_jitter_moves_each_nonzero_entry_by_up_to_k_ulps(monkeypatch):
    monkeypatch.setattr(helpers.JITTER, "ulps", 4)
    monkeypatch.setattr(helpers.JITTER, "rng", np.random.default_rng(7))
    x = np.array([1.0, -3.0e-300, 0.0, 7.5e10, np.inf])
    moved = helpers._jittered(x.copy())
    with np.errstate(invalid="ignore"):
        steps = np.abs(moved - x) / np.spacing(np.abs(x))
    assert moved[2] == 0.0 and moved[4] == np.inf
    assert np.all((steps[[0, 1, 3]] >= 1) & (steps[[0, 1, 3]] <= 4) & (steps[[0, 1, 3]] == np.round(steps[[0, 1, 3]])))
    # the rounding-alike comparison that a zero-spread bound would pass is caught: 1 ulp of slack is not enough
    with pytest.raises(AssertionError):
        for _ in range(20):
            assert_within(1.0, 1.0, np.spacing(1.0) / 2, "one rounding")


def test_the_statistical_helper_takes_its_limit_from_the_stated_rate():
    assert_statistic(4.8, 0.0, 1.0, "z", false_failure=1e-6)  # the two-sided 1e-6 quantile is 4.89
    with pytest.raises(AssertionError, match="limit is 4.89"):
        assert_statistic(4.95, 0.0, 1.0, "z", false_failure=1e-6)
    with pytest.raises(AssertionError, match="limit is 5.33"):  # 10 entries share the rate (Bonferroni)
        assert_statistic(np.r_[np.zeros(9), 5.4], 0.0, 1.0, "z", false_failure=1e-6)
    with pytest.raises(InvalidBound):
        assert_statistic(0.0, 0.0, 0.0, "z", false_failure=1e-6)
