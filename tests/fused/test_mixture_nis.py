"""The fused star update's moment-matched mixture NIS (agsf_torch.fused.mixture_nis)."""

from __future__ import annotations

import mpmath as mp
import pytest
import torch

import agsf_torch.fused.mixture_nis as mixture_nis
from agsf_torch.fused.mixture_nis import mixture_information_nis
from tests.helpers import F64, assert_within

EPS = torch.finfo(F64).eps


def _inputs(gen, B, N=5, d=15, k=3, sigma=1e-3, spread=1e-3, masked=False):
    """Random weights, innovations ``νᵢ`` and square roots ``Hᵢ Lᵢ`` (zero at masked entries)."""
    log_w = torch.log_softmax(torch.randn(B, N, generator=gen, dtype=F64), -1)
    nu = sigma * torch.randn(B, N, d, generator=gen, dtype=F64)
    HL = spread * torch.randn(B, N, d, k, generator=gen, dtype=F64)
    valid = None
    if masked:
        valid = (torch.rand(B, d, generator=gen) > 0.3).to(F64)
        nu = nu * valid.unsqueeze(-2)
        HL = HL * valid[:, None, :, None]
    return log_w, nu, HL, torch.tensor(sigma**2, dtype=F64), valid


def _dense(log_w, nu, HL, sigma2, valid):
    """``ν̄ᵀS̄⁻¹ν̄`` with ``S̄`` formed and solved by LU, and ``κ(S̄)``."""
    w = log_w.exp()
    nu_bar = (w.unsqueeze(-1) * nu).sum(-2)
    delta = nu - nu_bar.unsqueeze(-2)
    S = (w[..., None, None] * (HL @ HL.transpose(-1, -2) + delta.unsqueeze(-1) * delta.unsqueeze(-2))).sum(-3)
    diagonal = sigma2 if valid is None else valid * sigma2 + (1.0 - valid)
    S = S + torch.diag_embed(diagonal * torch.ones_like(nu_bar))
    x = torch.linalg.solve(S, nu_bar.unsqueeze(-1)).squeeze(-1)
    return (nu_bar * x).sum(-1), torch.linalg.cond(S)


@pytest.mark.parametrize("masked", [False, True])
@pytest.mark.parametrize(("sigma", "spread"), [(1e-3, 1e-3), (1e-3, 1e-1)])
def test_the_mixture_nis_equals_a_dense_solve(gen, masked, sigma, spread):
    """Against ``S̄`` formed entry by entry and solved by LU (both backward stable: each within
    ``O(d)·κ(S̄)·ε`` of the exact value), in the covariance form's range (``κ(S̄)`` up to ~10⁵)."""
    args = _inputs(gen, 64, sigma=sigma, spread=spread, masked=masked)
    got = mixture_information_nis(*args)
    want, kappa = _dense(*args)
    assert_within(got, want, 8 * 15 * kappa * EPS * want.abs(), "mixture NIS against a dense LU solve")


def _fifty_digits(log_w, nu, HL, sigma2, valid, b):
    """Trajectory ``b``'s ``ν̄ᵀS̄⁻¹ν̄`` in 50-digit arithmetic from the same float64 inputs."""
    with mp.workdps(50):
        f = lambda t: mp.mpf(float(t))  # noqa: E731
        N, d, k = HL.shape[-3:]
        w = [mp.e ** f(x) for x in log_w[b]]
        w = [x / sum(w) for x in w]
        nb = [sum(w[i] * f(nu[b, i, p]) for i in range(N)) for p in range(d)]
        S = mp.matrix(d, d)
        for p in range(d):
            for q in range(d):
                S[p, q] = sum(
                    w[i]
                    * (
                        sum(f(HL[b, i, p, c]) * f(HL[b, i, q, c]) for c in range(k))
                        + (f(nu[b, i, p]) - nb[p]) * (f(nu[b, i, q]) - nb[q])
                    )
                    for i in range(N)
                )
            S[p, p] += f(sigma2) if valid is None or valid[b, p] > 0 else 1
        x = mp.lu_solve(S, mp.matrix(nb))
        return float(sum(nb[p] * x[p] for p in range(d)))


@pytest.mark.parametrize("masked", [False, True])
def test_where_the_covariance_form_declines_the_information_form_matches_fifty_digits(gen, monkeypatch, masked):
    """A precise sensor after a wide prior with two components (``AAᵀ`` of rank 8 < 15, so
    ``κ(S̄) ≈ 10¹⁵``): every trajectory takes the information form (with stars masked at random, a trajectory
    left with few enough stars may not be rank-deficient and keep the covariance form), whose value is the minimum of a
    regularised least-squares problem solved by QR (an error in its minimiser enters the value at second
    order); its first-order error is the rounding of the final sums over ``K + d = 23`` terms: within
    ``4(K + d)·ε`` of the value's scale ``NIS + 1``."""
    declined = []

    def spy(*args):
        usable = generic_usable(*args)
        declined.append(int((~usable).sum()))
        return usable

    generic_usable = mixture_nis.covariance_form_usable
    monkeypatch.setattr(mixture_nis, "covariance_form_usable", spy)
    args = _inputs(gen, 6, N=2, sigma=1e-9, spread=1e-2, masked=masked)
    got = mixture_information_nis(*args)
    assert len(declined) == 1 and (declined[0] == 6 if not masked else declined[0] >= 1)
    for b in range(6):  # both forms, where each is taken, within the bound
        want = _fifty_digits(*args, b)
        assert_within(got[b], want, 4 * 23 * EPS * (want + 1.0), f"mixture NIS of trajectory {b} (50 digits)")


def test_under_autograd_the_same_numbers_and_their_gradients(gen):
    """With inputs that require gradients ``A`` is built by differentiable operations: the NIS is the
    same to the last bit, and its gradient passes ``gradcheck``."""
    log_w, nu, HL, sigma2, _ = _inputs(gen, 3, N=2, d=6, k=3)
    plain = mixture_information_nis(log_w, nu, HL, sigma2)
    leaves = [t.clone().requires_grad_(True) for t in (log_w, nu, HL)]
    tracked = mixture_information_nis(*leaves, sigma2)
    assert torch.equal(tracked.detach(), plain)
    assert torch.autograd.gradcheck(lambda *a: mixture_information_nis(*a, sigma2), leaves, eps=1e-7, atol=1e-4)


def test_weights_shared_by_a_batch_broadcast(gen):
    """One set of weights ``[N]`` for every trajectory is the same as those weights repeated."""
    log_w, nu, HL, sigma2, _ = _inputs(gen, 7)
    shared = log_w[0]
    assert torch.equal(
        mixture_information_nis(shared, nu, HL, sigma2),
        mixture_information_nis(shared.expand(7, -1).contiguous(), nu, HL, sigma2),
    )


def test_innovations_and_weights_shared_by_a_batch_broadcast_against_the_square_roots(gen):
    """``ν`` and the weights of one mixture with a batch of square roots: every entry of ``A`` is written
    (the same NIS as with the shared inputs repeated, and a dense solve's to ``8d·κ(S̄)·ε``)."""
    log_w, nu, HL, sigma2, _ = _inputs(gen, 7)
    got = mixture_information_nis(log_w[0], nu[0], HL, sigma2)
    repeated = (log_w[0].expand(7, -1), nu[0].expand(7, -1, -1), HL, sigma2, None)
    assert got.shape == (7,) and torch.equal(got, mixture_information_nis(*repeated))
    want, kappa = _dense(*repeated)
    assert_within(got, want, 8 * 15 * kappa * EPS * want.abs(), "mixture NIS with shared innovations")
