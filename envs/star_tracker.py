"""Star-tracker attitude environments (gymnasium): single and natively batched.

This module holds the gym adapters, :class:`StarTrackerAttitudeEnv` and
:class:`StarTrackerAttitudeVectorEnv` (the entry points registered by :mod:`envs`),
around the simulation of :mod:`envs.simulator`, configured by
:class:`~envs.config.StarTrackerConfig`.

One step is one gyro period Δt.  Timeline (**[choice]**, documented):

* ``reset`` returns the observation at ``t_0 = 0``: a gyro reading with the bias
  held (``ω(0) + b_0 + noise``, which closes no interval; filters normally ignore
  it) and **no star frame** (``star_mask`` all false).
* ``step(action)`` scores the action — the estimate of the attitude at the time of
  the *last* observation, ``t_k`` — with ``reward = −θ(action, p_k)`` (rad, the
  rotation angle between the two attitudes; any MRP, shadow sets included, is
  accepted with components within ±1e150 — beyond, it is refused before anything
  changes, see :data:`envs._checks.MRP_LIMIT`), then advances the truth over ``(t_k, t_{k+1}]`` with the held rate
  ``ω_{k+1}`` (:mod:`envs.dynamics`) and returns the observation at ``t_{k+1}``:
  the gyro reading ``ω̃_{k+1}`` of that interval (:mod:`envs.gyro`) — the one to
  propagate a filter from ``t_k`` to ``t_{k+1}`` — and, when ``k+1`` is a multiple of
  ``star_period/Δt``, a star frame taken at ``t_{k+1}``.  So with the defaults the
  first star frame arrives at t = 1 s, the paper's setting in which the filters
  first propagate a wide prior.
* ``info`` carries the truth at the new time: ``truth_mrp`` (p_{k+1}, short set
  ``|p| ≤ 1``), ``truth_bias`` (b_{k+1}, rad/s) and ``truth_rate`` (ω_{k+1}, the rate
  held over the step just taken, rad/s); ``reset``'s info the same at t_0 (rate ω(0)).
* The episode is truncated (never terminated) after ``max_steps`` steps.

Randomness is counter-based (:mod:`envs.random`, which also holds the stream ids):
trajectory draws are pure functions of ``(episode seed, step index, stream)``.
``reset(seed=s)`` of the vector env gives trajectory i the episode seed ``s + i``, which is exactly what the single
env gets from ``reset(seed=s + i)``: the trajectories are bit-identical.  An
unseeded reset continues deterministically from the previous episode seed
(``next = splitmix(seed) mod 2⁶²``, the same in both envs), or, before any seeded
reset, takes a fresh seed from the env's ``np_random``.

The vector env (:class:`StarTrackerAttitudeVectorEnv`) runs all B trajectories as one
tensor program and returns torch tensors; all trajectories share the step counter,
so they truncate together and are reset together on the next ``step`` call
(``AutoresetMode.NEXT_STEP``: that call ignores the actions and returns the reset
observation with zero reward).  :meth:`StarTrackerAttitudeVectorEnv.simulate` runs a
whole trajectory batch without actions for Monte Carlo runners (the same step
implementation as stepping, on blocks of steps: :mod:`envs.simulator`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space
from torch import Tensor

from ._checks import check_mrp, check_seeds
from .config import StarTrackerConfig
from .random import SEED_MASK
from .simulator import StarTrackerSimulator

__all__ = ["StarTrackerAttitudeEnv", "StarTrackerAttitudeVectorEnv"]


# ============================================================================ spaces
def _single_spaces(config: StarTrackerConfig) -> tuple[spaces.Dict, spaces.Box]:
    """Observation and action spaces of one trajectory (see :class:`StarTrackerAttitudeEnv`)."""
    m = config.max_stars
    obs = spaces.Dict(
        {
            "gyro": spaces.Box(-np.inf, np.inf, (3,), dtype=np.float64),
            "gyro_valid": spaces.Box(0, 1, (1,), dtype=np.bool_),
            "star_body": spaces.Box(-1.0, 1.0, (m, 3), dtype=np.float64),
            "star_inertial": spaces.Box(-1.0, 1.0, (m, 3), dtype=np.float64),
            "star_mask": spaces.Box(0, 1, (m,), dtype=np.bool_),
            "time": spaces.Box(0.0, config.max_steps * config.dt, (1,), dtype=np.float64),
        }
    )
    # Short-set MRPs lie in the unit ball; shadow MRPs outside the box are accepted too.
    act = spaces.Box(-1.0, 1.0, (3,), dtype=np.float64)
    return obs, act


def _seed_tensor(owner: str, seed: Any, num_envs: int) -> Tensor:
    """Episode seeds ``[B]``: ``seed + i`` for an integer, or one per env from a sequence
    (:func:`envs._checks.check_seeds`: the one check of both envs)."""
    return torch.tensor(check_seeds(owner, seed, num_envs), dtype=torch.int64)


def _action_tensor(owner: str, name: str, value: Any, shape: tuple[int, ...], device: torch.device) -> Tensor:
    """An action as a float64 tensor of ``shape`` (MRPs, last dim 3), checked before anything
    happens: real numbers only (no bool, complex, string or object dtype), the shape, and
    finite components within ±1e150 (:func:`envs._checks.check_mrp`, which names the index).

    Raises:
        ValueError: ``"{owner}: {name} …"`` naming the dtype, the shape or the offending entry.
    """
    if isinstance(value, Tensor):
        if value.dtype.is_complex or value.dtype == torch.bool:
            raise ValueError(f"{owner}: {name} must hold real numbers, got dtype {value.dtype}")
        a = value.to(device=device, dtype=torch.float64)
    else:
        arr = np.asarray(value)
        if arr.dtype.kind not in "iuf":
            raise ValueError(f"{owner}: {name} must hold real numbers, got dtype {arr.dtype}")
        a = torch.as_tensor(arr.astype(np.float64, copy=False), device=device)
    if a.shape != shape:
        what = "an MRP" if len(shape) == 1 else "MRPs"
        raise ValueError(f"{owner}: {name} must be {what} of shape {shape}, got shape {tuple(a.shape)}")
    check_mrp(owner, name, a)
    return a


# ============================================================================ single env
class StarTrackerAttitudeEnv(gym.Env):
    """Single-trajectory star-tracker attitude environment (numpy observations).

    Args:
        config: :class:`StarTrackerConfig` (default: defaults).
        render_mode: must be ``None`` (no rendering).
        **overrides: config fields to replace, e.g. ``dt=0.05, max_stars=8``.

    Observation (dict of numpy arrays): ``gyro [3]`` (rad/s), ``gyro_valid [1]`` (bool:
    false for a missing or saturated sample, see :mod:`envs.faults`), ``star_body [M, 3]``,
    ``star_inertial [M, 3]`` (unit vectors, zeros where masked), ``star_mask [M]``
    (bool), ``time [1]`` (s).  Action: MRP estimate ``[3]`` (real numbers, finite, each
    within ±1e150).  Reward: ``−θ`` (rad).
    Info: ``truth_mrp [3]``, ``truth_bias [3]`` (rad/s), ``truth_rate [3]`` (rad/s).
    See the module docstring for the timeline.
    """

    metadata = {"render_modes": []}

    def __init__(self, config: StarTrackerConfig | None = None, render_mode: str | None = None, **overrides: Any):
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        self.render_mode = None
        self.config = StarTrackerConfig.from_overrides(config, **overrides)
        self.sim = StarTrackerSimulator(self.config, 1)
        self.observation_space, self.action_space = _single_spaces(self.config)
        self._episode_seed: Tensor | None = None

    @staticmethod
    def _np(d: dict[str, Tensor]) -> dict[str, np.ndarray]:
        return {k: v[0].cpu().numpy().copy() for k, v in d.items()}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        """Start an episode; ``seed`` gives the episode seed (see the module docstring)."""
        if seed is not None:  # checked before anything changes
            seeds = _seed_tensor(type(self).__name__, seed, 1)
            seed = int(seeds[0])
        super().reset(seed=seed)
        if seed is None and self._episode_seed is not None:
            seeds = self.sim.next_seeds()
        elif seed is None:
            seeds = torch.tensor([int(self.np_random.integers(0, SEED_MASK + 1))], dtype=torch.int64)
        obs, info = self.sim.reset(seeds)  # may refuse (e.g. a rate profile): the bookkeeping is set after
        self._episode_seed = seeds
        return self._np(obs), self._np(info)

    def step(self, action):
        """Score ``action`` (MRP ``[3]``) against the truth at the current time, then advance Δt.

        Raises:
            ValueError: for an action that is not 3 real, finite numbers within ±1e150
                (naming the dtype, shape or entry), before the state advances.
        """
        if self.sim.q is None:
            raise RuntimeError("call reset() before step()")
        if self.sim.step_index >= self.config.max_steps:
            raise RuntimeError("the episode is over (truncated); call reset()")
        a = _action_tensor("StarTrackerAttitudeEnv", "action", action, (3,), self.sim.device)
        reward = float(self.sim.reward(a[None])[0])
        obs, info = self.sim.advance()
        truncated = self.sim.step_index >= self.config.max_steps
        return self._np(obs), reward, False, truncated, self._np(info)

    def render(self) -> None:
        """No rendering (``render_mode`` is always ``None``)."""
        return None


# ============================================================================ vector env
class StarTrackerAttitudeVectorEnv(VectorEnv):
    """Natively batched star-tracker environment: B trajectories, one tensor program.

    Args:
        num_envs: B ≥ 1.
        config: :class:`StarTrackerConfig` (default: defaults).
        device: torch device (default CPU).
        render_mode: must be ``None``.
        **overrides: config fields to replace.

    Observations, rewards, terminations, truncations and infos are torch tensors with
    a leading batch dimension B (the keys of the single env).  Actions: ``[B, 3]``
    torch tensor or numpy array.  ``metadata["autoreset_mode"] = NEXT_STEP``.
    """

    metadata = {"render_modes": [], "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 1,
        config: StarTrackerConfig | None = None,
        device: torch.device | str = "cpu",
        render_mode: str | None = None,
        **overrides: Any,
    ) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        self.render_mode = None
        self.config = StarTrackerConfig.from_overrides(config, **overrides)
        self.sim = StarTrackerSimulator(self.config, num_envs, device)
        self.num_envs = self.sim.num_envs
        self.device = self.sim.device
        self.single_observation_space, self.single_action_space = _single_spaces(self.config)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._seeded = False
        self._needs_reset = False

    def reset(self, *, seed: int | Sequence[int] | None = None, options: dict[str, Any] | None = None):
        """Start B episodes: trajectory i gets seed ``seed + i`` (or ``seed[i]`` for a sequence).

        Returns:
            ``(obs, info)``: dicts of ``[B, ...]`` torch tensors at t = 0.
        """
        if seed is not None:  # checked before anything changes
            seeds = _seed_tensor(type(self).__name__, seed, self.num_envs)
            if isinstance(seed, (int, np.integer)):
                super().reset(seed=int(seed))
        elif self._seeded:
            seeds = self.sim.next_seeds()
        else:
            base = int(self.np_random.integers(0, SEED_MASK + 1))
            seeds = _seed_tensor(type(self).__name__, base, self.num_envs)
        out = self.sim.reset(seeds)  # may refuse (e.g. a rate profile): the bookkeeping is set after
        self._seeded = True
        self._needs_reset = False
        return out

    def state_dict(self) -> dict[str, Any]:
        """Checkpointable state: the simulator's plus the episode bookkeeping."""
        return {"sim": self.sim.state_dict(), "seeded": self._seeded, "needs_reset": self._needs_reset}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict` (a resumed run continues bit for bit)."""
        self.sim.load_state_dict(state["sim"])
        self._seeded = bool(state["seeded"])
        self._needs_reset = bool(state["needs_reset"])

    def step(self, actions: Any):
        """Score the actions against the truth at the current time, then advance Δt.

        Args:
            actions: MRP estimates ``[B, 3]`` (torch or numpy; real, finite, each
                component within ±1e150, else ``ValueError`` before the state advances).

        Returns:
            ``(obs, reward [B], terminated [B], truncated [B], info)`` as torch tensors.
        """
        if self.sim.q is None:
            raise RuntimeError("call reset() before step()")
        b = self.num_envs
        false = torch.zeros(b, dtype=torch.bool, device=self.device)
        if self._needs_reset:  # NEXT_STEP autoreset: all trajectories ended together
            obs, info = self.reset()
            return obs, torch.zeros(b, dtype=torch.float64, device=self.device), false, false.clone(), info
        a = _action_tensor("StarTrackerAttitudeVectorEnv", "actions", actions, (b, 3), self.device)
        reward = self.sim.reward(a)
        obs, info = self.sim.advance()
        done = self.sim.step_index >= self.config.max_steps
        self._needs_reset = done
        truncated = torch.full((b,), done, dtype=torch.bool, device=self.device)
        return obs, reward, false, truncated, info

    def simulate(self, num_steps: int | None = None, seed: int | Sequence[int] | None = None) -> dict[str, Tensor]:
        """Reset and run ``num_steps`` steps (default ``max_steps``) without actions.

        The numbers equal ``reset(seed)`` followed by ``num_steps`` calls of
        :meth:`step` bit for bit; the env is left at step ``num_steps``.

        Returns:
            The dict of :meth:`StarTrackerSimulator.simulate` (batch-first tensors:
            ``gyro``, ``truth_* [B, T+1, 3]``, ``star_* [B, F, M(, 3)]`` at ``star_steps [F]``).
        """
        n = self.config.max_steps if num_steps is None else num_steps
        if isinstance(n, bool) or int(n) != n or not 0 <= int(n) <= self.config.max_steps:
            raise ValueError(
                f"num_steps must be an integer in [0, max_steps={self.config.max_steps}], got {num_steps!r}"
            )
        self.reset(seed=seed)
        out = self.sim.simulate(int(n))
        self._needs_reset = self.sim.step_index >= self.config.max_steps
        return out

    def render(self) -> None:
        """No rendering."""
        return None
