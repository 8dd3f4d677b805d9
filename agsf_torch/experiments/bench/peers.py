"""Peers of the classic GSF's propagation step, written the way their own users write them.

Both do exactly the numerical work of :func:`agsf_torch.propagation.propagate_moments`
for the 6-state attitude model (method.md §1) — one RK4 step of ``μ̇ = f(μ, ω̃)``,
``Φ̇ = AΦ``, ``Ṡ = AS + SAᵀ + gQgᵀ`` from ``Φ = I, S = 0``, then
``P ← ΦPΦᵀ + S`` — in float64 NumPy, with the closed-form drift, Jacobian and
``gQgᵀ`` of :class:`~agsf_torch.models.AttitudeModel`:

* :func:`filterpy_loop` — one ``filterpy.kalman.ExtendedKalmanFilter`` per
  component and trajectory holding ``x`` and ``P``, its ``predict`` overridden
  with the RK4 step on small NumPy arrays, called in a Python loop (filterpy
  has no continuous-time propagation of its own; this is how its users add one);
* :func:`numpy_batch` — the same step vectorised over all components at once
  (``[B·N, 6, 6]`` arrays and ``np.matmul``), as a NumPy user writes a batch;
* :func:`jax_batch` — the step written for one component in ``jax.numpy`` and batched
  the way JAX users batch, ``jax.jit(jax.vmap(step))``, in float64 (``jax_enable_x64``);
  JAX is an optional bench dependency (``pip install -c constraints.txt -e '.[bench]'``):
  without it the row is skipped with a message.

Our GSF's ``predict`` does this work and more (the MRP shadow switch and a
positive-definiteness check of every covariance).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np

__all__ = ["filterpy_loop", "filterpy_spacecraft", "numpy_batch", "jax_batch", "attitude_rk4_step", "JAX_MISSING"]

#: The message of a skipped JAX row.
JAX_MISSING = "JAX is not installed (an optional bench dependency: pip install -c constraints.txt -e '.[bench]')"


def _cross(v: np.ndarray) -> np.ndarray:
    z = np.zeros(v.shape[:-1])
    return np.stack(
        (
            np.stack((z, -v[..., 2], v[..., 1]), -1),
            np.stack((v[..., 2], z, -v[..., 0]), -1),
            np.stack((-v[..., 1], v[..., 0], z), -1),
        ),
        -2,
    )


def _terms(x: np.ndarray, w_meas: np.ndarray, sv2: float, su2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``f``, ``A`` and ``gQgᵀ`` of the 6-state model at ``x [..., 6]`` (NumPy, batched)."""
    p, b = x[..., :3], x[..., 3:]
    w = w_meas - b
    s = (p * p).sum(-1, keepdims=True)
    pw = (p * w).sum(-1, keepdims=True)
    eye = np.eye(3)
    B = (1.0 - s)[..., None] * eye + 2.0 * _cross(p) + 2.0 * p[..., :, None] * p[..., None, :]
    f = np.concatenate((0.25 * (B @ w[..., None])[..., 0], np.zeros_like(p)), -1)
    F = 0.5 * (p[..., :, None] * w[..., None, :] - w[..., :, None] * p[..., None, :] - _cross(w) + pw[..., None] * eye)
    A = np.zeros((*x.shape[:-1], 6, 6))
    A[..., :3, :3] = F
    A[..., :3, 3:] = -0.25 * B
    G = np.zeros_like(A)
    G[..., :3, :3] = (sv2 / 16.0) * ((1.0 + s) ** 2)[..., None] * eye
    G[..., 3:, 3:] = su2 * eye
    return f, A, G


def attitude_rk4_step(
    x: np.ndarray, P: np.ndarray, w_meas: np.ndarray, dt: float, sv2: float, su2: float
) -> tuple[np.ndarray, np.ndarray]:
    """One RK4 step of ``(μ, Φ, S)`` and ``P ← ΦPΦᵀ + S`` (module docstring); ``x [..., 6]``, ``P [..., 6, 6]``."""
    Phi = np.broadcast_to(np.eye(6), P.shape).copy()
    S = np.zeros_like(P)

    def rates(m, Ph, S_):
        f, A, G = _terms(m, w_meas, sv2, su2)
        AS = A @ S_
        return f, A @ Ph, AS + np.swapaxes(AS, -1, -2) + G

    k1 = rates(x, Phi, S)
    k2 = rates(x + 0.5 * dt * k1[0], Phi + 0.5 * dt * k1[1], S + 0.5 * dt * k1[2])
    k3 = rates(x + 0.5 * dt * k2[0], Phi + 0.5 * dt * k2[1], S + 0.5 * dt * k2[2])
    k4 = rates(x + dt * k3[0], Phi + dt * k3[1], S + dt * k3[2])
    x = x + dt / 6.0 * (k1[0] + 2.0 * (k2[0] + k3[0]) + k4[0])
    Phi = Phi + dt / 6.0 * (k1[1] + 2.0 * (k2[1] + k3[1]) + k4[1])
    S = S + dt / 6.0 * (k1[2] + 2.0 * (k2[2] + k3[2]) + k4[2])
    P = Phi @ P @ np.swapaxes(Phi, -1, -2) + 0.5 * (S + np.swapaxes(S, -1, -2))
    return x, 0.5 * (P + np.swapaxes(P, -1, -2))


