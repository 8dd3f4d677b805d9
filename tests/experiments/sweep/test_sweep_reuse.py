"""Sweeps do not redo work: a filter runs once per distinct set of what its results depend on
(:meth:`ExperimentConfig.filter_digest`), and its arrays are copied into the other configurations.

The reuse is only valid because a filter's numbers do not depend on which other filters run beside it:
the first test checks exactly that, bit for bit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run.experiment import run_experiment
from agsf_torch.experiments.sweep import run_sweep
from agsf_torch.experiments.sweep.rows import results_table
from tests.helpers import EAGER

TINY = ["runs=2", "duration=0.5", "components=2", *EAGER]
FILTERS = 'filters=["EKF","GSF","AGSF"]'


def _arrays(folder, name):
    with np.load(folder / "runs.npz") as f:
        return {k: f[k] for k in f.files if k.startswith(f"{name}/")}


def _assert_same(a: dict, b: dict) -> None:
    assert a.keys() == b.keys() and a
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)


def test_a_filter_gives_the_same_numbers_alone_or_beside_others(tmp_path):
    together = load_config("case1", [*TINY, FILTERS])
    run_experiment(together, tmp_path / "all", progress=False)
    run_experiment(together.replace(filters=["GSF"]), tmp_path / "gsf", progress=False)
    run_experiment(together.replace(filters=["AGSF", "EKF"]), tmp_path / "agsf_ekf", progress=False)
    _assert_same(_arrays(tmp_path / "all", "GSF"), _arrays(tmp_path / "gsf", "GSF"))
    for name in ("AGSF", "EKF"):  # the first filter drives the environment's action: it scores, changes nothing
        _assert_same(_arrays(tmp_path / "all", name), _arrays(tmp_path / "agsf_ekf", name))


def test_filter_digests_follow_what_each_filter_reads():
    cfg = load_config("case1", TINY)
    changed = {
        "reg": {"AGSF"},  # the paper's update only
        "tikhonov": {"AGSF-galerkin"},
        "components": {"GSF", "AGSF", "AGSF-galerkin"},  # not the one-component filters
        "update_iterations": {"EKF", "GSF", "AGSF", "AGSF-galerkin", "MEKF"},  # every filter's option
        "sigma_s": {"EKF", "GSF", "AGSF", "AGSF-galerkin", "MEKF"},  # the simulation
        "name": set(),
        "filters": set(),
    }
    values = {"reg": 0.5, "tikhonov": 1e-6, "components": 3, "update_iterations": 3, "sigma_s": 2e-5}
    values |= {"name": "other", "filters": ["GSF"]}
    for key, who in changed.items():
        other = cfg.replace(**{key: values[key]})
        differ = {
            n for n in ("EKF", "GSF", "AGSF", "AGSF-galerkin", "MEKF") if cfg.filter_digest(n) != other.filter_digest(n)
        }
        assert differ == who, key
    assert len({cfg.filter_digest(n) for n in ("EKF", "GSF", "AGSF", "AGSF-galerkin", "MEKF")}) == 5


def test_a_sweep_over_reg_runs_the_other_filters_once_and_says_so(tmp_path):
    base = load_config("case1", [*TINY, FILTERS])
    calls = []

    def counting(cfg, folder, **kw):
        calls.append((cfg.reg, sorted(kw.get("reuse", {}))))
        return run_experiment(cfg, folder, **kw)

    out = tmp_path / "sweep"
    rows = run_sweep(base, {"reg": [0.5, 1.0, 2.0]}, out, progress=False, runner=counting)
    assert calls == [(0.5, []), (1.0, ["EKF", "GSF"]), (2.0, ["EKF", "GSF"])]
    first = rows[0]["digest"]
    assert "reused" not in rows[0]
    assert all(r["reused"] == {"EKF": first, "GSF": first} for r in rows[1:])
    for name in ("EKF", "GSF"):  # identical columns, identical arrays
        assert len({r["metrics"][f"{name}/time_averaged_nees"] for r in rows}) == 1
        for r in rows[1:]:
            _assert_same(_arrays(out / "configs" / first, name), _arrays(out / "configs" / r["digest"], name))
    assert len({r["metrics"]["AGSF/time_averaged_nees"] for r in rows}) == 3  # the filter that reads reg ran thrice
    summary = json.loads((out / "configs" / rows[1]["digest"] / "summary.json").read_text())
    assert summary["reused"] == {"EKF": first, "GSF": first}
    table = results_table(rows)
    assert "reused (not rerun)" in table.splitlines()[0]
    assert sum(f"EKF, GSF ← {first}" in line for line in table.splitlines()) == 2
    assert "ran once" in table.splitlines()[-1]
    # the copies are what running the configuration whole gives
    whole = tmp_path / "whole"
    run_experiment(base.replace(reg=2.0), whole, progress=False)
    for name in ("EKF", "GSF", "AGSF"):
        _assert_same(_arrays(whole, name), _arrays(out / "configs" / rows[2]["digest"], name))


def test_a_resumed_sweep_reuses_the_configurations_already_done(tmp_path):
    base = load_config("case1", [*TINY, 'filters=["EKF","AGSF"]'])
    out = tmp_path / "sweep"
    rows = run_sweep(base, {"reg": [0.5, 1.0]}, out, progress=False)
    results = out / "results.jsonl"
    results.write_text(results.read_text().splitlines()[0] + "\n")  # the second row lost: it reruns
    calls = []

    def counting(cfg, folder, **kw):
        calls.append(sorted(kw.get("reuse", {})))
        return run_experiment(cfg, folder, **kw)

    again = run_sweep(base, {"reg": [0.5, 1.0]}, out, progress=False, runner=counting)
    assert calls == [["EKF"]] and again[1]["reused"] == {"EKF": rows[0]["digest"]}


def test_every_filter_reused_runs_no_simulation(tmp_path):
    cfg = load_config("case1", [*TINY, 'filters=["EKF","GSF"]'])
    run_experiment(cfg, tmp_path / "a", progress=False)
    summary = run_experiment(
        cfg.replace(name="again"), tmp_path / "b", progress=False, reuse={"EKF": tmp_path / "a", "GSF": tmp_path / "a"}
    )
    assert summary["reused"] == {"EKF": "a", "GSF": "a"}
    for name in ("EKF", "GSF"):
        _assert_same(_arrays(tmp_path / "a", name), _arrays(tmp_path / "b", name))
    assert (tmp_path / "b" / "rms.png").is_file()


def test_reuse_that_cannot_be_right_is_refused(tmp_path):
    cfg = load_config("case1", [*TINY, 'filters=["EKF","GSF"]'])
    run_experiment(cfg, tmp_path / "a", progress=False)
    with pytest.raises(ValueError, match="cannot reuse results of"):
        run_experiment(cfg.replace(filters=["GSF"]), tmp_path / "b", progress=False, reuse={"EKF": tmp_path / "a"})
    assert not (tmp_path / "b").exists()  # refused before the folder is created
    other = cfg.replace(star_period=0.5)  # another simulation
    with pytest.raises(ValueError, match="differs in what EKF reads"):
        run_experiment(other, tmp_path / "c", progress=False, reuse={"EKF": tmp_path / "a"})
    assert not (tmp_path / "c").exists()
    with pytest.raises(ValueError, match="no readable experiment.json"):
        run_experiment(cfg, tmp_path / "d", progress=False, reuse={"EKF": tmp_path / "nowhere"})


def test_arrays_of_another_simulation_are_never_merged(tmp_path):
    """The last guard, should a digest ever miss a field: the reused run's times and star frames must be
    this experiment's."""
    from agsf_torch.experiments.run.outputs import load_filter_runs, save_runs

    cfg = load_config("case1", [*TINY, 'filters=["EKF"]'])
    run_experiment(cfg, tmp_path / "a", progress=False)
    run_experiment(cfg.replace(star_period=0.5), tmp_path / "b", progress=False)
    mine = load_filter_runs(tmp_path / "a" / "runs.npz", "EKF")
    theirs = load_filter_runs(tmp_path / "b" / "runs.npz", "EKF")
    with pytest.raises(RuntimeError, match="do not match"):
        save_runs(tmp_path / "c.npz", None, {"EKF": mine, "GSF": theirs})
