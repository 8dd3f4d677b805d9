"""What a configuration builds: the simulated environment, the filters and the prior covariance."""

from __future__ import annotations

import torch

from ...constants import DEG_PER_HOUR
from ...filter_loop import FilterSetup
from ...filters.registry import filter_spec
from ...models import AttitudeModel
from .loader import ExperimentConfig

__all__ = ["make_env", "make_filters", "prior_covariance", "filter_model", "loop_options"]


def make_env(cfg: ExperimentConfig):
    """The batched star-tracker environment of a configuration (warning of faults it never reaches:
    :meth:`~agsf_torch.experiments.config.loader.ExperimentConfig.warn_unreached_faults`)."""
    import envs

    cfg.warn_unreached_faults()

    return envs.StarTrackerAttitudeVectorEnv(num_envs=cfg.runs, **cfg.env_settings())


def filter_model(cfg: ExperimentConfig) -> AttitudeModel:
    """The attitude model every filter of a configuration runs on (σ_v scaled by ``filter_sigma_v_scale``)."""
    return AttitudeModel(
        estimate_bias=cfg.estimate_bias, sigma_v=cfg.sigma_v * cfg.filter_sigma_v_scale, sigma_u=cfg.sigma_u
    )


def make_filters(cfg: ExperimentConfig) -> dict[str, FilterSetup]:
    """The filters a configuration names, built by the registry (:mod:`agsf_torch.filters.registry`),
    all on the same attitude model."""
    model = filter_model(cfg)
    options = cfg.filter_options()
    setups = {}
    for name in cfg.filters:
        spec = filter_spec(name)
        filt = spec.build(model, **options)
        setups[name] = FilterSetup(filt, cfg.components, cfg.spread) if spec.mixture else FilterSetup(filt, 1)
    return setups


def prior_covariance(cfg: ExperimentConfig) -> torch.Tensor:
    """The prior covariance ``[n, n]``: ``prior_var`` (MRP²) per attitude axis and, with the bias
    estimated, ``prior_bias_sigma_deg_per_hr`` squared (in (rad/s)²) per bias axis."""
    n = filter_model(cfg).state_dim
    sb = (cfg.prior_bias_sigma_deg_per_hr * DEG_PER_HOUR) ** 2
    return torch.diag(torch.tensor([cfg.prior_var] * 3 + [sb] * 3, dtype=torch.float64)[:n])


def loop_options(cfg: ExperimentConfig) -> dict:
    """The configuration's keyword arguments of the Monte Carlo loop (:func:`~agsf_torch.experiments.run.runner.monte_carlo_steps`,
    :func:`~agsf_torch.experiments.run.runner.run_monte_carlo`): steps, prior covariance, the filters' star noise (σ_s scaled by
    ``filter_sigma_s_scale``) and its model, the seed and whether the bias is estimated."""
    return {
        "num_steps": cfg.num_steps,
        "prior_cov": prior_covariance(cfg),
        "sigma_s": cfg.sigma_s * cfg.filter_sigma_s_scale,
        "seed": cfg.seed,
        "estimate_bias": cfg.estimate_bias,
        "noise_model": cfg.star_noise_model,
        "uniform_attitude": cfg.prior_attitude == "uniform",
    }
