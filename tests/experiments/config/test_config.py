"""Experiment configuration: presets, overrides, validation naming the key."""

from __future__ import annotations

import math

import pytest

from agsf_torch.experiments.config.loader import ExperimentConfig, load_config, load_preset, preset_names
from tests.helpers import assert_within


def test_presets_carry_the_decoded_and_guessed_values():
    assert {"case1", "case2", "case3", "wide_prior"} <= set(preset_names())
    c1, c2, c3 = (load_preset(f"case{k}") for k in (1, 2, 3))
    assert (c1.star_period, c2.star_period, c3.star_period) == (1.0, 2.0, 5.0)
    for c in (c1, c2, c3):
        assert c.fov_deg == 8.0 and c.focal_length == 0.065 and c.max_stars == 5
        assert c.sigma_s == 10e-6 and c.dt == 0.1 and c.prior_var == 1e-3
        assert c.gyro_bias_deg_per_hr == 0.1 and c.rate_axes == [1.0, 1.0, 0.0]
        # math.isclose's default: 1e-9 relative (each value is one or two roundings of a nonzero constant)
        for got, want, what in (
            (c.omega0, 2 * math.pi / 100, "ω₀"),
            (c.sigma_v, math.sqrt(10) * 1e-7, "σ_v"),
            (c.sigma_u, math.sqrt(10) * 1e-10, "σ_u"),
        ):
            assert_within(got, want, 1e-9 * want, what)
        assert c.reg == 1.0 and c.weight_ref == "update" and not c.estimate_bias and c.runs >= 100
    wide = load_preset("wide_prior")
    assert wide.max_stars == 2 and wide.prior_var > 0.01 and wide.sigma_s == c1.sigma_s  # inherits case1


