"""``agsf learn``: fit noise-model parameters on simulated or recorded trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from ...attitude.learning import PARAMETERS, fit_attitude_parameters
from ...attitude.recordings import Recording
from ...constants import DEG_PER_HOUR
from ...filter_loop import PRIOR_SEED_OFFSET, sample_prior
from ...storage.files import write_json, write_text
from ..config.loader import REPLAY_IGNORED, ExperimentConfig
from ..report.tensorboard import clear_events
from ..run.experiment import make_env, prepare_output, prior_covariance
from ..run.recorded import check_recording, record_environment
from ..run.resources import check_memory

__all__ = ["learn", "learning_problem", "check_learnable", "MIN_STAR_FRAMES"]


def learning_problem(cfg: ExperimentConfig, rec: Recording) -> tuple[dict, dict]:
    """What ``agsf learn`` fits a recording with, the same filter setup as ``agsf run``.

    Returns:
        ``(configured, likelihood_kwargs)``: the configured parameter values (the
        filter's: σ scaled by the ``filter_*_scale`` keys) and the keyword arguments of
        :func:`~agsf_torch.attitude.learning.attitude_log_likelihood` — the EKF with the
        configuration's update iterations, innovation gate and star noise model, the prior
        drawn as the runner draws it (:func:`~agsf_torch.filter_loop.sample_prior`).
    """
    if rec.truth_mrp is None:
        raise ValueError("learning needs a prior mean: the recording has no truth_mrp (column)")
    P0 = prior_covariance(cfg)
    n = P0.shape[0]
    zeros = np.zeros_like(rec.truth_mrp[:, 0])
    truth0 = torch.cat(
        (
            torch.as_tensor(rec.truth_mrp[:, 0]),
            torch.as_tensor(rec.truth_bias[:, 0] if rec.truth_bias is not None else zeros),
        ),
        -1,
    )[:, :n]
    mean0 = sample_prior(truth0, P0, torch.Generator().manual_seed(cfg.seed + PRIOR_SEED_OFFSET))
    configured = {
        "sigma_v": cfg.sigma_v * cfg.filter_sigma_v_scale,
        "sigma_u": cfg.sigma_u,
        "sigma_s": cfg.sigma_s * cfg.filter_sigma_s_scale,
        "bias": [cfg.gyro_bias_deg_per_hr * DEG_PER_HOUR] * 3,
        "reg": cfg.reg,
        "prior_scale": 1.0,
    }
    kwargs = {
        "prior_mean": mean0,
        "prior_cov": P0,
        "filter_kind": "EKF",
        "estimate_bias": cfg.estimate_bias,
        "update_iterations": cfg.update_iterations,
        "noise_model": cfg.star_noise_model,
        "gate_probability": cfg.filter_options()["gate_probability"],
    }
    return configured, kwargs


#: Star frames (samples with a valid star) a recording needs for the likelihood to constrain the noise
#: parameters: the gyro noise shows only in how the attitude drifts between two frames.
MIN_STAR_FRAMES = 2


def check_learnable(rec: Recording) -> None:
    """Refuse (``ValueError`` saying why) a recording whose likelihood cannot constrain the noise parameters:
    fewer than :data:`MIN_STAR_FRAMES` star frames in some trajectory (none: the likelihood does not depend
    on the star noise, and the gyro noise shows only between frames)."""
    frames = np.asarray(rec.star_mask).any(-1).sum(-1)  # [B]
    if int(frames.min()) < MIN_STAR_FRAMES:
        b = int(frames.argmin())
        raise ValueError(
            f"the recording has {int(frames[b])} star frame(s) in trajectory {b} of {rec.gyro.shape[1]} samples; "
            f"learning needs at least {MIN_STAR_FRAMES} (the noise shows in the drift between frames)"
        )


def learn(
    cfg: ExperimentConfig,
    names: list[str],
    out: Path,
    *,
    recording: str | Path | None = None,
    max_iter: int = 40,
    force: bool = False,
) -> str:
    """Fit ``names`` by maximum likelihood (EKF, ``cfg.update_iterations``); report learned vs configured.

    Data: ``recording`` if given (identified by its contents, not its path), else ``cfg.runs``
    simulated trajectories.  The configured values are the filter's (σ scaled by the
    ``filter_*_scale`` keys); the filter is set up as ``agsf run`` sets it up
    (:func:`learning_problem`).  The names, the data and the memory estimate (unless
    ``force``) are checked before ``out`` is created.
    """
    unknown = [k for k in names if k not in PARAMETERS]
    if not names or unknown or len(set(names)) != len(names):
        raise ValueError(f"--learn must name distinct parameters from {', '.join(PARAMETERS)}, got {','.join(names)!r}")
    if recording is not None:
        rec = Recording.load(recording)
        check_recording(rec, cfg, str(recording), whole_run=False)
        check_learnable(rec)
        source = f"recording={rec.content_digest()}"
    else:
        check_memory(cfg, force=force)
        rec, source = record_environment(make_env(cfg), cfg.num_steps, cfg.seed), "simulated"
    configured, kwargs = learning_problem(cfg, rec)
    digest = cfg.digest(replay=recording is not None)  # a replay: of the keys it reads
    ignored = REPLAY_IGNORED if recording is not None else ()
    out = prepare_output(
        Path(out), "learn", f"{digest}:{','.join(names)}:{source}:max_iter={max_iter}", cfg.to_dict(), ignored
    )
    from torch.utils.tensorboard import SummaryWriter

    clear_events(out / "tensorboard")  # a rerun replaces its events (the curve's steps would repeat)
    writer = SummaryWriter(str(out / "tensorboard"))

    def log(i, nll, values):
        writer.add_scalar("learn/nll", nll, i)
        for k, v in values.items():
            for j, x in enumerate(v if isinstance(v, list) else [v]):
                writer.add_scalar(f"learn/{k}" + (f"_{j}" if isinstance(v, list) else ""), x, i)

    try:
        res = fit_attitude_parameters(rec, configured, names, max_iter=max_iter, log=log, **kwargs)
    finally:
        writer.close()
    lines = [f"learn ({res.message}; −log-likelihood {res.nll:.6g}):"]
    for k in names:
        if res.inside[k] is None:
            why = "the fit did not converge" if not res.converged else res.notes.get(k) or "the interval is undefined"
            flag = "no verdict: " + why
        elif res.inside[k]:
            flag = "consistent with the data"
        else:
            flag = "OUTSIDE the 95 % interval: mis-modelled" if k != "bias" else "mis-modelled (Wald test at 5 %)"
        lines.append(
            f"  {k}: learned {_digits(res.learned[k])}, 95 % interval {_digits(res.interval[k])}, "
            f"configured {_digits(res.configured[k])} — {flag}"
        )
    if res.joint and len(names) > 1:
        j = res.joint
        verdict = "consistent with the data" if j["consistent"] else "mis-modelled"
        lines.append(
            f"  jointly: {verdict} (likelihood ratio {j['statistic']:.3g}, χ² on {j['dof']} degrees of freedom, p = "
            f"{j['p_value']:.3g}: it flags a correct model 5 % of the time, as each line above does on its own)"
        )
    report = "\n".join(lines)
    write_json(
        out / "learn.json",
        res.__dict__,
        indent=2,
        default=str,  # strict JSON (write_json): undefined numbers are null
    )
    write_text(out / "learn.md", report + "\n")
    return report


def _digits(value) -> str:
    """A learned value, interval or configured value for the report: 5 significant digits, a list per axis and
    a ``(low, high)`` pair as such (``learn.json`` keeps every digit)."""
    if isinstance(value, tuple):
        return "(" + ", ".join(_digits(v) for v in value) + ")"
    if isinstance(value, list):
        return "[" + ", ".join(_digits(v) for v in value) + "]"
    return f"{value:.5g}"