def _problem(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    x = np.concatenate((0.3 * rng.standard_normal((count, 3)), np.zeros((count, 3))), -1)
    P = np.broadcast_to(np.diag([1e-3] * 3 + [1e-12] * 3), (count, 6, 6)).copy()
    return x, P, np.array([0.06, 0.06, 0.06])


def filterpy_loop(samples: int, dt: float = 0.1, sv2: float = 1e-13, su2: float = 1e-19) -> dict[str, Any]:
    """Component-steps/s of the per-component filterpy loop (module docstring), over ``samples`` components."""
    from filterpy.kalman import ExtendedKalmanFilter

    class AttitudeEKF(ExtendedKalmanFilter):
        def predict(self, u=None):  # continuous-time propagation, RK4 of (μ, Φ, S)
            x, P = attitude_rk4_step(self.x.ravel(), self.P, u, dt, sv2, su2)
            self.x, self.P = x.reshape(-1, 1), P

    x, P, w = _problem(samples)
    filters = []
    for k in range(samples):
        ekf = AttitudeEKF(dim_x=6, dim_z=3)
        ekf.x, ekf.P = x[k].reshape(-1, 1), P[k].copy()
        filters.append(ekf)
    filters[0].predict(w)  # warm-up
    t = time.perf_counter()
    for ekf in filters:
        ekf.predict(w)
    sec = time.perf_counter() - t
    return {
        "what": "filterpy ExtendedKalmanFilter per component, RK4 (μ, Φ, S) in NumPy, Python loop",
        "samples": samples,
        "component_steps_per_s": samples / sec,
    }


def numpy_batch(
    count: int, repeats: int = 3, dt: float = 0.1, sv2: float = 1e-13, su2: float = 1e-19
) -> dict[str, Any]:
    """Component-steps/s of the NumPy-vectorised step over ``count`` components at once."""
    x, P, w = _problem(count)
    attitude_rk4_step(x, P, w, dt, sv2, su2)  # warm-up
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        attitude_rk4_step(x, P, w, dt, sv2, su2)
        times.append(time.perf_counter() - t)
    return {
        "what": "NumPy, all components vectorised ([B·N, 6, 6] arrays, np.matmul)",
        "components": count,
        "component_steps_per_s": count / min(times),
    }


def _jax_step():
    """The RK4 (μ, Φ, S) step of one 6-state component in ``jax.numpy``, as a JAX user writes it."""
    import jax.numpy as jnp

    def cross(v):
        return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])

    def terms(x, w_meas, sv2, su2):
        p, b = x[:3], x[3:]
        w = w_meas - b
        s = p @ p
        eye = jnp.eye(3)
        B = (1.0 - s) * eye + 2.0 * cross(p) + 2.0 * jnp.outer(p, p)
        f = jnp.concatenate((0.25 * B @ w, jnp.zeros(3)))
        F = 0.5 * (jnp.outer(p, w) - jnp.outer(w, p) - cross(w) + (w @ p) * eye)
        A = jnp.block([[F, -0.25 * B], [jnp.zeros((3, 3)), jnp.zeros((3, 3))]])
        G = jnp.block([[(sv2 / 16.0) * (1.0 + s) ** 2 * eye, jnp.zeros((3, 3))], [jnp.zeros((3, 3)), su2 * eye]])
        return f, A, G

    def step(x, P, w_meas, dt, sv2, su2):
        def rates(m, Ph, S):
            f, A, G = terms(m, w_meas, sv2, su2)
            AS = A @ S
            return f, A @ Ph, AS + AS.T + G

        Phi, S = jnp.eye(6), jnp.zeros((6, 6))
        k1 = rates(x, Phi, S)
        k2 = rates(x + 0.5 * dt * k1[0], Phi + 0.5 * dt * k1[1], S + 0.5 * dt * k1[2])
        k3 = rates(x + 0.5 * dt * k2[0], Phi + 0.5 * dt * k2[1], S + 0.5 * dt * k2[2])
        k4 = rates(x + dt * k3[0], Phi + dt * k3[1], S + dt * k3[2])
        x = x + dt / 6.0 * (k1[0] + 2.0 * (k2[0] + k3[0]) + k4[0])
        Phi = Phi + dt / 6.0 * (k1[1] + 2.0 * (k2[1] + k3[1]) + k4[1])
        S = S + dt / 6.0 * (k1[2] + 2.0 * (k2[2] + k3[2]) + k4[2])
        P = Phi @ P @ Phi.T + 0.5 * (S + S.T)
        return x, 0.5 * (P + P.T)

    return step


