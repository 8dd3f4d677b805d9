"""Shared checks of the one-component attitude filters (the MEKF and USQUE): the same contract, the same refusals."""

from __future__ import annotations

import pytest
import torch

from agsf_torch.mixture import GaussianMixture
from agsf_torch.models import AttitudeModel
from tests.helpers import F64


def assert_bad_input_refused_before_anything_changes(filt, mix: GaussianMixture, u, y, meas) -> None:
    """``filt`` (6-state, on ``mix`` of 4 trajectories with the gyro ``u`` and the frame ``(y, meas)`` of 5 stars,
    after one accepted predict) refuses every bad input with a clear error and changes nothing: not its
    diagnostics, not the belief it was given."""
    cls = type(filt)
    diag_before = filt.diagnostics
    means_before, covs_before = mix.means.clone(), mix.covs.clone()
    three = GaussianMixture.from_gaussian(mix.means[:, 0], mix.covs[:, 0], 3)
    with pytest.raises(ValueError, match="one-component"):
        filt.predict(three, u, 0.1)
    with pytest.raises(ValueError, match="one-component"):
        filt.update(three, y, meas)
    with pytest.raises(ValueError, match="state dimension 6 != model state_dim 3"):
        cls(AttitudeModel()).predict(mix, u, 0.1)
    with pytest.raises(ValueError, match=r"u must have shape \[\.\.\., 3\]"):
        filt.predict(mix, torch.zeros(4, 2, dtype=F64), 0.1)
    with pytest.raises(ValueError, match="u has shape"):
        filt.predict(mix, torch.zeros(5, 3, dtype=F64), 0.1)
    u_nan = u.clone()
    u_nan[1, 2] = float("nan")
    with pytest.raises(ValueError, match="u must be finite"):
        filt.predict(mix, u_nan, 0.1)
    with pytest.raises(ValueError, match="gyro reading"):
        filt.predict(mix, None, 0.1)
    for dt in (0.0, -0.1, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="dt"):
            filt.predict(mix, u, dt)
    with pytest.raises(ValueError, match="predicts 15"):
        filt.update(mix, y[:, :12], meas)
    y_inf = y.clone()
    y_inf[0, 0] = float("inf")
    with pytest.raises(ValueError, match="y must be finite"):
        filt.update(mix, y_inf, meas)
    with pytest.raises(ValueError, match="y has shape"):
        filt.update(mix, y[:3], meas)
    with pytest.raises(TypeError, match="MeasurementModel"):
        filt.update(mix, y, lambda x: x)
    broken = mix.replace(
        covs=mix.covs * torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=F64)[:, None, None, None], validate=False
    )
    with pytest.raises(ValueError, match=r"not positive definite in the input belief at trajectory index \(1,\)"):
        filt.predict(broken, u, 0.1)
    with pytest.raises(ValueError, match=r"not positive definite in the input belief at trajectory index \(1,\)"):
        filt.update(broken, y, meas)
    assert filt.diagnostics is diag_before
    assert torch.equal(mix.means, means_before) and torch.equal(mix.covs, covs_before)
