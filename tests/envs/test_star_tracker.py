"""Star-tracker environments: API, timeline, truth consistency, seeding, bad configs.

Statistical bounds are stated where used: chi-square central intervals of
probability 1 − 1e-6 for variances, and a false-failure rate of 1e-6 per assertion
(:func:`tests.helpers.assert_statistic`) for means, correlations and the weighted sum
of squares of the star errors.
"""

from __future__ import annotations

import ast
import math
import warnings
from pathlib import Path

import gymnasium
import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode
from scipy import stats

import envs
from agsf_torch.rotations import attitude_error_angle, cross_matrix, mrp_compose, mrp_to_dcm
from envs import (
    ENV_ID,
    StarTrackerAttitudeEnv,
    StarTrackerAttitudeVectorEnv,
    StarTrackerConfig,
    register_envs,
)
from envs.gyro import DEFAULT_SIGMA_U, DEFAULT_SIGMA_V
from tests.helpers import assert_statistic, assert_within

ALPHA = 1e-6


def _bits_equal(a: np.ndarray, b: np.ndarray) -> bool:
    a, b = np.ascontiguousarray(a), np.ascontiguousarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


def _np(d: dict) -> dict:
    return {k: v.numpy() for k, v in d.items()}


# ------------------------------------------------------------------ registration / API
def test_registration_is_idempotent_and_has_both_entry_points():
    register_envs()
    register_envs()
    spec = gymnasium.spec(ENV_ID)
    assert spec.entry_point == "envs.star_tracker:StarTrackerAttitudeEnv"
    assert spec.vector_entry_point == "envs.star_tracker:StarTrackerAttitudeVectorEnv"


def test_check_env_passes():
    env = gymnasium.make(ENV_ID)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env.unwrapped)
    # The only complaints allowed: the gyro reading is unbounded (a Gaussian noise model).
    others = [str(w.message) for w in caught if "infinity" not in str(w.message)]
    assert others == []
    env.close()


def test_make_passes_config_fields_and_config_objects():
    env = gymnasium.make(ENV_ID, star_period=0.5, max_stars=3, max_steps=20)
    cfg = env.unwrapped.config
    assert (cfg.star_period, cfg.max_stars, cfg.max_steps) == (0.5, 3, 20)
    obs, info = env.reset(seed=0)
    assert obs["star_body"].shape == (3, 3) and obs["star_mask"].dtype == np.bool_
    assert obs["gyro"].dtype == np.float64 and obs["time"].tolist() == [0.0]
    assert set(info) == {"truth_mrp", "truth_bias", "truth_rate"}
    env2 = gymnasium.make(ENV_ID, config=StarTrackerConfig(dt=0.05, star_period=0.5), max_stars=4)
    assert env2.unwrapped.config.dt == 0.05 and env2.unwrapped.config.max_stars == 4


def test_make_vec_uses_the_native_vector_env():
    venv = gymnasium.make_vec(ENV_ID, num_envs=4, vectorization_mode="vector_entry_point", max_steps=12)
    assert isinstance(venv.unwrapped, StarTrackerAttitudeVectorEnv)
    assert venv.num_envs == 4 and venv.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP
    single = StarTrackerAttitudeEnv(max_steps=12)
    assert venv.single_observation_space == single.observation_space
    assert venv.single_action_space == single.action_space
    obs, info = venv.reset(seed=3)
    assert all(isinstance(v, torch.Tensor) for v in (*obs.values(), *info.values()))
    assert obs["gyro"].shape == (4, 3) and obs["star_body"].shape == (4, 5, 3)
    assert obs["star_mask"].shape == (4, 5) and obs["time"].shape == (4, 1)
    assert _np(obs) in venv.observation_space
    obs, reward, term, trunc, info = venv.step(np.zeros((4, 3)))
    assert reward.shape == (4,) and reward.dtype == torch.float64
    assert term.dtype == torch.bool and trunc.dtype == torch.bool
    assert info["truth_mrp"].shape == (4, 3)