def test_file_with_preset_and_overrides(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('preset = "case2"\nname = "mine"\ncomponents = 3\n')
    cfg = load_config(f, ["runs=7", "scaling=none", "rate_axes=[0.0, 0.0, 1.0]"])
    assert (cfg.name, cfg.components, cfg.runs, cfg.scaling, cfg.star_period) == ("mine", 3, 7, "none", 2.0)
    assert cfg.rate_axes == [0.0, 0.0, 1.0]
    assert cfg.digest() != load_config(f).digest()


@pytest.mark.parametrize(
    "text, key",
    [
        ("bogus = 1", "bogus"),
        ('runs = "many"', "runs"),
        ("runs = 0", "runs"),
        ("runs = 2.5", "runs"),
        ("sigma_s = -1e-6", "sigma_s"),
        ("duration = inf", "duration"),
        ("spread = 1.0", "spread"),
        ('scaling = "log"', "scaling"),
        ("estimate_bias = 1", "estimate_bias"),
        ('filters = ["UKF"]', "filters"),
        ("star_period = 0.25", "star_period"),
        ("rate_axes = [1.0, 2.0]", "rate_axes"),
        ('preset = "case9"', "case9"),
    ],
)
def test_bad_files_name_the_key(tmp_path, text, key):
    f = tmp_path / "bad.toml"
    f.write_text(text + "\n")
    with pytest.raises(ValueError, match=key):
        load_config(f)


def test_bad_overrides_and_files(tmp_path):
    with pytest.raises(ValueError, match="unknown config key 'nope'"):
        load_config("case1", ["nope=3"])
    with pytest.raises(ValueError, match="key=value"):
        load_config("case1", ["runs"])
    with pytest.raises(ValueError, match="does not exist"):
        load_config(tmp_path / "missing.toml")
    f = tmp_path / "broken.toml"
    f.write_text("runs = [\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_config(f)
    # TOML is data only: a would-be code string is just an invalid value
    f.write_text("name = \"__import__('os').system('false')\"\nruns = \"__import__('os')\"\n")
    with pytest.raises(ValueError, match="'runs' must be an integer"):
        load_config(f)


def test_defaults_validate():
    assert ExperimentConfig().num_steps == 300


def test_faults_preset_and_fault_validation():
    cfg = load_preset("faults")
    assert cfg.gate_probability == 0.9999 and cfg.estimate_bias and len(cfg.faults) == 4
    assert {f["kind"] for f in cfg.faults} == {"misidentified_star", "star_outage", "gyro_dropout", "gyro_saturation"}
    assert all(f["end"] <= cfg.duration for f in cfg.faults)
    with pytest.raises(
        ValueError, match=r"config key 'faults': faults\[0\]: SensorFault: end \(1.0\) must be after start"
    ):
        ExperimentConfig(faults=[{"kind": "star_outage", "start": 2.0, "end": 1.0}])
    for p in (-0.1, 1.0):
        with pytest.raises(
            ValueError,
            match=r"config key 'gate_probability': gate probability must lie in \(0, 1\), got .* \(or 0.0: off\)",
        ):
            ExperimentConfig(gate_probability=p)


def test_every_filter_option_is_a_config_key_with_its_declared_default_help_and_validation():
    """Options are declared once (the filters' and weight updates' dataclass fields): each appears in the
    configuration with the declared default, in the command line's key list and in the docs, and a bad
    value is refused by the declaring class, naming the key."""
    from agsf_torch.experiments.cli.main import build_parser
    from agsf_torch.experiments.config.loader import config_key_help
    from agsf_torch.filters.registry import CONFIG_OPTIONS

    cfg = ExperimentConfig()
    run_help = build_parser()._subparsers._group_actions[0].choices["run"].format_help()
    for name, opt in CONFIG_OPTIONS.items():
        assert getattr(cfg, name) == opt.default, name
        assert opt.help in config_key_help()[name] and opt.help in " ".join(run_help.split()), name
        assert f"{name}: {opt.help}" in " ".join(ExperimentConfig.__doc__.split()), name
    with pytest.raises(ValueError, match="config key 'tikhonov': tikhonov must be a finite number > 0"):
        ExperimentConfig(tikhonov=-1.0)
    assert ExperimentConfig(cadence=3).filter_options()["cadence"] == 3


def test_a_fault_after_the_end_of_a_simulated_run_is_named_in_a_warning_and_a_replay_is_not_warned(tmp_path):
    """A fault window starting at or after ``duration`` is legal (a longer run meets it) but injects nothing: the
    simulation warns, naming it; reading the configuration does not, nor does a replay, which reads no fault."""
    import warnings

    from agsf_torch.attitude.recordings import Recording
    from agsf_torch.experiments.cli import main as cli
    from agsf_torch.experiments.config.factories import make_env
    from agsf_torch.experiments.run.recorded import record_environment

    faults = '[{kind="star_outage", start=1.0, end=2.0}, {kind="gyro_dropout", start=3.0, end=4.0}]'
    keys = [f"faults={faults}", "duration=3.0", "runs=2", "compile=false", "compile_fused=false"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cfg = load_config("case1", keys)
        record_environment(make_env(load_config("case1", keys[:1] + ["duration=3.1", "runs=2"])), 3, 1)
    with pytest.warns(UserWarning, match=r"fault\(s\) \[1\] start at or after the end of the run \(duration = 3 s\)"):
        rec = record_environment(make_env(cfg), cfg.num_steps, cfg.seed)
    path = Recording(
        **{k: getattr(rec, k) for k in ("time", "gyro", "star_body", "star_inertial", "star_mask")},
        truth_mrp=rec.truth_mrp,
        truth_bias=rec.truth_bias,
    ).save(tmp_path / "log.npz")
    argv = ["run", "case1", *sum((["--set", k] for k in keys), []), "--recording", str(path)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert cli.main([*argv, "--out", str(tmp_path / "replay"), "--quiet"]) == 0


def test_the_weight_updates_compile_follows_the_filters_switch_unless_set():
    """``compile = "auto"`` (the default) leaves the adaptive filters' FPKE kernels to ``compile_fused``; true or
    false sets them; anything else is refused naming the choices."""
    assert load_config("case1", ["compile=auto"]).compile == "auto"
    assert load_config("case1", ["compile=false"]).compile is False
    with pytest.raises(ValueError, match=r"config key 'compile' must be true or false \(or 'auto'\), got 'maybe'"):
        load_config("case1", ["compile=maybe"])


def test_the_prior_attitude_is_gaussian_or_uniform():
    assert load_config("case1", ['prior_attitude="uniform"']).prior_attitude == "uniform"
    assert load_config("lost_in_space").prior_attitude == "uniform"
    with pytest.raises(ValueError, match="config key 'prior_attitude' must be 'gaussian' or 'uniform', got 'flat'"):
        load_config("case1", ['prior_attitude="flat"'])


def test_a_managed_filters_capacity_below_the_components_is_refused_by_name():
    with pytest.raises(ValueError, match="'capacity'"):
        load_config("case1", ['filters=["GSF-managed"]', "components=9", "capacity=8"])
    cfg = load_config("case1", ['filters=["GSF", "GSF-managed"]', "components=9", "capacity=9"])
    assert cfg.filter_options()["capacity"] == 9
    assert load_config("case1", ['filters=["GSF"]', "components=9", "capacity=4"]).components == 9  # unmanaged: unused


def test_an_adaptive_managed_filters_capacity_above_the_qp_limit_is_refused_by_name():
    with pytest.raises(ValueError, match="'capacity' must be ≤ 64 .*AGSF-galerkin-managed"):
        load_config("case1", ['filters=["GSF-managed", "AGSF-galerkin-managed"]', "capacity=128"])
    assert load_config("case1", ['filters=["GSF-managed"]', "capacity=128"]).filter_options()["capacity"] == 128
