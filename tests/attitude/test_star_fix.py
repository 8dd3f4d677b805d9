"""The attitude of one star frame (Wahba's problem), batched."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.attitude.star_fix import star_fix
from agsf_torch.rotations import attitude_error_angle, mrp_to_dcm
from tests.helpers import F64, assert_within, random_mrps, random_unit_vectors, relative_bound


def test_exact_vectors_give_the_attitude_to_rounding(gen):
    """Noise-free ``b = C r`` with some stars masked out (their entries garbage): the attitude is recovered to
    rounding (the SVD of a well-spread profile matrix: errors of a few ε)."""
    B, M = 64, 6
    truth = random_mrps(B, gen)
    r = random_unit_vectors(gen, B, M)
    b = (mrp_to_dcm(truth)[:, None] @ r[..., None]).squeeze(-1)
    mask = torch.rand(B, M, generator=gen) < 0.7
    mask[:, :2] = True  # at least two stars each
    b = torch.where(mask[..., None], b, torch.full_like(b, float("nan")))
    p, ok = star_fix(b, r, mask)
    assert ok.all()
    assert_within(attitude_error_angle(p, truth), 0.0, 1e-12, "attitude error of noise-free frames")


def test_agrees_with_scipy_on_noisy_frames(gen):
    """An independent solution of the same problem (scipy's ``Rotation.align_vectors``, one frame at a time)."""
    from scipy.spatial.transform import Rotation

    B, M = 8, 5
    truth = random_mrps(B, gen)
    r = random_unit_vectors(gen, B, M)
    b = (mrp_to_dcm(truth)[:, None] @ r[..., None]).squeeze(-1) + 1e-3 * torch.randn(B, M, 3, generator=gen, dtype=F64)
    b = b / b.norm(dim=-1, keepdim=True)
    p, ok = star_fix(b, r, torch.ones(B, M, dtype=torch.bool))
    C = mrp_to_dcm(p).numpy()
    for k in range(B):
        theirs = Rotation.align_vectors(b[k].numpy(), r[k].numpy())[0].as_matrix()
        # assert_allclose's rtol=1e-7 (numpy's default) beside atol=1e-12, as before
        assert_within(C[k], theirs, relative_bound(theirs, 1e-7, 1e-12), "attitude matrix against scipy's")
    assert ok.all()


def test_a_frame_that_determines_no_attitude_is_flagged():
    r = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]], dtype=F64)
    masks = torch.tensor([[True, True, False], [True, False, False], [False, False, False], [True, False, True]])
    p, ok = star_fix(r.expand(4, 3, 3), r.expand(4, 3, 3), masks)  # two stars; one; none; two parallel
    assert ok.tolist() == [True, False, False, False]
    assert_within(p[0], 0.0, 1e-15, "the identity's MRP")
    with pytest.raises(ValueError, match=r"star_fix needs body and inertial \[..., M, 3\] and mask \[..., M\]"):
        star_fix(r, r, masks)
    bad = r.clone()
    bad[0, 0] = float("inf")
    with pytest.raises(ValueError, match="not finite"):
        star_fix(bad, r, torch.tensor([True, True, False]))


def test_a_simulated_star_frame_gives_the_true_attitude_with_the_expected_spread():
    """The camera's frames (σ_s per axis across each star vector): the fix is the maximum-likelihood attitude, so
    its error ``δθ`` has the covariance ``P = σ_s² (Σ_j (I − b_j b_jᵀ))⁻¹`` (Shuster's QUEST covariance) and
    ``δθᵀ P⁻¹ δθ`` is χ²(3); the mean over 256 trajectories must lie in the 99.9 % band of that average."""
    from scipy.stats import chi2

    import envs
    from agsf_torch.rotations import attitude_error_vector

    env = envs.StarTrackerAttitudeVectorEnv(num_envs=256, max_steps=20)
    obs, info = env.reset(seed=4)
    for _ in range(10):  # the first star frame: t = 1 s
        obs, _, _, _, info = env.step(info["truth_mrp"])
    p, ok = star_fix(obs["star_body"], obs["star_inertial"], obs["star_mask"])
    assert ok.all()
    e = attitude_error_vector(p, info["truth_mrp"])  # [B, 3], rad
    b, m = obs["star_body"], obs["star_mask"].to(F64)[..., None, None]
    information = (m * (torch.eye(3, dtype=F64) - b[..., :, None] * b[..., None, :])).sum(-3) / env.config.sigma_s**2
    nees = (e[:, None, :] @ information @ e[:, :, None]).reshape(-1)
    B = len(nees)
    lo, hi = chi2.ppf(0.0005, 3 * B) / B, chi2.ppf(0.9995, 3 * B) / B
    assert lo < float(nees.mean()) < hi, (float(nees.mean()), lo, hi)