# ------------------------------------------------------------------ seeding
def _rate_profile(t: torch.Tensor) -> torch.Tensor:
    return torch.stack((0.05 * torch.sin(t), 0.03 + 0 * t, 0.02 * torch.cos(t)), -1)


@pytest.mark.parametrize(
    "overrides",
    [
        dict(star_period=0.5, max_steps=30),
        dict(
            star_period=0.3,
            max_steps=30,
            rate=_rate_profile,
            star_noise="unit_vector",
            initial_attitude=(0.1, -0.2, 0.3),
            max_stars=7,
        ),
    ],
)
def test_vector_env_equals_single_envs_bit_for_bit(overrides):
    b, seed = 6, 123
    venv = StarTrackerAttitudeVectorEnv(b, **overrides)
    g = torch.Generator().manual_seed(0)
    actions = 0.3 * torch.randn(30, b, 3, generator=g, dtype=torch.float64)
    v_obs, v_info = venv.reset(seed=seed)
    history = [(v_obs, v_info, None, None)]
    for k in range(30):
        o, r, te, tr, i = venv.step(actions[k])
        history.append((o, i, r, tr))
    for j in (0, 2, 5):
        env = StarTrackerAttitudeEnv(**overrides)
        obs, info = env.reset(seed=seed + j)
        for key in obs:
            assert _bits_equal(obs[key], history[0][0][key][j].numpy()), key
        for key in info:
            assert _bits_equal(info[key], history[0][1][key][j].numpy()), key
        for k in range(30):
            obs, reward, term, trunc, info = env.step(actions[k, j].numpy())
            o, i, r, tr = history[k + 1]
            for key in obs:
                assert _bits_equal(obs[key], o[key][j].numpy()), (k, key)
            for key in info:
                assert _bits_equal(info[key], i[key][j].numpy()), (k, key)
            assert reward == float(r[j]) and trunc == bool(tr[j]) and term is False


def test_seed_sequence_and_batch_size_independence():
    venv = StarTrackerAttitudeVectorEnv(2, max_steps=15)
    out = venv.simulate(15, seed=[5, 9])
    big = StarTrackerAttitudeVectorEnv(300, max_steps=15).simulate(15, seed=5)
    small = StarTrackerAttitudeVectorEnv(1, max_steps=15).simulate(15, seed=9)
    for key, value in out.items():
        if value.dim() >= 2 and value.shape[0] == 2:
            assert torch.equal(value[0], big[key][0]), key
            assert torch.equal(value[1], small[key][0]), key


def test_simulate_equals_stepping():
    b = 5
    venv = StarTrackerAttitudeVectorEnv(b, max_steps=40, star_period=0.4)
    obs, info = venv.reset(seed=7)
    obs_hist, info_hist = [obs], [info]
    for _ in range(25):
        obs, _, _, _, info = venv.step(torch.zeros(b, 3, dtype=torch.float64))
        obs_hist.append(obs)
        info_hist.append(info)
    out = venv.simulate(25, seed=7)
    assert out["gyro"].shape == (b, 26, 3) and out["truth_mrp"].shape == (b, 26, 3)
    assert out["star_steps"].tolist() == [4, 8, 12, 16, 20, 24]
    assert out["star_body"].shape == (b, 6, 5, 3) and out["star_mask"].shape == (b, 6, 5)
    assert torch.equal(out["time"], torch.arange(26, dtype=torch.float64) * 0.1)
    for k in range(26):
        assert torch.equal(out["gyro"][:, k], obs_hist[k]["gyro"])
        for key in ("truth_mrp", "truth_bias", "truth_rate"):
            assert torch.equal(out[key][:, k], info_hist[k][key]), (k, key)
    for f, k in enumerate(out["star_steps"].tolist()):
        for key in ("star_body", "star_inertial", "star_mask"):
            assert torch.equal(out[key][:, f], obs_hist[k][key]), (k, key)
    # The env continues from where simulate stopped, as after 25 steps.
    o1, *_ = venv.step(np.zeros((b, 3)))
    venv2 = StarTrackerAttitudeVectorEnv(b, max_steps=40, star_period=0.4)
    venv2.reset(seed=7)
    for _ in range(26):
        o2, *_ = venv2.step(np.zeros((b, 3)))
    for key in o1:
        assert torch.equal(o1[key], o2[key]), key
    with pytest.raises(ValueError, match=r"num_steps must be an integer in \[0, max_steps=40\], got 41"):
        venv.simulate(41)


