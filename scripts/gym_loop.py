"""A gymnasium loop with a filter as the agent.

The environment simulates the spacecraft, the gyro and the star camera; at each
step the agent (an adaptive Gaussian sum filter) propagates with the gyro sample,
updates with the star frame when there is one, and returns its attitude estimate
as the action.  The reward is minus the attitude error angle.

    .venv/bin/python scripts/gym_loop.py            # single environment
    .venv/bin/python scripts/gym_loop.py --batch 64 # natively batched vector environment
"""

from __future__ import annotations

import argparse

import gymnasium
import numpy as np
import torch
from tqdm import tqdm

import envs  # noqa: F401  (registers agsf/StarTrackerAttitude-v0)
from agsf_torch import GaussianMixture
from agsf_torch.filters import AdaptiveGaussianSumFilter
from agsf_torch.models import AttitudeModel, StarVectorMeasurement


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=0, help="vector environment with this many trajectories")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    if args.batch:
        env = gymnasium.make_vec(
            "agsf/StarTrackerAttitude-v0",
            num_envs=args.batch,
            vectorization_mode="vector_entry_point",
            max_steps=args.steps,
        )
    else:
        env = gymnasium.make("agsf/StarTrackerAttitude-v0", max_steps=args.steps)
    obs, info = env.reset(seed=args.seed)
    batched = bool(args.batch)
    as_t = lambda x: torch.as_tensor(np.asarray(x) if not torch.is_tensor(x) else x, dtype=torch.float64)  # noqa: E731

    # prior: a coarse attitude fix 0.2° per axis off the truth (the filter never sees the truth again)
    gen = torch.Generator().manual_seed(args.seed)
    truth = as_t(info["truth_mrp"]).reshape(-1, 3)
    P0 = 1e-6 * torch.eye(3, dtype=torch.float64)
    mean0 = truth + 1e-3 * torch.randn(truth.shape, generator=gen, dtype=torch.float64)
    mix = GaussianMixture.from_gaussian(mean0, P0.expand(len(truth), 3, 3), 3)
    model = AttitudeModel(estimate_bias=False)  # 3-state: the gyro bias is known and removed from the input
    agent = AdaptiveGaussianSumFilter(model)
    dt = env.unwrapped.config.dt if not batched else env.config.dt

    total = 0.0
    bar = tqdm(total=args.steps, desc="gym loop", unit="step")
    for _ in range(args.steps):
        action = agent.estimate(mix)[0]
        obs, reward, terminated, truncated, info = env.step(action if batched else action[0].numpy())
        total += float(np.mean(np.asarray(reward)))
        bias = as_t(info["truth_bias"]).reshape(-1, 3)  # the known bias (here: from the simulator)
        mix = agent.predict(mix, as_t(obs["gyro"]).reshape(-1, 3) - bias, dt)
        mask = as_t(obs["star_mask"]).reshape(len(truth), -1).bool()
        if bool(mask.any()):
            frame = {
                "star_body": as_t(obs["star_body"]).reshape(len(truth), -1, 3),
                "star_inertial": as_t(obs["star_inertial"]).reshape(len(truth), -1, 3),
                "star_mask": mask,
            }
            y, meas = StarVectorMeasurement.from_observation(frame, sigma=10e-6)
            mix = agent.update(mix, y, meas)
        bar.update(1)
        if np.any(np.asarray(truncated)):
            break
    bar.close()
    err = -np.asarray(reward)
    print(f"mean reward {total / args.steps:.3e} rad; final attitude error {np.degrees(err).mean() * 3600:.3f} arcsec")
    env.close()


if __name__ == "__main__":
    main()
