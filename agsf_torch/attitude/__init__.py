"""The attitude application: what joins a gyro and a star camera to the generic filters.

* :mod:`.physics` — the attitude physics written once (MRP chart, kinematics, gyro noise, star camera, Fokker–Planck
  terms), on entries: the attitude model, the star-vector measurement, :mod:`agsf_torch.rotations` and the fused
  kernels are all built from it; it imports nothing but the small-matrix algebra (:mod:`agsf_torch.fused.algebra`);
* :mod:`.inputs` — the filter loop's attitude adapter (observations → steps);
* :mod:`.gyro_hold` — bridging missing or saturated gyro samples, with the covariance they cost;
* :mod:`.recordings` — sensor logs on disk (a user's own data), identified by content;
* :mod:`.star_fix` — the attitude of one star frame (Wahba's problem), batched: where a replay without the truth starts;
* :mod:`.floor` — the physical floor: the steady-state error covariance of a gyro and a star camera (the DARE);
* :mod:`.learning` — maximum-likelihood fits of the noise model through the filter, one data set or many at once;
* :mod:`.autocovariance` — the autocovariance least-squares baseline for the same noise (σ_v, σ_s).

The attitude *model* and the star-vector *measurement* are models like any other
(:mod:`agsf_torch.models`), and the multiplicative EKF a filter like any other
(:mod:`agsf_torch.filters`).
"""