# ------------------------------------------------------------------ timeline
def test_timeline_star_frames_truncation_and_autoreset():
    cfg = dict(dt=0.1, star_period=0.3, max_steps=7)
    venv = StarTrackerAttitudeVectorEnv(3, **cfg)
    obs, _ = venv.reset(seed=11)
    assert not bool(obs["star_mask"].any()) and bool((obs["star_body"] == 0).all())
    assert obs["time"].flatten().tolist() == [0.0] * 3
    for k in range(1, 8):
        obs, reward, term, trunc, info = venv.step(torch.zeros(3, 3))
        assert obs["time"].flatten().tolist() == [k * 0.1] * 3
        assert bool(obs["star_mask"].any()) == (k % 3 == 0)
        assert not bool(term.any())
        assert trunc.tolist() == [k == 7] * 3
    # NEXT_STEP autoreset: this call ignores the actions and starts new episodes.
    obs, reward, term, trunc, info = venv.step(torch.full((3, 3), float("nan")))
    assert obs["time"].flatten().tolist() == [0.0] * 3
    assert reward.tolist() == [0.0] * 3 and not bool(trunc.any()) and not bool(term.any())
    # The new episodes are those a single env starts with an unseeded reset after its episode.
    env = StarTrackerAttitudeEnv(**cfg)
    env.reset(seed=12)
    for _ in range(7):
        *_, trunc_single, _ = env.step(np.zeros(3))
    assert trunc_single
    with pytest.raises(RuntimeError, match="episode is over"):
        env.step(np.zeros(3))
    obs_single, info_single = env.reset()
    for key in obs_single:
        assert _bits_equal(obs_single[key], obs[key][1].numpy()), key
    assert _bits_equal(info_single["truth_mrp"], info["truth_mrp"][1].numpy())
    assert not _bits_equal(info_single["truth_mrp"], info["truth_mrp"][0].numpy())


def test_step_before_reset_and_bad_actions_raise():
    env = StarTrackerAttitudeEnv()
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(3))
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action must be an MRP of shape \(3,\), got shape \(2,\)"):
        env.step(np.zeros(2))
    with pytest.raises(ValueError, match="action must be finite"):
        env.step(np.array([np.nan, 0.0, 0.0]))
    venv = StarTrackerAttitudeVectorEnv(2)
    venv.reset(seed=0)
    with pytest.raises(ValueError, match=r"actions must be MRPs of shape \(2, 3\), got shape \(3,\)"):
        venv.step(np.zeros(3))
    with pytest.raises(ValueError, match="actions must be finite"):
        venv.step(torch.full((2, 3), float("inf")))


def test_reward_is_minus_the_error_angle_at_the_current_time():
    venv = StarTrackerAttitudeVectorEnv(4, max_steps=10)
    _, info = venv.reset(seed=21)
    truth = info["truth_mrp"]
    _, reward, _, _, info = venv.step(truth)  # exact estimate of the attitude at t_0
    assert_within(reward, 0.0, 1e-15, "reward of the exact estimate")  # the angle of a rounded identity
    truth = info["truth_mrp"]
    shadow = -truth / (truth * truth).sum(-1, keepdim=True)
    _, reward, _, _, info = venv.step(shadow.numpy())  # the same attitude, numpy action
    assert_within(reward, 0.0, 1e-14, "reward of the exact estimate's shadow MRP")
    truth = info["truth_mrp"]
    axis = torch.nn.functional.normalize(torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64), dim=-1)
    offset = axis * math.tan(0.1 / 4)  # a 0.1 rad rotation
    _, reward, _, _, _ = venv.step(mrp_compose(offset.expand(4, 3), truth))
    assert_within(reward, -0.1, 1e-12, "reward of an estimate 0.1 rad off")
    angle = attitude_error_angle(mrp_compose(offset.expand(4, 3), truth), truth)
    # (torch.allclose's default rtol of 1e-5 dropped: both sides are one angle of the same attitudes, to rounding)
    assert_within(-reward, angle, 1e-14, "reward against the error angle at the current time")