def jax_batch(count: int, repeats: int = 3, dt: float = 0.1, sv2: float = 1e-13, su2: float = 1e-19) -> dict[str, Any]:
    """Component-steps/s of ``jax.jit(jax.vmap(step))`` over ``count`` components (float64, CPU), the first
    (compiling) call excluded; ``{"skipped": reason}`` without JAX."""
    try:
        import jax
    except ImportError:
        return {"skipped": JAX_MISSING}
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    x, P, w = _problem(count)
    batched = jax.jit(jax.vmap(_jax_step(), in_axes=(0, 0, None, None, None, None)))
    args = (jnp.asarray(x), jnp.asarray(P), jnp.asarray(w), dt, sv2, su2)
    t = time.perf_counter()
    jax.block_until_ready(batched(*args))
    compile_s = time.perf_counter() - t
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(batched(*args))
        times.append(time.perf_counter() - t)
    return {
        "what": f"JAX {jax.__version__} jit(vmap(step)), float64, one component's step in jax.numpy",
        "components": count,
        "component_steps_per_s": count / min(times),
        "first_call_s": compile_s,
    }


def _star_model(x: np.ndarray, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``h(x) = vec(C(p) rⱼ)`` and ``H = [4/(1+s)² [bⱼ×] B(p)ᵀ, 0]`` for one 6-state component (NumPy)."""
    p = x[:3]
    s = p @ p
    px = _cross(p)
    C = np.eye(3) + (8.0 * px @ px - 4.0 * (1.0 - s) * px) / (1.0 + s) ** 2
    B = (1.0 - s) * np.eye(3) + 2.0 * px + 2.0 * np.outer(p, p)
    b = r @ C.T  # [M, 3]
    H = np.zeros((3 * len(r), 6))
    H[:, :3] = (4.0 / (1.0 + s) ** 2 * (_cross(b) @ B.T)).reshape(-1, 3)
    return b.reshape(-1), H


def filterpy_spacecraft(
    N: int = 5,
    M: int = 5,
    repeats: int = 20,
    dt: float = 0.1,
    sv2: float = 1e-13,
    su2: float = 1e-19,
    sigma: float = 1e-5,
) -> dict[str, Any]:
    """Seconds per predict + star update of one spacecraft's ``N`` components as a filterpy user writes it:
    one ``ExtendedKalmanFilter`` per component, ``predict`` overridden with the RK4 step, filterpy's own
    ``update(z, HJacobian, Hx, R)`` (Joseph form) with ``M`` star vectors, in a Python loop."""
    from filterpy.kalman import ExtendedKalmanFilter

    class AttitudeEKF(ExtendedKalmanFilter):
        def predict(self, u=None):
            x, P = attitude_rk4_step(self.x.ravel(), self.P, u, dt, sv2, su2)
            self.x, self.P = x.reshape(-1, 1), P

    x, P, w = _problem(N)
    rng = np.random.default_rng(1)
    r = rng.standard_normal((M, 3))
    r /= np.linalg.norm(r, axis=-1, keepdims=True)
    z = (_star_model(x[0], r)[0]).reshape(-1, 1)
    R = sigma**2 * np.eye(3 * M)
    filters = []
    for k in range(N):
        ekf = AttitudeEKF(dim_x=6, dim_z=3 * M)
        ekf.x, ekf.P = x[k].reshape(-1, 1), P[k].copy()
        filters.append(ekf)

    def step():
        for ekf in filters:
            ekf.predict(w)
            ekf.update(
                z, lambda s: _star_model(s.ravel(), r)[1], lambda s: _star_model(s.ravel(), r)[0].reshape(-1, 1), R=R
            )

    step()
    times = []
    for _ in range(repeats):
        for k, ekf in enumerate(filters):  # the same problem each repeat
            ekf.x, ekf.P = x[k].reshape(-1, 1), P[k].copy()
        t = time.perf_counter()
        step()
        times.append(time.perf_counter() - t)
    return {
        "what": f"filterpy ExtendedKalmanFilter per component: RK4 predict and its update (Joseph form), {N} components, {M} stars",
        "seconds": float(np.median(times)),
    }
