"""Units and the sensor constants shared by the estimator, the simulator and the experiments.

A leaf module.  The simulator (``envs``, which depends on :mod:`agsf_torch.rotations`
only) keeps its own copy of the gyro values — the truth it simulates, as opposed to
the values the filters assume — and a test checks that the defaults agree.
"""

from __future__ import annotations

import math

__all__ = ["DEG_PER_HOUR", "ARCSEC_PER_RAD", "ATTITUDE_RADIANS_PER_MRP", "DEFAULT_SIGMA_V", "DEFAULT_SIGMA_U"]

#: One degree per hour in rad/s (gyro bias and drift rates).
DEG_PER_HOUR = math.pi / 180.0 / 3600.0
#: Arcseconds per radian.
ARCSEC_PER_RAD = math.degrees(1.0) * 3600.0
#: Small-angle scale of an MRP error: a rotation by ``δθ`` has MRP ``δp ≈ δθ/4`` (rad per MRP unit).
ATTITUDE_RADIANS_PER_MRP = 4.0
#: Gyro angle random walk σ_v (rad/s^½) of the paper's gyro (method.md §4).
DEFAULT_SIGMA_V = math.sqrt(10.0) * 1e-7
#: Gyro rate random walk σ_u (rad/s^{3/2}) of the paper's gyro (method.md §4).
DEFAULT_SIGMA_U = math.sqrt(10.0) * 1e-10