# ------------------------------------------------------------------ truth consistency
def test_truth_follows_the_held_rate_exactly():
    venv = StarTrackerAttitudeVectorEnv(8, max_steps=60, rate=_rate_profile)
    out = venv.simulate(60, seed=4)
    C = mrp_to_dcm(out["truth_mrp"])  # [B, T+1, 3, 3]
    w = out["truth_rate"][:, 1:]
    step = torch.linalg.matrix_exp(-cross_matrix(w) * 0.1)
    assert_within(C[:, 1:], step @ C[:, :-1], 1e-13, "attitude matrix one step on")
    t_mid = out["time"][:-1] + 0.05
    # the profile at the same midpoint t_k + Δt/2 (the same float): the same rate, bit for bit (an absolute 1e-17,
    # a few ulps of these rates, held only where both round alike)
    assert torch.equal(w, _rate_profile(t_mid)[None].expand(8, -1, -1))


def test_fixed_and_random_initial_attitudes():
    env = StarTrackerAttitudeEnv(initial_attitude=(0.1, -0.2, 0.3))
    _, info = env.reset(seed=0)
    assert_within(info["truth_mrp"], np.array([0.1, -0.2, 0.3]), 1e-15, "fixed initial MRP through the quaternion")
    # Random: uniform on SO(3), so E[C] = 0 (each entry has variance 1/3).
    n = 4000
    _, info = StarTrackerAttitudeVectorEnv(n).reset(seed=99)
    mean_C = mrp_to_dcm(info["truth_mrp"]).mean(0)
    assert_statistic(mean_C, 0.0, math.sqrt(1 / 3 / n), "mean attitude matrix", false_failure=ALPHA)


def test_noise_free_star_vectors_are_C_r():
    venv = StarTrackerAttitudeVectorEnv(64, sigma_s=0.0, max_steps=20)
    out = venv.simulate(20, seed=1)
    f = out["star_steps"]  # after a reset, step k is index k of the truth arrays
    C = mrp_to_dcm(out["truth_mrp"][:, f])  # [B, F, 3, 3]
    pred = torch.einsum("bfij,bfmj->bfmi", C, out["star_inertial"])
    m = out["star_mask"]
    assert int(m.sum()) > 0.99 * m.numel()
    assert_within(out["star_body"][m], pred[m], 1e-12, "noise-free star vectors against C r")


def test_star_noise_matches_sigma_s_in_the_env():
    """Focal-plane noise: per star the radial error has variance σ²cos⁴θ and the
    tangential σ²cos²θ (θ the off-axis angle).  The ratio Σ|e⊥|² / Σσ²(cos⁴θ + cos²θ)
    must be 1 within 5 of its standard deviations sqrt(Σ2σ⁴(cos⁸θ + cos⁴θ)) / Σσ²(…)."""
    sigma = 10e-6
    venv = StarTrackerAttitudeVectorEnv(4000, max_steps=50)
    out = venv.simulate(50, seed=3)
    f = out["star_steps"]
    C = mrp_to_dcm(out["truth_mrp"][:, f])
    v = torch.einsum("bfij,bfmj->bfmi", C, out["star_inertial"])[out["star_mask"]]
    e = out["star_body"][out["star_mask"]] - v
    e_perp = e - (e * v).sum(-1, keepdim=True) * v
    c2 = v[:, 2] ** 2  # cos²θ
    expected = sigma**2 * (c2 * c2 + c2)
    sd = torch.sqrt((2 * sigma**4 * (c2**4 + c2**2)).sum())
    ratio = float((e_perp * e_perp).sum(-1).sum() / expected.sum())
    assert e.shape[0] >= 99_000
    assert_statistic(
        ratio, 1.0, float(sd / expected.sum()), "star errors' sum of squares / expected", false_failure=ALPHA
    )


