"""Recordings and the environment: export simulations, replay recordings through the runner."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from ...attitude.recordings import Recording
from .progress import progress_bar

__all__ = ["record_environment", "RecordingEnv"]


def record_environment(env, num_steps: int, seed: int, progress: bool = False) -> Recording:
    """Step a batched environment ``num_steps`` times (no actions needed) and keep everything.

    Sample 0 is the reset (t = 0); sample k the observation after step k.  ``progress`` shows a
    progress bar on stderr.
    """
    obs, info = env.reset(seed=seed)
    keys = ("gyro", "gyro_valid", "star_body", "star_inertial", "star_mask")
    rows = {k: [torch.as_tensor(obs[k])] for k in keys}
    truth = {"truth_mrp": [torch.as_tensor(info["truth_mrp"])], "truth_bias": [torch.as_tensor(info["truth_bias"])]}
    times = [float(torch.as_tensor(obs["time"]).reshape(-1)[0])]
    zeros = torch.zeros(env.num_envs, 3, dtype=torch.float64)
    for _ in progress_bar(
        range(num_steps), desc="simulating", unit="step", total=num_steps, disable=not progress, leave=False
    ):
        obs, _, _, _, info = env.step(zeros)
        for k in keys:
            rows[k].append(torch.as_tensor(obs[k]))
        for k in truth:
            truth[k].append(torch.as_tensor(info[k]))
        times.append(float(torch.as_tensor(obs["time"]).reshape(-1)[0]))
    arrays = {k: torch.stack(v, 1).numpy() for k, v in {**rows, **truth}.items()}
    arrays["gyro_valid"] = arrays["gyro_valid"].reshape(env.num_envs, -1)
    return Recording(time=np.array(times), **arrays)


def sample_spacing(recording: Recording, name: str = "") -> tuple[float, float]:
    """``(Δt, tolerance)``: the recording's uniform sample spacing (s), judged at the precision of its
    timestamps, or ``ValueError`` (naming the recording ``name``) if the samples are not uniformly spaced:
    the filters step by one constant ``Δt``, so a log with jittered timestamps is resampled first.

    A timestamp ``t`` stored with machine epsilon ``ε`` (float32's if every time is a float32 number,
    else float64's) is known to ``ε|t|/2``, so two spacings may differ by ``2ε max|t|`` from rounding
    alone (Unix-epoch seconds in float64: ~4e-7 s); the tolerance is twice that plus ``1e-9 Δt``.
    """
    t = np.asarray(recording.time, dtype=np.float64)
    if t.size < 2:
        return 0.0, 0.0
    single = np.array_equal(t.astype(np.float32).astype(np.float64), t)
    eps = float(np.finfo(np.float32 if single else np.float64).eps)
    dt = float((t[-1] - t[0]) / (t.size - 1))
    tol = 4.0 * eps * float(np.abs(t).max()) + 1e-9 * dt
    worst = float(np.abs(np.diff(t) - dt).max())
    if worst > tol:
        raise ValueError(
            f"{f'recording {name}: ' if name else ''}the samples are not uniformly spaced (column 'time'): a spacing "
            f"differs from the mean {dt:g} s by {worst:.3g} s, more than the timestamps' precision allows "
            f"({tol:.3g} s); the filters step by one constant dt: resample the log onto a uniform time grid"
        )
    return dt, tol


def has_truth(recording: Recording, name: str = "") -> bool:
    """Whether ``recording`` holds the truth (``truth_mrp`` and ``truth_bias``) to score the filters against;
    ``ValueError`` (naming the recording ``name``) if it holds one of the two columns only."""
    if (recording.truth_mrp is None) != (recording.truth_bias is None):
        have, lack = ("truth_mrp", "truth_bias") if recording.truth_bias is None else ("truth_bias", "truth_mrp")
        raise ValueError(
            f"recording {name} has {have} but not {lack}: a replay scores against the whole truth, give both columns "
            "or neither (a replay of flight data)"
        )
    return recording.truth_mrp is not None


def initial_estimate(recording: Recording, name: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Where the filters start on a recording without the truth: ``(mrp [B, 3], bias [B, 3])``, the file's
    ``initial_mrp`` / ``initial_bias`` (zero if absent) or, without ``initial_mrp``, the star fix of row 0
    (:func:`~agsf_torch.attitude.star_fix.star_fix`) and a zero bias.

    Raises:
        ValueError: no ``initial_mrp`` and a trajectory whose row 0 determines no attitude (fewer than two valid,
            non-parallel stars), naming the recording ``name`` and the trajectory.
    """
    B = recording.num_trajectories
    bias = np.zeros((B, 3)) if recording.initial_bias is None else recording.initial_bias
    if recording.initial_mrp is not None:
        return recording.initial_mrp, bias
    from ...attitude.star_fix import star_fix

    t = torch.as_tensor
    mrp, ok = star_fix(t(recording.star_body[:, 0]), t(recording.star_inertial[:, 0]), t(recording.star_mask[:, 0]))
    if not bool(ok.all()):
        raise ValueError(
            f"recording {name} has neither the truth (truth_mrp and truth_bias) nor an initial estimate (initial_mrp "
            f"[B, 3]; initial_bias [B, 3] optional), and row 0 of trajectory {int((~ok).nonzero()[0, 0])} holds no "
            "star frame that determines an attitude (two valid, non-parallel stars): the filters start around one "
            "of these"
        )
    return mrp.numpy(), bias


def check_recording(recording: Recording, cfg, name: str, *, whole_run: bool = True) -> float:
    """The one check of a recording against a configuration, for ``agsf run --recording`` and ``agsf learn``:
    uniformly spaced samples (:func:`sample_spacing`) at the configuration's ``dt`` (to the timestamps'
    precision), gyro rates that turn less than half a turn per sample (``|ω̃|·Δt < π``: beyond, a sampled
    rotation is not defined — e.g. rates in the wrong unit) and, if ``whole_run``, both truth columns or neither
    and then an initial estimate (:func:`initial_estimate`: ``initial_mrp`` or row 0's star fix), and ``cfg.runs``
    trajectories of at least ``cfg.num_steps`` steps.  Returns ``Δt``; ``ValueError`` naming the recording otherwise."""
    dt, tol = sample_spacing(recording, name)
    if recording.num_samples > 1 and abs(dt - cfg.dt) > tol + 1e-9 * cfg.dt:
        raise ValueError(f"recording {name} is sampled every {dt:g} s; the configuration's dt is {cfg.dt:g} s")
    gyro = np.asarray(recording.gyro, dtype=np.float64)
    if gyro.size:
        rate = float(np.nanmax(np.linalg.norm(gyro, axis=-1)))
        if dt > 0 and not rate * dt < np.pi:
            raise ValueError(
                f"recording {name}: a gyro rate of {rate:g} rad/s turns {rate * dt:g} rad per sample of {dt:g} s, "
                "half a turn or more: not a sampled rotation (are the rates in rad/s?)"
            )
    if whole_run and not has_truth(recording, name):
        initial_estimate(recording, name)  # where the filters start without the truth, or ValueError
    if whole_run and (recording.num_trajectories != cfg.runs or recording.num_samples - 1 < cfg.num_steps):
        raise ValueError(
            f"recording {name} has {recording.num_trajectories} trajectories × {recording.num_samples - 1} steps of "
            f"{dt:g} s; the configuration needs runs={cfg.runs}, ≥ {cfg.num_steps} steps of dt={cfg.dt:g}"
        )
    return dt


class RecordingEnv:
    """Replays a :class:`Recording` with the reset/step interface the Monte Carlo runner uses.

    With the truth (``truth_mrp``, ``truth_bias``) its ``info`` carries it at every sample, and the runner scores
    the filters against it.  Without it ``reset``'s ``info`` carries an initial estimate instead
    (:func:`initial_estimate`: the file's ``initial_mrp`` / ``initial_bias`` or row 0's star fix, ``[B, 3]``) and
    later samples an empty ``info``: the runner starts the filters there and keeps their estimates, covariances and
    innovations, scoring nothing.
    ``config.dt`` is the recording's (uniform) sample spacing.
    """

    def __init__(self, recording: Recording) -> None:
        name = "(in memory)"
        self.start = None if has_truth(recording, name) else initial_estimate(recording, name)  # or ValueError
        dt, _ = sample_spacing(recording)
        self.rec = recording
        self.num_envs = recording.num_trajectories
        self.config = SimpleNamespace(dt=dt, max_steps=recording.num_samples - 1)
        self._k = 0

    def _sample(self, k: int):
        r, t = self.rec, torch.as_tensor
        obs = r.observation(k)
        if self.start is None:  # with the truth
            return obs, {"truth_mrp": t(r.truth_mrp[:, k]), "truth_bias": t(r.truth_bias[:, k])}
        if k > 0:
            return obs, {}
        return obs, {"initial_mrp": t(self.start[0]), "initial_bias": t(self.start[1])}

    def reset(self, seed=None):
        self._k = 0
        return self._sample(0)

    def step(self, action):
        if self._k + 1 >= self.rec.num_samples:
            raise RuntimeError("the recording has no more samples")
        self._k += 1
        obs, info = self._sample(self._k)
        zeros = torch.zeros(self.num_envs, dtype=torch.bool)
        return obs, torch.zeros(self.num_envs, dtype=torch.float64), zeros, zeros, info
