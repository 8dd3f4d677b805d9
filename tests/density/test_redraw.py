"""The path-space redraw on sharp star frames (agsf_torch.density.redraw).

Attitude posteriors after 1- and 2-star frames, where a bootstrap filter collapses;
one is checked against an independent numpy importance-sampling estimate.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.stats import multivariate_normal

from agsf_torch.density import PosteriorReference, chart_for
from agsf_torch.filters import GaussianSumFilter
from agsf_torch.mixture import GaussianMixture
from agsf_torch.models import AttitudeModel, StarVectorMeasurement
from agsf_torch.rotations import mrp_to_dcm, mrp_to_quat, quat_multiply, quat_to_mrp, rotvec_to_quat
from tests.density.conftest import f64
from tests.helpers import assert_statistic


def _attitude_problem(B: int, steps: int, gen: torch.Generator):
    """Truth, prior mean, gyro rate and star frames for the 3-state attitude model."""
    P0 = 1e-3 * torch.eye(3, dtype=f64)
    p_true = 0.3 * torch.randn(B, 3, generator=gen, dtype=f64)
    m0 = p_true + torch.randn(B, 3, generator=gen, dtype=f64) @ torch.linalg.cholesky(P0).T
    omega = 0.0628 * torch.tensor([1.0, 1.0, 0.0], dtype=f64).expand(B, 3)
    r = torch.tensor([[0.0, 0.0, 1.0], [0.05, 0.03, 1.0]], dtype=f64)
    r = (r / r.norm(dim=-1, keepdim=True)).expand(B, 2, 3)
    sigma = 1e-5
    q = mrp_to_quat(p_true)
    truth, ys = [], []
    for _ in range(steps):
        q = quat_multiply(rotvec_to_quat(omega * 0.1), q)
        p = quat_to_mrp(q)
        b = (mrp_to_dcm(p).unsqueeze(-3) @ r.unsqueeze(-1)).squeeze(-1)
        truth.append(p)
        ys.append((b + sigma * torch.randn(B, 2, 3, generator=gen, dtype=f64)).flatten(-2))
    return m0, P0, omega, StarVectorMeasurement(r, None, sigma), truth, ys


def test_attitude_star_frames_ess_and_sample_size_convergence():
    """Three 2-star frames (σ_s = 1e-5 rad, prior 7° per axis): the bootstrap ESS
    collapses at the first frame, the path-space redraw keeps a large ESS, and the
    scores of an iterated EKF with K = 2000 and K = 8000 agree within their errors."""
    B = 2
    m0, P0, omega, meas, truth, ys = _attitude_problem(B, 30, torch.Generator().manual_seed(5))
    model = AttitudeModel(estimate_bias=False)
    assert chart_for(model) == "mrp"
    results = {}
    for K in (2000, 8000):
        ref = PosteriorReference(model, m0, P0, num_samples=K, generator=torch.Generator().manual_seed(K), substeps=1)
        filt = GaussianSumFilter(model, update_iterations=3)
        mix = GaussianMixture.from_gaussian(m0, P0.expand(B, 3, 3), 1)
        out = []
        for k in range(30):
            ref.predict(omega, 0.1)
            mix = filt.predict(mix, omega, 0.1)
            if (k + 1) % 10 == 0:
                ref.update(ys[k], meas, hints=mix.means)
                mix = filt.update(mix, ys[k], meas)
                out.append(ref.score(mix))
                rec = ref.history[-1]
                if k + 1 == 10:
                    assert bool((rec.bootstrap_ess < 0.01 * K).all())
                    assert bool(rec.redrawn.all())
                    assert bool((rec.ess > 0.3 * K).all()), rec.ess / K
                assert bool((rec.ess > 0.05 * K).all())
                # the truth is a plausible draw of the reference posterior (χ²₃ Mahalanobis distance)
                w = torch.softmax(ref.log_weights, -1)
                mean = (w[..., None] * ref.samples).sum(1)
                d = ref.samples - mean[:, None]
                cov = (w[..., None, None] * d[..., :, None] * d[..., None, :]).sum(1)
                e = (mean - truth[k]).unsqueeze(-1)
                assert float((e.transpose(-1, -2) @ torch.linalg.solve(cov, e)).max()) < 16.0
        results[K] = out
    for (_, e1), (_, e2) in zip(results[2000], results[8000]):
        assert bool((e2 < e1).all()) and bool((e2 < 0.05).all())
    # independent references (generators seeded K): the difference has both errors in quadrature; 1e-4 over the
    # three frames and B trajectories (the 4σ limit per entry it replaces had 6.3e-5 per entry)
    s1, e1 = (torch.stack(v) for v in zip(*results[2000], strict=True))  # [frames, B]
    s2, e2 = (torch.stack(v) for v in zip(*results[8000], strict=True))
    assert_statistic(s1, s2, torch.sqrt(e1**2 + e2**2), "score with K = 2000 against K = 8000", false_failure=1e-4)


def _np_dcm(p: np.ndarray) -> np.ndarray:
    """C(p) = I + (8[p×]² − 4(1 − s)[p×])/(1 + s)², numpy, ``[..., 3]`` → ``[..., 3, 3]``."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    o = np.zeros_like(x)
    px = np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1), np.stack([-y, x, o], -1)], -2)
    s = (p * p).sum(-1)[..., None, None]
    return np.eye(3) + (8 * px @ px - 4 * (1 - s) * px) / (1 + s) ** 2