def test_gyro_noise_and_bias_walk_in_the_env():
    b, steps, dt = 4000, 50, 0.1
    venv = StarTrackerAttitudeVectorEnv(b, max_steps=steps)
    out = venv.simulate(steps, seed=8)
    bias = out["truth_bias"]
    err = (out["gyro"][:, 1:] - out["truth_rate"][:, 1:] - 0.5 * (bias[:, 1:] + bias[:, :-1])).reshape(-1)
    inc = (bias[:, 1:] - bias[:, :-1]).reshape(-1)
    n = err.numel()  # 600 000
    lo, hi = stats.chi2.ppf(ALPHA / 2, n) / n, stats.chi2.ppf(1 - ALPHA / 2, n) / n
    var_meas = DEFAULT_SIGMA_V**2 / dt + DEFAULT_SIGMA_U**2 * dt / 12
    var_inc = DEFAULT_SIGMA_U**2 * dt
    assert lo <= float((err * err).mean()) / var_meas <= hi
    assert lo <= float((inc * inc).mean()) / var_inc <= hi
    # Independent over time: lag-1 correlation of the measurement noise (standard error 1/sqrt(n)).
    e3 = err.reshape(b, steps, 3)
    lag = float(torch.corrcoef(torch.stack((e3[:, 1:].reshape(-1), e3[:, :-1].reshape(-1))))[0, 1])
    se = 1 / math.sqrt(e3[:, 1:].numel())
    assert_statistic(lag, 0.0, se, "lag-1 correlation of the gyro noise", false_failure=ALPHA)
    # The bias is a random walk: var(b_50 − b_0) = 50 σ_u² Δt (n = 12 000 samples).
    total = (bias[:, -1] - bias[:, 0]).reshape(-1)
    m = total.numel()
    lo_m, hi_m = stats.chi2.ppf(ALPHA / 2, m) / m, stats.chi2.ppf(1 - ALPHA / 2, m) / m
    assert lo_m <= float((total * total).mean()) / (steps * var_inc) <= hi_m
    # The reset reading holds the initial bias: ω(0) + b_0 + noise, each a normal draw of variance var_meas.
    e0 = out["gyro"][:, 0] - out["truth_rate"][:, 0] - bias[:, 0]
    assert_statistic(e0, 0.0, math.sqrt(var_meas), "reset reading's noise", false_failure=ALPHA)


