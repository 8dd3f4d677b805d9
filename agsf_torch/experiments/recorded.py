"""Recordings and the environment: export simulations, replay recordings through the runner."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch
from tqdm import tqdm

from ..attitude.recordings import Recording

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
    for _ in tqdm(range(num_steps), desc="simulating", unit="step", disable=not progress, leave=False):
        obs, _, _, _, info = env.step(zeros)
        for k in keys:
            rows[k].append(torch.as_tensor(obs[k]))
        for k in truth:
            truth[k].append(torch.as_tensor(info[k]))
        times.append(float(torch.as_tensor(obs["time"]).reshape(-1)[0]))
    arrays = {k: torch.stack(v, 1).numpy() for k, v in {**rows, **truth}.items()}
    arrays["gyro_valid"] = arrays["gyro_valid"].reshape(env.num_envs, -1)
    return Recording(time=np.array(times), **arrays)


class RecordingEnv:
    """Replays a :class:`Recording` with the reset/step interface the Monte Carlo runner uses.

    The recording must hold the truth (``truth_mrp``, ``truth_bias``): the runner
    scores the filters against it.  ``config.dt`` is the recording's (uniform) sample spacing.
    """

    def __init__(self, recording: Recording) -> None:
        if recording.truth_mrp is None or recording.truth_bias is None:
            raise ValueError("replaying through the Monte Carlo runner needs truth_mrp and truth_bias in the recording")
        steps = np.diff(recording.time)
        if steps.size and not np.allclose(steps, steps[0], rtol=1e-9, atol=0):
            raise ValueError("the runner needs uniformly spaced samples (column 'time')")
        self.rec = recording
        self.num_envs = recording.num_trajectories
        self.config = SimpleNamespace(dt=float(steps[0]) if steps.size else 0.0, max_steps=recording.num_samples - 1)
        self._k = 0

    def _sample(self, k: int):
        r, t = self.rec, torch.as_tensor
        obs = r.observation(k)
        info = {"truth_mrp": t(r.truth_mrp[:, k]), "truth_bias": t(r.truth_bias[:, k])}
        return obs, info

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
