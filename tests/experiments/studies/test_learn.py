"""``agsf learn`` drives the same filter loop as ``agsf run``: a gyro dropout is handled alike."""

from __future__ import annotations

import math

import torch

from agsf_torch.attitude.learning import attitude_log_likelihood
from agsf_torch.experiments.config.factories import loop_options
from agsf_torch.experiments.config.loader import load_preset
from agsf_torch.experiments.run.experiment import make_env, make_filters
from agsf_torch.experiments.run.recorded import RecordingEnv, record_environment
from agsf_torch.experiments.run.runner import monte_carlo_steps
from agsf_torch.experiments.studies.learn import learning_problem
from tests.helpers import assert_within

EPS = torch.finfo(torch.float64).eps


def _faults_with_an_early_dropout():
    """The ``faults`` preset, shortened to 12 s, its gyro dropout moved to 3–6 s, the EKF (what learn fits).

    The gyro period is 0.125 s so that the recorded sample times are exact multiples: the
    runner steps by the configured period, learning by the recorded spacing (which for
    0.1 s differs from 0.1 in the last bit)."""
    cfg = load_preset("faults")
    dropout = next(f for f in cfg.faults if f["kind"] == "gyro_dropout")
    return cfg.replace(
        runs=3,
        duration=12.0,
        dt=0.125,
        star_period=1.0,
        filters=["EKF"],
        faults=[{**dropout, "start": 3.0, "end": 6.0}],
    )


def test_learn_treats_a_gyro_dropout_as_run_does():
    cfg = _faults_with_an_early_dropout()
    rec = record_environment(make_env(cfg), cfg.num_steps, cfg.seed)
    assert rec.gyro_valid is not None and (~rec.gyro_valid).sum() > 0  # the dropout is in the data
    configured, kwargs = learning_problem(cfg, rec)

    run_total, run_terms, held = torch.zeros((), dtype=torch.float64), torch.zeros((), dtype=torch.float64), 0
    steps = monte_carlo_steps(RecordingEnv(rec), make_filters(cfg), **loop_options(cfg))
    for step in steps:
        if step.index == 0:
            assert torch.equal(step.prior_mean, kwargs["prior_mean"])  # the same prior draw
        fs = step.filters["EKF"]
        held += int(fs.extra["gyro_held"].sum())
        if fs.log_likelihood is not None:
            run_total = run_total + fs.log_likelihood.sum()
            run_terms = run_terms + fs.log_likelihood.abs().sum()
    assert held == int((~rec.gyro_valid[:, 1:]).sum()) > 0

    params = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in configured.items()}
    learn_total = attitude_log_likelihood(rec, params, **kwargs)
    assert math.isfinite(float(learn_total))
    # the same terms summed in another order (learning sums each trajectory over time first): n additions of terms
    # whose magnitudes add up to run_terms round to at most n·ε·run_terms apart
    additions = cfg.num_steps * rec.num_trajectories
    assert_within(float(learn_total), float(run_total), additions * EPS * float(run_terms), "the run's log-likelihood")


def test_learn_without_the_hold_would_differ():
    """The dropout matters to the likelihood: zeroed readings taken as real rates give another value."""
    cfg = _faults_with_an_early_dropout()
    rec = record_environment(make_env(cfg), cfg.num_steps, cfg.seed)
    configured, kwargs = learning_problem(cfg, rec)
    params = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in configured.items()}
    held = attitude_log_likelihood(rec, params, **kwargs)
    raw = type(rec)(**{**rec.__dict__, "gyro_valid": None})  # the dropout's zero readings as if valid
    assert float(attitude_log_likelihood(raw, params, **kwargs)) < float(held) - 1.0