# ------------------------------------------------------------------ configuration
NAN, INF = float("nan"), float("inf")


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("dt", 0.0, r"dt must be finite and > 0, got 0.0"),
        ("dt", -0.1, r"dt must be finite and > 0, got -0.1"),
        ("dt", NAN, r"dt must be finite and > 0, got nan"),
        ("star_period", 0.0, r"star_period must be finite and > 0, got 0.0"),
        ("star_period", -1.0, r"star_period must be finite and > 0, got -1.0"),
        ("star_period", 0.15, r"star_period must be a positive integer multiple of dt=0.1, got 0.15"),
        ("star_period", 0.05, r"star_period must be a positive integer multiple of dt=0.1, got 0.05"),
        ("sigma_v", -1e-7, r"sigma_v must be finite and ≥ 0, got -1e-07"),
        ("sigma_v", INF, r"sigma_v must be finite and ≥ 0, got inf"),
        ("sigma_u", -1e-10, r"sigma_u must be finite and ≥ 0, got -1e-10"),
        ("sigma_u", NAN, r"sigma_u must be finite and ≥ 0, got nan"),
        ("initial_bias", (0.0, NAN, 0.0), r"initial_bias must be 3 finite numbers, got \(0.0, nan, 0.0\)"),
        ("initial_bias", (1e-7, 1e-7), r"initial_bias must be 3 finite numbers, got \(1e-07, 1e-07\)"),
        ("sigma_s", -1e-5, r"sigma_s must be finite and ≥ 0, got -1e-05"),
        ("sigma_s", NAN, r"sigma_s must be finite and ≥ 0, got nan"),
        ("fov_deg", 0.0, r"fov_deg must be in \(0, 180\) degrees, got 0.0"),
        ("fov_deg", (8.0, -8.0), r"fov_deg must be in \(0, 180\) degrees, got \(8.0, -8.0\)"),
        ("fov_deg", (180.0, 8.0), r"fov_deg must be in \(0, 180\) degrees, got \(180.0, 8.0\)"),
        ("fov_deg", (8.0, NAN), r"fov_deg must be 2 finite numbers, got \(8.0, nan\)"),
        ("focal_length", 0.0, r"focal_length must be finite and > 0, got 0.0"),
        ("focal_length", -0.065, r"focal_length must be finite and > 0, got -0.065"),
        ("max_stars", 0, r"max_stars must be an integer ≥ 1, got 0"),
        ("max_stars", 2.5, r"max_stars must be an integer ≥ 1, got 2.5"),
        ("max_stars", True, r"max_stars must be an integer ≥ 1, got True"),
        ("max_magnitude", NAN, r"max_magnitude must be finite, got nan"),
        ("max_magnitude", INF, r"max_magnitude must be finite, got inf"),
        ("star_noise", "pixel", r"star_noise must be one of \('focal_plane', 'unit_vector'\), got 'pixel'"),
        ("principal_point", (NAN, 0.0), r"principal_point must be 2 finite numbers, got \(nan, 0.0\)"),
        ("rate", (NAN, 0.0, 0.0), r"rate must be 3 finite numbers \(rad/s\), got \(nan, 0.0, 0.0\)"),
        ("rate", (0.1, 0.1), r"rate must be 3 finite numbers \(rad/s\), got \(0.1, 0.1\)"),
        ("initial_attitude", "identity", r"initial_attitude must be 'random' or an MRP \(3 numbers\), got 'identity'"),
        ("initial_attitude", (0.0, INF, 0.0), r"initial_attitude must be 3 finite numbers, got \(0.0, inf, 0.0\)"),
        ("max_steps", 0, r"max_steps must be an integer ≥ 1, got 0"),
        ("max_steps", 1.5, r"max_steps must be an integer ≥ 1, got 1.5"),
    ],
)
def test_bad_config_values_raise(field, value, message):
    with pytest.raises(ValueError, match=rf"StarTrackerConfig: {message}"):
        StarTrackerConfig(**{field: value})


def test_bad_values_raise_through_make_and_constructors():
    with pytest.raises(ValueError, match=r"StarTrackerConfig: focal_length must be finite and > 0, got -1.0"):
        gymnasium.make(ENV_ID, focal_length=-1.0)
    with pytest.raises(ValueError, match=r"StarTrackerConfig: dt must be finite and > 0, got -0.1"):
        gymnasium.make_vec(ENV_ID, num_envs=2, vectorization_mode="vector_entry_point", dt=-0.1)
    with pytest.raises(ValueError, match=r"max_magnitude=-5.0 leaves no stars"):
        StarTrackerAttitudeEnv(max_magnitude=-5.0)
    with pytest.raises(ValueError, match=r"unknown field\(s\) \['fov'\]"):
        StarTrackerAttitudeEnv(fov=8.0)
    with pytest.raises(ValueError, match=r"num_envs must be an integer ≥ 1, got 0"):
        StarTrackerAttitudeVectorEnv(0)
    with pytest.raises(ValueError, match=r"render_mode must be None"):
        StarTrackerAttitudeEnv(render_mode="human")


def test_config_normalises_values():
    cfg = StarTrackerConfig(fov_deg=10, initial_bias=1e-7, star_period=0.5, rate=[0, 0, 1])
    assert cfg.fov_deg == (10.0, 10.0) and cfg.initial_bias == (1e-7,) * 3
    assert cfg.steps_per_star_frame == 5 and cfg.rate == (0.0, 0.0, 1.0)