def test_attitude_posterior_at_a_frame_matches_brute_force_importance_sampling():
    """A 2-star frame at t₀: the reference's score of an iterated-EKF posterior equals an
    independent numpy importance-sampling estimate of E_p[log q̂] (proposal N(μ, 4P)
    around the filter's posterior, 400 000 draws)."""
    B, K = 2, 4000
    m0, P0, omega, meas, truth, ys = _attitude_problem(B, 1, torch.Generator().manual_seed(21))
    # the frame at t₀ itself: measurement of the initial attitude
    p_true0 = quat_to_mrp(quat_multiply(rotvec_to_quat(-omega * 0.1), mrp_to_quat(truth[0])))
    r = meas.r_inertial
    y = (
        (mrp_to_dcm(p_true0).unsqueeze(-3) @ r.unsqueeze(-1)).squeeze(-1)
        + 1e-5 * torch.randn(B, 2, 3, generator=torch.Generator().manual_seed(2), dtype=f64)
    ).flatten(-2)
    model = AttitudeModel()
    ref = PosteriorReference(model, m0, P0, num_samples=K, generator=torch.Generator().manual_seed(9))
    ref.update(y, meas)
    assert bool(ref.history[-1].redrawn.all())
    filt = GaussianSumFilter(model, update_iterations=3)
    mix = filt.update(GaussianMixture.from_gaussian(m0, P0.expand(B, 3, 3), 1), y, meas)
    score, se = ref.score(mix)

    rng = np.random.default_rng(0)
    N = 400_000
    mu, P = mix.means[:, 0].numpy(), mix.covs[:, 0].numpy()
    brute, brute_se = np.zeros(B), np.zeros(B)
    for b in range(B):
        x = rng.multivariate_normal(mu[b], 4 * P[b], size=N)
        pred = (_np_dcm(x)[:, None] @ r[b].numpy()[None, :, :, None])[..., 0].reshape(N, 6)
        log_w = (
            multivariate_normal(m0[b].numpy(), P0.numpy()).logpdf(x)
            - 0.5 * ((y[b].numpy() - pred) ** 2).sum(-1) / 1e-10
            - multivariate_normal(mu[b], 4 * P[b]).logpdf(x)
        )
        w = np.exp(log_w - log_w.max())
        w /= w.sum()
        phi = multivariate_normal(mu[b], P[b]).logpdf(x)
        est = (w * phi).sum()
        se_bf = np.sqrt((w**2 * (phi - est) ** 2).sum())
        assert 1.0 / (w**2).sum() > 0.2 * N  # the brute force is itself well conditioned
        brute[b], brute_se[b] = est, se_bf
    # two independent importance-sampling estimates: their difference has the standard error of both in quadrature
    # (1e-4 over the B trajectories: the 4σ limit per entry it replaces had 6.3e-5 per entry)
    assert_statistic(
        score.numpy(), brute, np.hypot(se.numpy(), brute_se), "score against brute force", false_failure=1e-4
    )


def test_attitude_single_star_frame_keeps_a_large_ess():
    """One star leaves the rotation about it unobserved: the posterior is a thin ring
    (7° long, µrad wide).  In the multiplicative chart of the redraw proposal the ring
    is straight, so the redraw keeps most of its samples."""
    B, K = 2, 2000
    m0, P0, omega, meas, truth, ys = _attitude_problem(B, 5, torch.Generator().manual_seed(8))
    one = StarVectorMeasurement(meas.r_inertial[:, :1], None, 1e-5)
    ref = PosteriorReference(AttitudeModel(), m0, P0, num_samples=K, generator=torch.Generator().manual_seed(1))
    for _ in range(5):
        ref.predict(omega, 0.1)
    ref.update(ys[4][:, :3], one)
    rec = ref.history[-1]
    assert bool((rec.bootstrap_ess < 0.01 * K).all()) and bool(rec.redrawn.all())
    assert bool((rec.ess > 0.3 * K).all()), rec.ess / K
