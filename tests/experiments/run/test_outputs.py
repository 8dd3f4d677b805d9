"""Nothing lost: inputs identified by content, sweeps that survive torn logs and refuse to run twice,
grids that name each experiment once, and memory estimates checked before any work."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from agsf_torch.experiments.cli import main as cli
from agsf_torch.experiments.config.loader import load_config
from agsf_torch.experiments.run.experiment import OutputConflict, make_env, run_experiment
from agsf_torch.experiments.run.recorded import record_environment
from agsf_torch.experiments.run.resources import (
    BASE_PROCESS,
    RETAINED_OVERHEAD,
    WORKING_OVERHEAD,
    TooLarge,
    check_memory,
    estimated_memory,
)
from agsf_torch.experiments.sweep import SweepBusy, parse_grid, run_sweep

TINY = ["runs=2", "duration=0.3", 'filters=["EKF"]', "compile_fused=false"]


def _tiny(*more):
    return load_config("case1", TINY + list(more))


# -------------------------------------------------------------- content, not path


def test_new_recording_contents_at_the_same_path_never_replace_earlier_results(tmp_path):
    cfg = _tiny()
    path = tmp_path / "rec.npz"
    record_environment(make_env(cfg), cfg.num_steps, seed=1).save(path)
    out = tmp_path / "replay"
    first = run_experiment(cfg, out, progress=False, recording=path)
    kept = (out / "summary.json").read_bytes()
    record_environment(make_env(cfg), cfg.num_steps, seed=2).save(path)  # new data, same path
    with pytest.raises(OutputConflict, match="different experiment .*: the same configuration with another input"):
        run_experiment(cfg, out, progress=False, recording=path)
    assert (out / "summary.json").read_bytes() == kept
    # the first contents under another name are the same experiment: the folder is reused
    record_environment(make_env(cfg), cfg.num_steps, seed=1).save(tmp_path / "copy.npz")
    again = run_experiment(cfg, out, progress=False, recording=tmp_path / "copy.npz")
    assert again["filters"]["EKF"]["rms_deg"] == first["filters"]["EKF"]["rms_deg"]


def test_learn_identifies_its_recording_by_content(tmp_path):
    cfg = _tiny("star_period=0.1")  # star frames in 0.3 s: learning needs two
    path = tmp_path / "rec.npz"
    record_environment(make_env(cfg), cfg.num_steps, seed=1).save(path)
    args = [
        "learn",
        "case1",
        *sum([["--set", s] for s in [*TINY, "star_period=0.1"]], []),
        "--learn",
        "sigma_v",
        "--max-iter",
        "1",
        "--recording",
        str(path),
        "--out",
        str(tmp_path / "learn"),
    ]
    assert cli.main(args) == 0
    kept = (tmp_path / "learn" / "learn.json").read_bytes()
    record_environment(make_env(cfg), cfg.num_steps, seed=2).save(path)
    assert cli.main(args) == 2
    assert (tmp_path / "learn" / "learn.json").read_bytes() == kept


# -------------------------------------------------------------- sweeps


def test_a_sweep_resumes_past_a_torn_last_line_with_a_warning_naming_the_file(tmp_path):
    base = _tiny()
    grid = parse_grid(["reg=0.5,1"], base)
    out = tmp_path / "sweep"
    run_sweep(base, grid, out, progress=False)
    results = out / "results.jsonl"
    rows = results.read_text().splitlines()
    results.write_text(rows[0] + "\n" + rows[1][: len(rows[1]) // 2])  # killed while writing the second row
    ran = []

    def counting(cfg, out, **kw):
        ran.append(cfg.reg)
        return run_experiment(cfg, out, **kw)

    with pytest.warns(RuntimeWarning, match=r"results.jsonl: removed a torn last line"):
        again = run_sweep(base, grid, out, progress=False, runner=counting)
    assert ran == [json.loads(rows[1])["params"]["reg"]]  # only the configuration whose row was torn
    assert [json.loads(line) for line in results.read_text().splitlines()] == again
    assert sorted(r["params"]["reg"] for r in again) == [0.5, 1.0]


def test_a_truncated_experiment_marker_is_an_error_naming_the_file(tmp_path):
    out = tmp_path / "sweep"
    base = _tiny()
    run_sweep(base, parse_grid(["reg=1"], base), out, progress=False)
    marker = out / "experiment.json"
    marker.write_text(marker.read_text()[:20])
    with pytest.raises(ValueError, match=r"experiment marker .*experiment.json is corrupt"):
        run_sweep(base, parse_grid(["reg=1"], base), out, progress=False)


def test_grid_values_are_normalised_and_duplicates_refused():
    base = _tiny()
    assert parse_grid(["reg=1,2"], base) == parse_grid(["reg=1.0,2.0"], base) == {"reg": [1.0, 2.0]}
    assert isinstance(parse_grid(["reg=1"], base)["reg"][0], float)
    with pytest.raises(ValueError, match=r"grid key 'reg' lists the value 1.0 twice"):
        parse_grid(["reg=1,1.0"], base)
    with pytest.raises(ValueError, match="grid key 'reg' is given twice"):
        parse_grid(["reg=1", "reg=2"], base)
    with pytest.raises(ValueError, match="config key 'reg': reg must be a finite number ≥ 0"):
        parse_grid(["reg=-1"], base)


def test_list_valued_keys_sweep_whole_values():
    """Commas inside brackets and quotes belong to the value: a list-valued key can be swept (it was split
    into "[1" and "0" and refused as "must be a list, got '[1'")."""
    base = _tiny()
    grid = parse_grid(["rate_axes=[1,0,0], [0,1,0]", 'star_noise_model="tangent","isotropic"'], base)
    assert grid == {"rate_axes": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], "star_noise_model": ["tangent", "isotropic"]}
    with pytest.raises(ValueError, match=r"grid key 'rate_axes' lists the value \[1.0, 0, 0\] twice"):
        parse_grid(["rate_axes=[1,0,0],[1.0,0,0]"], base)


def test_the_same_grid_written_with_ints_or_floats_is_one_experiment(tmp_path):
    base = _tiny()
    out = tmp_path / "sweep"
    first = run_sweep(base, {"reg": [1]}, out, progress=False)
    ran = []
    again = run_sweep(base, {"reg": [1.0]}, out, progress=False, runner=lambda *a, **k: ran.append(a))
    assert again == first and not ran  # same folder accepted, nothing rerun
    # duplicate values passed to the API directly run once
    twice = run_sweep(base, {"reg": [0.5, 0.5]}, tmp_path / "dup", progress=False)
    assert len(twice) == 1


def test_a_second_sweep_into_the_same_folder_is_refused_while_the_first_runs(tmp_path):
    base = _tiny()
    grid = parse_grid(["reg=1"], base)
    out = tmp_path / "sweep"
    seen = []

    def nested(cfg, folder, **kw):  # while this sweep runs, start the same sweep again
        with pytest.raises(SweepBusy, match="another agsf sweep is writing"):
            run_sweep(base, grid, out, progress=False)
        seen.append(True)
        return run_experiment(cfg, folder, **kw)

    rows = run_sweep(base, grid, out, progress=False, runner=nested)
    assert seen == [True] and len(rows) == 1
    assert len((out / "results.jsonl").read_text().splitlines()) == 1


# -------------------------------------------------------------- memory


def test_the_memory_estimate_counts_what_the_runner_keeps():
    cfg = load_config("case1", ["runs=100", "duration=30", 'filters=["EKF", "GSF", "AGSF"]', "components=5"])
    est = estimated_memory(cfg)
    # per step and trajectory: angle, estimate (3), error (3), sigma (3), covariance (9), NEES, NIS, NIS dof,
    # weights (N), entropy, and up to 16 diagnostics; EKF has N = 1, GSF and AGSF N = 5
    floats = (1 + 3 + 3 + 3 + 9 + 1 + 1 + 1 + 1 + 1 + 16) + 2 * (1 + 3 + 3 + 3 + 9 + 1 + 1 + 1 + 5 + 1 + 16)
    assert est.retained == RETAINED_OVERHEAD * 8 * 300 * 100 * floats
    assert est.working == WORKING_OVERHEAD * 8 * 100 * ((1 + 5 + 5) * 9 + 3 * 5)
    assert est.total == est.retained + est.working + BASE_PROCESS
    assert estimated_memory(cfg, keep_steps=False).retained == 0


def test_a_configuration_larger_than_the_budget_is_refused_unless_forced():
    cfg = _tiny()
    need = estimated_memory(cfg).total
    with pytest.raises(TooLarge, match=r"runs=2, 3 steps .* needs an estimated .* GB of memory .* --force"):
        check_memory(cfg, budget=need - 1)
    assert check_memory(cfg, budget=need).total == need
    assert check_memory(cfg, budget=need - 1, force=True).total == need


def test_run_refuses_a_configuration_that_cannot_fit_before_creating_anything(tmp_path):
    with pytest.raises(TooLarge, match="runs=1000000000"):
        run_experiment(_tiny("runs=1000000000"), tmp_path / "x", progress=False)
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_the_memory_estimate_bounds_a_measured_peak(tmp_path):
    """The estimate of ``agsf run case1`` (1024 runs × 300 steps) lies above the measured peak
    resident memory of the process, by less than a factor of two."""
    cfg = load_config("case1", ["runs=1024"])
    code = (
        "from agsf_torch.experiments import cli; from agsf_torch.experiments.run.resources import peak_resident_memory; "
        f"cli.main(['run', 'case1', '--set', 'runs=1024', '--quiet', '--out', {str(tmp_path / 'run')!r}]); "
        "print(peak_resident_memory() // 1024)"
    )
    peak_kb = int(
        subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True).stdout.split()[-1]
    )
    estimate = estimated_memory(cfg).total
    assert peak_kb * 1024 < estimate < 2 * peak_kb * 1024, (peak_kb / 2**20, estimate / 2**30)


@pytest.mark.filterwarnings("ignore::pytest.PytestUnraisableExceptionWarning")  # the swallowed Ctrl-C itself
def test_a_ctrl_c_swallowed_inside_a_finaliser_still_stops_the_sweep(tmp_path):
    """Python drops an exception raised while a finaliser runs ("Exception ignored in: …"): a Ctrl-C landing
    there let the sweep run to its end.  The latch stops it after the row in progress."""
    import os
    import signal

    from agsf_torch.experiments.run.experiment import run_experiment
    from agsf_torch.storage.files import read_json_lines

    class Finaliser:
        def __del__(self):
            os.kill(os.getpid(), signal.SIGINT)  # delivered while __del__ runs: the KeyboardInterrupt is dropped

    def runner(cfg, folder, **kwargs):
        summary = run_experiment(cfg, folder, **kwargs)
        obj = Finaliser()
        del obj
        return summary

    base = _tiny()
    with pytest.raises(KeyboardInterrupt):
        run_sweep(base, parse_grid(["reg=0.5,1,2"], base), tmp_path / "sweep", progress=False, runner=runner)
    assert len(read_json_lines(tmp_path / "sweep" / "results.jsonl")) == 1


def test_a_conflict_names_what_differs_and_how_much_more(tmp_path):
    """A refused folder says which keys differ from the experiment it holds (the first four, then how many
    more), with both values; nested configurations (a sweep's base and grid) by dotted keys."""
    from agsf_torch.experiments.run.outputs import check_output, prepare_output, release_outputs

    out = prepare_output(tmp_path / "x", "run", "aaaa", {"runs": 2, "grid": {"reg": [1.0, 2.0]}, "seed": 1})
    release_outputs()
    with pytest.raises(
        OutputConflict, match=r"differs in grid\.reg: \[1\.0, 2\.0\] there, \[2\.0, 1\.0\] here; choose"
    ):
        check_output(out, "run", "bbbb", {"runs": 2, "grid": {"reg": [2.0, 1.0]}, "seed": 1})
    many = {"runs": 3, "grid": {"reg": [3.0]}, "seed": 2, "a": 1, "b": 2}
    with pytest.raises(OutputConflict, match=r"differs in a: \"—\" there, 1 here; .*; and 1 more; choose"):
        check_output(out, "run", "bbbb", many)
    with pytest.raises(OutputConflict, match=r"\(run aaaa\); choose"):  # another kind: no configuration to compare
        check_output(out, "sweep", "aaaa", {"runs": 2})


def test_runs_npz_is_what_numpy_reads_with_the_same_bytes_for_the_same_arrays(tmp_path):
    """``save_npz``: every array back as it went in (dtype, shape, NaN) through ``np.load(allow_pickle=False)``, the
    same bytes for the same arrays (entries dated 1980, as ``np.savez`` dates them), and an array numpy would have
    to pickle refused with no file and no temporary file left."""
    import zipfile

    import numpy as np

    from agsf_torch.experiments.run.outputs import save_npz

    rng = np.random.default_rng(0)
    nis = np.full((50, 300), np.nan)
    nis[:, 9::10] = rng.chisquare(15, size=(50, 30))
    data = {
        "time": 0.1 * np.arange(1, 301),
        "star_frame": np.arange(300) % 10 == 9,
        "GSF/cov": rng.normal(size=(50, 300, 3, 3)),
        "GSF/nis": nis,
        "GSF/gyro_held": np.zeros((50, 300), np.int64),
        "GSF/weights": rng.dirichlet(np.ones(5), size=(50, 300)),
        "empty": np.zeros((0, 3)),
        "units": np.array(json.dumps({"time": "s"})),
    }
    first, second = save_npz(tmp_path / "a.npz", data), save_npz(tmp_path / "b.npz", data)
    assert first == tmp_path / "a.npz" and first.read_bytes() == second.read_bytes()
    with np.load(first, allow_pickle=False) as back:
        assert sorted(back.files) == sorted(data)
        for key, value in data.items():
            assert back[key].dtype == value.dtype and back[key].shape == value.shape
            np.testing.assert_array_equal(back[key], value)
    assert all(i.date_time == (1980, 1, 1, 0, 0, 0) for i in zipfile.ZipFile(first).infolist())
    with pytest.raises(ValueError, match="pickle"):
        save_npz(tmp_path / "c.npz", {"time": data["time"], "objects": np.array([{}, None], dtype=object)})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "b.npz"]