def test_envs_imports_only_the_rotations_module_of_agsf_torch():
    root = Path(envs.__file__).parent
    for path in root.glob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
            for name in names:
                if name.startswith("agsf_torch"):
                    assert name == "agsf_torch.rotations", (path.name, name)


@pytest.mark.parametrize(
    ("seed", "named"),
    [
        ([3, -7], r"seed\[1\] must lie in \[0, 2\*\*63 - 1\], got -7"),
        ([3, 2**64 + 3], r"seed\[1\] must lie in \[0, 2\*\*63 - 1\]"),  # wrapped: two trajectories alike
        (2**63 - 1, r"seed 9223372036854775807 \+ 1 .* exceeds 2\*\*63 - 1"),
        ("37", r"seed must be an integer or 2 integers \(one per trajectory\), got str"),
        ([3.0, 4.0], r"seed\[0\] must be an integer, got float"),
        (2.5, r"seed must be an integer or 2 integers \(one per trajectory\), got float"),
        (True, r"seed must be an integer or 2 integers \(one per trajectory\), got bool"),
        (torch.tensor([1.0, 2.0]), r"seed must hold integers, got a torch.float32 tensor"),
    ],
)
def test_the_vector_env_checks_every_seed_before_anything_changes(seed, named):
    env = envs.StarTrackerAttitudeVectorEnv(num_envs=2, max_steps=5)
    env.reset(seed=11)
    with pytest.raises(ValueError, match=named):
        env.reset(seed=seed)
    fresh = envs.StarTrackerAttitudeVectorEnv(num_envs=2, max_steps=5)
    fresh.reset(seed=11)
    action = torch.zeros(2, 3, dtype=torch.float64)
    assert torch.equal(env.step(action)[0]["gyro"], fresh.step(action)[0]["gyro"])  # the episode went on untouched


@pytest.mark.parametrize("seed", [7, np.int64(7), np.uint32(7), [7, 8], np.array([7, 8]), torch.tensor([7, 8])])
def test_every_integer_type_gives_the_same_episodes(seed):
    """Python and NumPy integers, sequences, arrays and integer tensors: the same seeds, the same episodes;
    the single env takes NumPy integers too and refuses bool as the vector env does."""
    ref, _ = envs.StarTrackerAttitudeVectorEnv(num_envs=2, max_steps=5).reset(seed=7)
    got, _ = envs.StarTrackerAttitudeVectorEnv(num_envs=2, max_steps=5).reset(seed=seed)
    assert torch.equal(got["gyro"], ref["gyro"]) and torch.equal(got["star_body"], ref["star_body"])
    single = envs.StarTrackerAttitudeEnv(max_steps=5)
    if not isinstance(seed, (list, np.ndarray, torch.Tensor)):
        one, _ = single.reset(seed=seed)
        assert np.array_equal(one["gyro"], ref["gyro"][0].numpy())
    with pytest.raises(ValueError, match="seed must be an integer"):
        single.reset(seed=True)
    with pytest.raises(ValueError, match=r"seed must be an integer, got \[1, 2\]"):  # not "or 1 integers"
        single.reset(seed=[1, 2])


def _steps(venv, n: int, seed: int) -> list:
    """``n`` steps of ``venv`` after a reset: every observation and info, and the simulator's state after each."""
    venv.reset(seed=seed)
    zero = torch.zeros(venv.num_envs, 3, dtype=torch.float64)
    out = []
    for _ in range(n):
        obs, _, _, _, info = venv.step(zero)
        out.append((obs, info, venv.sim.state_dict()))
    return out


