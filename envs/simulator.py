"""The batched star-tracker simulation behind the gym environments: :class:`StarTrackerSimulator`.

It holds the state of B trajectories (truth attitude, gyro bias, held rate, episode
seeds, the shared step index) and advances it.  There is one implementation of a
time step, :meth:`StarTrackerSimulator._advance_block`, which advances S steps at
once with the block versions of the physics (:meth:`envs.dynamics.AttitudeDynamics.held_rates`,
:func:`envs.dynamics.propagate_quat_block`, :meth:`envs.gyro.Gyro.step_block`,
the noise of a block drawn in one call, the star frames of the block in batched
camera calls).  :meth:`~StarTrackerSimulator.advance` (one env step) runs it with
S = 1, :meth:`~StarTrackerSimulator.simulate` (a whole trajectory batch) with blocks
of up to ``2²⁰ / B`` steps, and both apply the sensor faults with
:meth:`~StarTrackerSimulator._sensor_outputs`, so stepping and ``simulate`` agree bit
for bit by construction.  The timeline and seeding are described in
:mod:`envs.star_tracker`; the random-stream ids are in :mod:`envs.random`.

The reward's error angle is :func:`agsf_torch.rotations.attitude_error_angle`
(batch-independent to the bit, so a vector env equals single envs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, NamedTuple

import torch
from torch import Tensor

from agsf_torch.rotations import attitude_error_angle, mrp_to_quat, quat_to_dcm, quat_to_mrp

from ._checks import check_count, check_mrp
from .camera import StarCamera
from .catalog import shared_hipparcos
from .config import StarTrackerConfig
from .dynamics import AttitudeDynamics
from .faults import apply_gyro_faults, apply_star_faults
from .gyro import Gyro
from .random import (
    STREAM_GYRO_BIAS_WALK,
    STREAM_GYRO_RATE_NOISE,
    STREAM_INITIAL_ATTITUDE,
    STREAM_STAR_NOISE,
    CounterKey,
    counter_normal,
    next_episode_seeds,
)

__all__ = ["StarTrackerSimulator"]

_BLOCK_ELEMENTS = 1 << 20  # simulate(): steps × trajectories (and frames × B × M × 4) per block
#: advance(): the elements of the steps it computes at once and serves one by one (~13 per trajectory and step, 7 per
#: star); at B = 100 that is 54 steps, from B ≈ 5,000 one step at a time.
_AHEAD_ELEMENTS = 1 << 18
_AHEAD_STEPS = 64
_FIRST_AHEAD = 4  # the first block after a reset: a short episode computes few steps it will not take

Stars = tuple[Tensor, Tensor, Tensor]  # (star_body [..., M, 3], star_inertial [..., M, 3], star_mask [..., M])


class _Block(NamedTuple):
    """S steps of B trajectories, time-major, fault-free (see ``_advance_block``)."""

    q: Tensor  # [S, B, 4] truth quaternions q_{k+1} … q_{k+S}
    bias: Tensor  # [S, B, 3] b_{k+1} … b_{k+S} (rad/s)
    rate: Tensor  # [S, B, 3] held rates ω_{k+1} … ω_{k+S} (rad/s)
    gyro: Tensor  # [S, B, 3] readings ω̃_{k+1} … ω̃_{k+S} (rad/s)
    star_steps: Tensor  # [F] int64 step indices of the star frames in the block
    stars: Stars | None  # [F, B, M(, 3)]; None if F = 0


@dataclass
class _Ahead:
    """A block computed ahead by :meth:`StarTrackerSimulator.advance` and how far it has been served."""

    block: _Block
    first_step: int  # the step index the block starts from (its row 0 is step first_step + 1)
    row: int  # the next row to serve
    frame: int  # the next of the block's star frames to serve
    frame_steps: list[int]  # the block's star-frame step indices (block.star_steps as a list)


class StarTrackerSimulator:
    """The batched simulation behind both environments (torch, float64).

    Args:
        config: a :class:`~envs.config.StarTrackerConfig`.
        num_envs: B ≥ 1.
        device: torch device of every tensor.

    State after :meth:`reset` / :meth:`advance` / :meth:`simulate`: ``step_index`` k
    (shared), ``q`` ``[B, 4]`` truth quaternion, ``bias`` ``[B, 3]`` (rad/s), ``rate``
    ``[B, 3]`` (rad/s, held over the last step), ``seeds`` ``[B]`` int64 episode seeds,
    ``last_gyro`` ``[B, 3]`` (rad/s, the fault-free reading of the last step).
    """

    def __init__(self, config: StarTrackerConfig, num_envs: int, device: torch.device | str = "cpu") -> None:
        if not isinstance(config, StarTrackerConfig):
            raise ValueError(f"StarTrackerSimulator: config must be a StarTrackerConfig, got {type(config).__name__}")
        self.config = config
        self.num_envs = check_count("StarTrackerSimulator", "num_envs", num_envs)
        self.device = torch.device(device)
        self.dtype = torch.float64
        self.gyro = Gyro(config.sigma_v, config.sigma_u, config.dt, config.initial_bias)
        self.dynamics = AttitudeDynamics(config.rate, config.dt)
        self.camera = StarCamera(
            shared_hipparcos(config.max_magnitude, self.device),
            fov_deg=config.fov_deg,
            focal_length=config.focal_length,
            max_stars=config.max_stars,
            sigma=config.sigma_s,
            noise=config.star_noise,
            principal_point=config.principal_point,
        )
        self.step_index = 0
        self.seeds: Tensor | None = None
        self.q: Tensor | None = None
        self.bias: Tensor | None = None
        self.rate: Tensor | None = None
        self.last_gyro: Tensor | None = None  # fault-free reading of the last step
        self._ahead: _Ahead | None = None  # advance()'s block computed ahead
        self._ahead_size = _FIRST_AHEAD  # the length of advance()'s next block: doubled each block, from a reset

    # --------------------------------------------------------------- checkpoints
    _STATE = ("seeds", "q", "bias", "rate", "last_gyro")

    def state_dict(self) -> dict[str, Any]:
        """The simulation's full state (tensors and the step index); with the counter-based
        random numbers this is everything a bit-identical continuation needs."""
        state: dict[str, Any] = {"step_index": int(self.step_index)}
        for key in self._STATE:
            value = getattr(self, key)
            state[key] = None if value is None else value.clone()
        return state

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`; shapes must match this simulator's batch."""
        for key in self._STATE:
            value = state[key]
            if value is not None and value.shape[0] != self.num_envs:
                raise ValueError(f"state {key!r} has batch {value.shape[0]}, this simulator {self.num_envs}")
        self.step_index = int(state["step_index"])
        self._ahead, self._ahead_size = None, _FIRST_AHEAD
        for key in self._STATE:
            value = state[key]
            setattr(self, key, None if value is None else value.to(self.device).clone())

    # ------------------------------------------------------------------ helpers
    def _times(self, steps: Tensor | int) -> Tensor:
        """Times ``k·Δt`` (s) of step indices (int or int64 tensor ``[...]``) → float64 ``[...]``."""
        return torch.as_tensor(steps, device=self.device).to(self.dtype) * self.config.dt

    def is_star_step(self, k: int) -> bool:
        """Whether step k (time k·Δt) carries a star frame: ``k ≥ 1`` and ``k % (star_period/Δt) = 0``."""
        return k >= 1 and k % self.config.steps_per_star_frame == 0

    def star_frame(self, q: Tensor, seeds: Tensor, k: Tensor | int) -> Stars:
        """Fault-free star frame of attitudes ``q [..., 4]`` with noise key ``(seeds, k, STREAM_STAR_NOISE)``.

        ``seeds`` (int64) and ``k`` (int or int64 step indices) broadcast to ``[...]``.
        Returns ``(star_body [..., M, 3], star_inertial [..., M, 3], star_mask [..., M])``.
        """
        return tuple(self.camera.observe(quat_to_dcm(q), CounterKey(seeds, k, STREAM_STAR_NOISE)))

    def _star_frames(self, q: Tensor, steps: Tensor) -> Stars:
        """:meth:`star_frame` of ``q [F, B, 4]`` at steps ``[F]``, in chunks of frames that keep
        the camera's temporaries near ``2²⁰`` elements → ``[F, B, M(, 3)]``."""
        assert self.seeds is not None
        f, b, m = q.shape[0], self.num_envs, self.config.max_stars
        body = torch.zeros(f, b, m, 3, dtype=self.dtype, device=self.device)
        inertial = torch.zeros_like(body)
        mask = torch.zeros(f, b, m, dtype=torch.bool, device=self.device)
        chunk = max(1, _BLOCK_ELEMENTS // (4 * b * m))
        for f0 in range(0, f, chunk):
            rows = slice(f0, f0 + chunk)
            body[rows], inertial[rows], mask[rows] = self.star_frame(q[rows], self.seeds[None, :], steps[rows, None])
        return body, inertial, mask

    def _sensor_outputs(
        self, gyro: Tensor, gyro_steps: Tensor | int, stars: Stars, star_steps: Tensor | int
    ) -> tuple[Tensor, Tensor, Stars]:
        """The sensors' reports: fault-free readings with the configured faults applied.

        Args:
            gyro: ``[..., 3]`` readings (rad/s) at step indices ``gyro_steps``
                (broadcastable to ``gyro.shape[:-1]``).
            stars: frames ``[..., M(, 3)]`` at step indices ``star_steps`` (broadcastable
                to ``mask.shape[:-1]``).

        Returns:
            ``(gyro [..., 3], gyro_valid [...] bool, stars)``.
        """
        faults = self.config.faults
        gyro, valid = apply_gyro_faults(faults, gyro, self._times(gyro_steps))
        if faults and bool(stars[2].any()):  # frames without stars have nothing to corrupt
            stars = apply_star_faults(faults, self.camera.catalog.r, *stars, self._times(star_steps))
        return gyro, valid, stars

    def _no_stars(self) -> Stars:
        """An empty frame ``[B, M(, 3)]``: zero vectors, mask all false."""
        m, b = self.config.max_stars, self.num_envs
        body = torch.zeros(b, m, 3, dtype=self.dtype, device=self.device)
        return body, body.clone(), torch.zeros(b, m, dtype=torch.bool, device=self.device)

    def _obs(self, gyro: Tensor, stars: Stars) -> dict[str, Tensor]:
        """Observation dict at the current step from the fault-free reading and frame ``[B, ...]``."""
        k = self.step_index
        gyro, valid, stars = self._sensor_outputs(gyro, k, stars, k)
        return {
            "gyro": gyro,
            "gyro_valid": valid[:, None],
            "star_body": stars[0],
            "star_inertial": stars[1],
            "star_mask": stars[2],
            "time": torch.full((self.num_envs, 1), k * self.config.dt, dtype=self.dtype, device=self.device),
        }

    def _info(self) -> dict[str, Tensor]:
        assert self.q is not None and self.bias is not None and self.rate is not None
        return {"truth_mrp": quat_to_mrp(self.q), "truth_bias": self.bias.clone(), "truth_rate": self.rate.clone()}

    # ------------------------------------------------------------------ the time step
    def _advance_block(self, num_steps: int) -> _Block:
        """Advance every trajectory by S = ``num_steps`` ≥ 1 steps: the one implementation of a step.

        Step ``k → k+1`` holds the rate ``ω_{k+1} = rate(t_k + Δt/2)``, propagates the
        truth quaternion, walks the bias and forms the gyro reading with the normals
        of key ``(seed, k+1, stream)``, and at a star step takes a frame of ``q_{k+1}``
        with key ``(seed, k+1, STREAM_STAR_NOISE)``.  Updates the state to step ``k+S``.
        """
        assert self.q is not None and self.bias is not None and self.seeds is not None
        k0, b, dt = self.step_index, self.num_envs, self.config.dt
        steps = torch.arange(k0 + 1, k0 + num_steps + 1, device=self.device)  # k+1 for each step
        omega = self.dynamics.held_rates([k * dt for k in range(k0, k0 + num_steps)], b, self.dtype, self.device)
        seeds, nxt = self.seeds[None, :], steps[:, None]
        n_v = counter_normal(seeds, nxt, STREAM_GYRO_RATE_NOISE, (3,), dtype=self.dtype)
        n_u = counter_normal(seeds, nxt, STREAM_GYRO_BIAS_WALK, (3,), dtype=self.dtype)
        q = self.dynamics.step_block(self.q, omega)
        gyro, bias = self.gyro.step_block(omega, self.bias, n_v, n_u)
        rows = [j for j in range(num_steps) if self.is_star_step(k0 + 1 + j)]
        star_steps = steps[rows]
        block = _Block(q, bias, omega, gyro, star_steps, self._star_frames(q[rows], star_steps) if rows else None)
        # Everything computed: only now does the state move, to the last rows (copied when the block is longer, so
        # that the state does not pin its memory); a failure above leaves it where it was.
        self.q, self.bias, self.rate, self.last_gyro = (
            x[-1] if num_steps == 1 else x[-1].clone() for x in (q, bias, omega, gyro)
        )
        self.step_index = k0 + num_steps
        return block

    # ------------------------------------------------------------------ API
    def reset(self, seeds: Tensor) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """Start episodes with int64 seeds ``[B]``; returns ``(obs, info)`` at t = 0 (see
        :class:`~envs.star_tracker.StarTrackerAttitudeEnv` for the keys)."""
        cfg = self.config
        b = self.num_envs
        seeds = seeds.to(device=self.device, dtype=torch.int64).reshape(b)
        if cfg.initial_attitude == "random":
            z = counter_normal(seeds, 0, STREAM_INITIAL_ATTITUDE, (4,), dtype=self.dtype)
            q = z / torch.linalg.vector_norm(z, dim=-1, keepdim=True)
        else:
            p0 = torch.tensor(cfg.initial_attitude, dtype=self.dtype, device=self.device)
            q = mrp_to_quat(p0).expand(b, 4).clone()
        bias = self.gyro.initial_bias_tensor((b,), self.dtype, self.device)
        t0 = torch.zeros(b, dtype=self.dtype, device=self.device)
        rate = self.dynamics.rate(t0).expand(b, 3).clone()  # a callable profile is checked here
        n_v = counter_normal(seeds, 0, STREAM_GYRO_RATE_NOISE, (3,), dtype=self.dtype)
        # Everything computed: only now is the state replaced.
        self.seeds, self.step_index, self.q, self.bias, self.rate = seeds, 0, q, bias, rate
        self.last_gyro = self.gyro.read(self.rate, self.bias, n_v)
        self._ahead, self._ahead_size = None, _FIRST_AHEAD
        return self._obs(self.last_gyro, self._no_stars()), self._info()

    def advance(self) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """One step (Δt) for every trajectory; returns ``(obs, info)`` at the new time.

        ``obs``: ``gyro [B, 3]`` (rad/s), ``gyro_valid [B, 1]``, ``star_body / star_inertial
        [B, M, 3]``, ``star_mask [B, M]`` (all false between frames), ``time [B, 1]`` (s);
        ``info``: ``truth_mrp [B, 3]``, ``truth_bias [B, 3]``, ``truth_rate [B, 3]`` (rad/s).

        With a constant rate the steps are computed ahead in blocks (:meth:`_advance_block`: 4 steps after a reset,
        doubling to ``_AHEAD_STEPS``, within ``_AHEAD_ELEMENTS`` elements, never past ``max_steps``) and served one
        by one: a step's random numbers are keyed by its index, so the numbers are those of one step at a time, bit
        for bit, and the state after each call is that step's (:meth:`state_dict`, :meth:`simulate` and
        :meth:`reset` see no block; change the state through :meth:`load_state_dict`, not by assigning its
        attributes).  A failure while a block is computed leaves the state at the last step served.  A callable
        rate profile is called when its step is taken (it may refuse a rate then, or have effects of its own): one
        step at a time.
        """
        if self._ahead is None:
            k0 = self.step_index
            block = self._advance_block(self._steps_ahead())
            self._ahead = _Ahead(block, k0, 0, 0, block.star_steps.tolist())
            self._ahead_size = min(2 * self._ahead_size, _AHEAD_STEPS)
        ahead = self._ahead
        block, j = ahead.block, ahead.row
        k = ahead.first_step + j + 1
        stars = self._no_stars()
        if ahead.frame < len(ahead.frame_steps) and ahead.frame_steps[ahead.frame] == k:
            stars = tuple(s[ahead.frame] for s in block.stars)  # type: ignore[union-attr]
            ahead.frame += 1
        ahead.row = j + 1
        if ahead.row == block.q.shape[0]:
            self._ahead = None
        self.q, self.bias, self.rate, self.last_gyro = (x[j] if x.shape[0] == 1 else x[j].clone() for x in block[:4])
        self.step_index = k
        return self._obs(self.last_gyro, stars), self._info()  # type: ignore[arg-type]

    def _steps_ahead(self) -> int:
        """How many steps :meth:`advance` computes at once from the current step."""
        if self.dynamics.rate_fn is not None:
            return 1
        per_step = self.num_envs * (13 + 7 * self.config.max_stars)
        left = self.config.max_steps - self.step_index
        return max(1, min(self._ahead_size, _AHEAD_STEPS, _AHEAD_ELEMENTS // per_step, left))

    def reward(self, action: Tensor) -> Tensor:
        """``−θ(action, p_k)`` (rad) against the current truth; ``action [B, 3]`` (MRP) → ``[B]``.

        Raises:
            ValueError: for a non-finite action or one with a component beyond ±1e150
                (:func:`envs._checks.check_mrp`), naming the index; nothing changes.
        """
        assert self.q is not None, "call reset() first"
        check_mrp("StarTrackerSimulator", "action", action)
        return -attitude_error_angle(action, quat_to_mrp(self.q))

    def next_seeds(self) -> Tensor:
        """Seeds of the next episode derived from the current ones: ``[B]`` int64 in [0, 2⁶²)."""
        assert self.seeds is not None
        return next_episode_seeds(self.seeds)

    def simulate(self, num_steps: int) -> dict[str, Tensor]:
        """Advance ``num_steps`` steps from the current state, stacking everything.

        Runs :meth:`_advance_block` (the step of :meth:`advance`) on blocks of up to
        ``2²⁰ / B`` steps and applies the faults once to the stacked readings, so the
        numbers equal step-by-step stepping bit for bit.  Temporaries stay at ~2²⁰
        elements per tensor besides the outputs.

        Returns:
            a dict, batch-first (``T = num_steps``, ``F`` star frames among steps
            ``k₀+1 … k₀+T``, ``k₀`` the step index on entry):
            ``time [T+1]`` (s), ``step [T+1]`` (int64), ``gyro [B, T+1, 3]`` (rad/s; index 0
            is the reading on entry, i.e. the reset reading after a reset), ``gyro_valid
            [B, T+1]`` (bool, false for missing or saturated samples, :mod:`envs.faults`),
            ``truth_mrp / truth_bias / truth_rate [B, T+1, 3]``, ``star_steps [F]``
            (int64 step indices), ``star_time [F]`` (s), ``star_body / star_inertial
            [B, F, M, 3]``, ``star_mask [B, F, M]``.
        """
        assert self.q is not None and self.seeds is not None and self.bias is not None
        assert self.rate is not None and self.last_gyro is not None
        if num_steps < 0:
            raise ValueError(f"num_steps must be ≥ 0, got {num_steps}")
        self._ahead = None  # from the current step (advance()'s block computed ahead is dropped)
        k0, b, m = self.step_index, self.num_envs, self.config.max_stars
        opts: dict[str, Any] = {"dtype": self.dtype, "device": self.device}
        steps = torch.arange(k0, k0 + num_steps + 1, device=self.device)
        n_frames = sum(1 for k in range(k0 + 1, k0 + num_steps + 1) if self.is_star_step(k))
        keys = ("gyro", "truth_mrp", "truth_bias", "truth_rate")
        out = {key: torch.empty(b, num_steps + 1, 3, **opts) for key in keys}
        out["truth_mrp"][:, 0], out["truth_bias"][:, 0] = quat_to_mrp(self.q), self.bias
        out["truth_rate"][:, 0], out["gyro"][:, 0] = self.rate, self.last_gyro
        body = torch.zeros(b, n_frames, m, 3, **opts)
        inertial = torch.zeros(b, n_frames, m, 3, **opts)
        mask = torch.zeros(b, n_frames, m, dtype=torch.bool, device=self.device)
        star_steps = torch.empty(n_frames, dtype=torch.int64, device=self.device)
        block_steps, f = max(1, _BLOCK_ELEMENTS // b), 0
        for j0 in range(0, num_steps, block_steps):
            blk = self._advance_block(min(block_steps, num_steps - j0))
            cols = slice(j0 + 1, j0 + 1 + blk.q.shape[0])
            out["truth_mrp"][:, cols] = quat_to_mrp(blk.q).transpose(0, 1)
            out["truth_bias"][:, cols] = blk.bias.transpose(0, 1)
            out["truth_rate"][:, cols] = blk.rate.transpose(0, 1)
            out["gyro"][:, cols] = blk.gyro.transpose(0, 1)
            if blk.stars is not None:
                frames = slice(f, f + blk.star_steps.numel())
                star_steps[frames] = blk.star_steps
                body[:, frames], inertial[:, frames], mask[:, frames] = (s.transpose(0, 1) for s in blk.stars)
                f = frames.stop
        gyro, valid, stars = self._sensor_outputs(out.pop("gyro"), steps, (body, inertial, mask), star_steps)
        return {
            "time": self._times(steps),
            "step": steps,
            "gyro": gyro,
            "gyro_valid": valid,
            **out,
            "star_steps": star_steps,
            "star_time": self._times(star_steps),
            "star_body": stars[0],
            "star_inertial": stars[1],
            "star_mask": stars[2],
        }