def test_steps_computed_ahead_are_those_of_one_step_at_a_time(monkeypatch):
    from envs import simulator

    b, n = 3, 130  # past two blocks computed ahead, star frames inside and across their edges
    ahead = _steps(StarTrackerAttitudeVectorEnv(b, max_steps=n, star_period=0.3), n, 11)
    monkeypatch.setattr(simulator, "_AHEAD_STEPS", 1)
    single = _steps(StarTrackerAttitudeVectorEnv(b, max_steps=n, star_period=0.3), n, 11)
    assert StarTrackerAttitudeVectorEnv(b, max_steps=n).sim._steps_ahead() == 1
    for (o1, i1, s1), (o2, i2, s2) in zip(ahead, single):
        assert all(torch.equal(o1[k], o2[k]) for k in o1) and all(torch.equal(i1[k], i2[k]) for k in i1)
        assert s1["step_index"] == s2["step_index"]
        assert all(torch.equal(s1[k], s2[k]) for k in ("q", "bias", "rate", "seeds", "last_gyro"))


def test_a_block_computed_ahead_is_dropped_by_simulate_reset_and_a_restored_state():
    b = 2
    venv = StarTrackerAttitudeVectorEnv(b, max_steps=100, star_period=0.3)
    reference = _steps(StarTrackerAttitudeVectorEnv(b, max_steps=100, star_period=0.3), 60, 5)
    zero = torch.zeros(b, 3, dtype=torch.float64)
    venv.reset(seed=5)
    for _ in range(10):
        venv.step(zero)
    assert venv.sim._ahead is not None  # in the middle of a block
    saved = venv.sim.state_dict()
    venv.sim.simulate(20)  # from step 10 to 30
    obs, _, _, _, _ = venv.step(zero)
    assert all(torch.equal(obs[k], reference[30][0][k]) for k in obs)  # step 31, not the block's step 11
    venv.sim.load_state_dict(saved)
    obs, _, _, _, _ = venv.step(zero)
    assert all(torch.equal(obs[k], reference[10][0][k]) for k in obs)  # step 11 again
    venv.reset(seed=5)
    obs, _, _, _, _ = venv.step(zero)
    assert all(torch.equal(obs[k], reference[0][0][k]) for k in obs)


def test_a_callable_rate_profile_is_stepped_one_step_at_a_time():
    calls = []

    def rate(t):
        calls.append(t.clone())
        return torch.full((*t.shape, 3), 0.01, dtype=t.dtype)

    venv = StarTrackerAttitudeVectorEnv(2, max_steps=50, rate=rate)
    venv.reset(seed=0)
    calls.clear()
    venv.step(torch.zeros(2, 3, dtype=torch.float64))
    assert venv.sim._steps_ahead() == 1 and venv.sim._ahead is None
    assert len(calls) == 1 and torch.equal(calls[0], torch.full((2,), 0.05, dtype=torch.float64))  # t_k + Δt/2


def test_a_failure_while_steps_are_computed_ahead_leaves_the_state_at_the_last_step_served(monkeypatch):
    b = 2
    reference = _steps(StarTrackerAttitudeVectorEnv(b, max_steps=100, star_period=0.3), 40, 9)
    venv = StarTrackerAttitudeVectorEnv(b, max_steps=100, star_period=0.3)
    zero = torch.zeros(b, 3, dtype=torch.float64)
    venv.reset(seed=9)
    for _ in range(12):  # to the end of the blocks of 4 and 8 steps: the next step computes a block of 16
        venv.step(zero)
    assert venv.sim._ahead is None
    before = venv.sim.state_dict()
    real = venv.sim.star_frame
    monkeypatch.setattr(venv.sim, "star_frame", lambda *a: (_ for _ in ()).throw(MemoryError("no room")))
    with pytest.raises(MemoryError):
        venv.step(zero)
    after = venv.sim.state_dict()
    assert after["step_index"] == before["step_index"] == 12
    assert all(torch.equal(after[k], before[k]) for k in ("q", "bias", "rate", "seeds", "last_gyro"))
    monkeypatch.setattr(venv.sim, "star_frame", real)
    obs, _, _, _, _ = venv.step(zero)
    assert all(torch.equal(obs[k], reference[12][0][k]) for k in obs)  # step 13, as if nothing had failed
