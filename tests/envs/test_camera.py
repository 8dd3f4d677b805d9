"""Pinhole star camera: geometry, selection, noise statistics, padding, bad settings.

Noise statistics (:func:`tests.helpers.assert_statistic`, a false-failure rate of 1e-6 per assertion): with n
independent normal errors the sample standard deviation has relative standard error 1/sqrt(2(n−1)) (≈ 0.16 % at
n = 200 000), and the mean the standard error σ/sqrt(n).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats
from scipy.special import ndtri

from agsf_torch.rotations import mrp_to_dcm, quat_to_dcm
from envs.camera import StarCamera, random_attitude_quat, star_count_distribution
from envs.catalog import StarCatalog
from envs.random import CounterKey
from tests.helpers import assert_statistic, assert_within

N = 200_000
ALPHA = 1e-6  # the false-failure rate of each statistical assertion
EPS = np.finfo(np.float64).eps

# Documented in envs/catalog.py (10⁶ attitudes, seed 0, default camera and cut):
DOCUMENTED_FRACTIONS = [0.0, 0.0, 0.000003, 0.000045, 0.00026, 0.999692]


def _random_mrps(num: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(num, 4, generator=g, dtype=torch.float64)
    q = q / q.norm(dim=-1, keepdim=True)
    q = q * torch.where(q[:, 3:] < 0, -1.0, 1.0)
    return q[:, :3] / (1.0 + q[:, 3:])


@pytest.mark.parametrize("noise", ["focal_plane", "unit_vector"])
@pytest.mark.parametrize("principal_point", [(0.0, 0.0), (1.3e-3, -0.7e-3)])
def test_noise_free_star_vectors_equal_C_r(default_catalog, noise, principal_point):
    cam = StarCamera(default_catalog, noise=noise, principal_point=principal_point)
    p = _random_mrps(2000, 0)
    C = mrp_to_dcm(p)
    body, inertial, mask = cam.observe(C)
    assert body.shape == (2000, 5, 3) and inertial.shape == (2000, 5, 3) and mask.shape == (2000, 5)
    assert body.dtype == torch.float64 and mask.dtype == torch.bool
    predicted = torch.einsum("bij,bmj->bmi", C, inertial)
    assert int(mask.sum()) > 9000
    # unit vectors (entries ≤ 1) through the camera's projection and back: rounding far below 1e-12
    assert_within(body[mask], predicted[mask], 1e-12, "noise-free star vectors against C r")
    # Every reported star is visible in the image plane of the definition.
    f = cam.focal_length
    v = predicted[mask]
    tx, ty = cam.tan_half
    assert bool((v[:, 2] > 0).all())
    assert bool(((f * v[:, 0] / v[:, 2]).abs() <= f * tx * (1 + 1e-12)).all())
    assert bool(((f * v[:, 1] / v[:, 2]).abs() <= f * ty * (1 + 1e-12)).all())
    # r = (cos δ cos α, cos δ sin α, sin δ): 2 roundings an entry, its norm 4 more (within 4ε of 1); 2× that
    assert_within(inertial[mask].norm(dim=-1), 1.0, 8 * EPS, "norm of the catalogue's unit vectors")


def test_selection_matches_brute_force_image_plane(default_catalog):
    cam = StarCamera(default_catalog)
    cat = default_catalog
    C = quat_to_dcm(random_attitude_quat(11, 200))
    idx, mask = cam.select(C)
    r = cat.r.numpy()
    mag, ids = cat.magnitude.numpy(), cat.ids.numpy()
    f, (x0, y0) = cam.focal_length, (0.0, 0.0)
    hx, hy = (f * t for t in cam.tan_half)
    for b in range(C.shape[0]):
        v = r @ C[b].numpy().T
        with np.errstate(divide="ignore", invalid="ignore"):
            x = -f * v[:, 0] / v[:, 2] + x0
            y = -f * v[:, 1] / v[:, 2] + y0
        visible = np.flatnonzero((v[:, 2] > 0) & (np.abs(x - x0) <= hx) & (np.abs(y - y0) <= hy))
        brightest = visible[np.lexsort((ids[visible], mag[visible]))][:5]
        got = idx[b][mask[b]].numpy()
        assert np.array_equal(ids[got], ids[brightest])


def test_grid_index_equals_dense_bit_for_bit(default_catalog):
    grid = StarCamera(default_catalog)
    dense = StarCamera(default_catalog, index="dense")
    C = quat_to_dcm(random_attitude_quat(3, 400))
    key = CounterKey(torch.arange(400), 10, 4)
    a, b = grid.observe(C, key), dense.observe(C, key)
    for x, y in zip(a, b):
        assert torch.equal(x, y)
    assert torch.equal(grid.count_visible(C), dense.count_visible(C))


def _attitudes_with_boresights(d: torch.Tensor, seed: int) -> torch.Tensor:
    """Attitude matrices whose third row (the boresight in inertial axes) is ``d``, random roll."""
    g = torch.Generator().manual_seed(seed)
    z = d / d.norm(dim=-1, keepdim=True)
    a = torch.randn(d.shape, generator=g, dtype=torch.float64)
    x = a - (a * z).sum(-1, keepdim=True) * z
    x = x / x.norm(dim=-1, keepdim=True)
    y = torch.linalg.cross(z, x, dim=-1)
    return torch.stack((x, y, z), -2)


def test_grid_matches_dense_at_cube_edges_and_corners(default_catalog):
    """The sky index is a cube map: boresights on and next to its face edges and
    corners (where cells are smallest and the cell lookup rounds) must still see
    exactly the stars that the dense search sees."""
    g = torch.Generator().manual_seed(5)
    signs = torch.tensor([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=torch.float64)
    corners = signs.repeat(16, 1)
    edges = torch.cat([signs * torch.tensor(m, dtype=torch.float64) for m in ([1, 1, 0], [0, 1, 1], [1, 0, 1])]).repeat(
        8, 1
    )
    base = torch.cat((corners, edges))
    jitter = torch.cat(
        [s * torch.randn(base.shape, generator=g, dtype=torch.float64) for s in (0.0, 1e-15, 1e-9, 1e-4, 1e-2)]
    )
    d = base.repeat(5, 1) + jitter
    C = _attitudes_with_boresights(d, 6)
    grid = StarCamera(default_catalog)
    dense = StarCamera(default_catalog, index="dense")
    assert torch.equal(grid.count_visible(C), dense.count_visible(C))
    for x, y in zip(grid.select(C), dense.select(C)):
        assert torch.equal(x, y)


def test_batch_size_does_not_change_a_frame(default_camera):
    C = quat_to_dcm(random_attitude_quat(8, 1500))
    key = CounterKey(torch.arange(1500), 3, 4)
    full = default_camera.observe(C, key)
    for lo, hi in ((0, 1), (7, 10), (1000, 1500)):
        part = default_camera.observe(C[lo:hi], CounterKey(torch.arange(lo, hi), 3, 4))
        for x, y in zip(full, part):
            assert torch.equal(x[lo:hi], y)


def test_memory_safe_at_8192_and_leading_dims(default_camera):
    C = quat_to_dcm(random_attitude_quat(4, 8192))
    body, inertial, mask = default_camera.observe(C, CounterKey(torch.arange(8192), 1, 4))
    assert body.shape == (8192, 5, 3) and mask.shape == (8192, 5)
    assert torch.equal(mask.sum(-1), default_camera.count_visible(C).clamp(max=5))
    out = default_camera.observe(C[:24].reshape(2, 3, 4, 3, 3))
    assert out.star_body.shape == (2, 3, 4, 5, 3) and out.mask.shape == (2, 3, 4, 5)


def test_fewer_stars_are_padded_and_none_is_not_an_error():
    r = torch.tensor([[0.0, 0.0, 1.0], [0.01, 0.02, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    cam = StarCamera(StarCatalog.from_vectors(r))
    eye = torch.eye(3, dtype=torch.float64)[None]
    body, inertial, mask = cam.observe(eye, torch.randn(1, 5, 3, dtype=torch.float64))
    assert mask.tolist() == [[True, True, False, False, False]]
    assert bool((body[0, 2:] == 0).all()) and bool((inertial[0, 2:] == 0).all())
    assert torch.equal(inertial[0, :2], StarCatalog.from_vectors(r).r[:2])  # the catalogue's vectors, gathered
    # Looking along +y: no star in view.
    C = torch.tensor([[[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]], dtype=torch.float64)  # body z = inertial +y
    body, inertial, mask = cam.observe(C)
    assert not bool(mask.any()) and bool((body == 0).all()) and bool((inertial == 0).all())


def _two_star_camera(noise: str, theta: float, fov: float) -> tuple[StarCamera, torch.Tensor]:
    """Stars at the boresight and θ off-axis along body x (C = I)."""
    r = torch.tensor([[0.0, 0.0, 1.0], [math.sin(theta), 0.0, math.cos(theta)]], dtype=torch.float64)
    cam = StarCamera(StarCatalog.from_vectors(r), fov_deg=(fov, fov), max_stars=2, noise=noise)
    C = torch.eye(3, dtype=torch.float64).expand(N, 3, 3)
    body, inertial, mask = cam.observe(C, CounterKey(torch.arange(N), 0, 4))
    assert bool(mask.all())
    return cam, body


def _check_std(sample: torch.Tensor, expected: float) -> float:
    s = float(sample.std())
    assert_statistic(float(sample.mean()), 0.0, expected / math.sqrt(N), "mean star error", false_failure=ALPHA)
    se = 1.0 / math.sqrt(2.0 * (N - 1))  # of a normal sample's standard deviation, relative
    assert_statistic(s / expected, 1.0, se, "star error's standard deviation / σ", false_failure=ALPHA)
    return s


def test_focal_plane_noise_matches_sigma_on_axis_and_off_axis_geometry():
    sigma = 10e-6
    # Default field: the boresight star's angular error is σ per axis.
    cam, body = _two_star_camera("focal_plane", math.radians(3.0), 8.0)
    e = body[:, 0] - torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    _check_std(e[:, 0], sigma)
    _check_std(e[:, 1], sigma)
    # Off-axis (wide field so the geometry is resolvable): radial σcos²θ, tangential σcosθ.
    theta = math.radians(25.0)
    cam, body = _two_star_camera("focal_plane", theta, 60.0)
    v = torch.tensor([math.sin(theta), 0.0, math.cos(theta)], dtype=torch.float64)
    e = body[:, 1] - v
    radial = e @ torch.tensor([math.cos(theta), 0.0, -math.sin(theta)], dtype=torch.float64)
    _check_std(radial, sigma * math.cos(theta) ** 2)
    _check_std(e[:, 1], sigma * math.cos(theta))


def test_unit_vector_noise_is_sigma_per_perpendicular_axis():
    sigma = 10e-6
    theta = math.radians(25.0)
    cam, body = _two_star_camera("unit_vector", theta, 60.0)
    for slot, v in ((0, [0.0, 0.0, 1.0]), (1, [math.sin(theta), 0.0, math.cos(theta)])):
        v = torch.tensor(v, dtype=torch.float64)
        e = body[:, slot] - v
        t1 = torch.tensor([v[2], 0.0, -v[0]], dtype=torch.float64)  # ⟂ v in the x–z plane
        t2 = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        _check_std(e @ t1, sigma)
        _check_std(e @ t2, sigma)
        # Unit length: the component along v is the second-order −|e|²/2 (≤ 1.3e-9 here),
        # up to the rounding of two unit vectors (|b| = 1 ± a few 1e-16).
        assert_within(e @ v, -0.5 * (e * e).sum(-1), 1e-15, "star error along the star vector")


def test_explicit_normals_equal_counter_key(default_camera):
    C = quat_to_dcm(random_attitude_quat(2, 50))
    key = CounterKey(torch.arange(50), 5, 4)
    a = default_camera.observe(C, key)
    b = default_camera.observe(C, key.normal((5, 3)))
    assert torch.equal(a.star_body, b.star_body)
    with pytest.raises(ValueError, match=r"noise must have shape \(50, 5, 3\), got \(50, 5, 2\)"):
        default_camera.observe(C, torch.zeros(50, 5, 2, dtype=torch.float64))
    with pytest.raises(ValueError, match=r"C must have shape \[\.\.\., 3, 3\]"):
        default_camera.observe(torch.zeros(4, 3, dtype=torch.float64))


def test_star_count_distribution_matches_documented_table(default_camera):
    n = 20_000
    hist = star_count_distribution(n, seed=1, camera=default_camera)
    assert hist.shape == (6,)
    assert_within(hist.sum(), 1.0, 1e-12, "sum of the star-count fractions")
    # The table holds the counts of 10⁶ attitudes (fractions to 6 decimals); these n are another sample of the same
    # law.  The rare counts (0–6 frames of n) are far from normal, so each category takes the exact test of two
    # binomial samples: given its total T over both, this sample's count is Binomial(T, n/(n + 10⁶)).  Its
    # two-sided p-value, as the normal score with the same tail, is a standard normal under the null, conservatively.
    doc_counts = np.rint(np.asarray(DOCUMENTED_FRACTIONS) * 1e6).astype(int)
    counts = np.rint(hist * n).astype(int)
    p = [stats.binomtest(k, k + K, n / (n + 1e6)).pvalue if k + K else 1.0 for k, K in zip(counts, doc_counts)]
    scores = ndtri(1.0 - np.minimum(p, 1.0) / 2)
    assert_statistic(scores, 0.0, 1.0, "star counts against the documented table (exact test)", false_failure=ALPHA)
    assert hist[5] >= 0.999


def test_star_count_distribution_rejects_bad_count(default_camera):
    with pytest.raises(ValueError, match="num_attitudes must be ≥ 1, got 0"):
        star_count_distribution(0, 0, default_camera)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(fov_deg=(0.0, 8.0)), r"fov_deg must be finite and > 0, got 0.0"),
        (dict(fov_deg=(8.0, -8.0)), r"fov_deg must be finite and > 0, got -8.0"),
        (dict(fov_deg=(8.0, float("nan"))), r"fov_deg must be finite and > 0, got nan"),
        (dict(fov_deg=(180.0, 8.0)), r"fov_deg must be < 180 degrees, got \(180.0, 8.0\)"),
        (dict(fov_deg=(8.0,)), r"fov_deg must hold 2 values"),
        (dict(focal_length=0.0), r"focal_length must be finite and > 0, got 0.0"),
        (dict(focal_length=-0.065), r"focal_length must be finite and > 0, got -0.065"),
        (dict(focal_length=float("inf")), r"focal_length must be finite and > 0, got inf"),
        (dict(max_stars=0), r"max_stars must be an integer ≥ 1, got 0"),
        (dict(max_stars=2.5), r"max_stars must be an integer ≥ 1, got 2.5"),
        (dict(sigma=-1e-6), r"sigma must be finite and ≥ 0, got -1e-06"),
        (dict(sigma=float("nan")), r"sigma must be finite and ≥ 0, got nan"),
        (dict(noise="pixel"), r"noise must be one of .*, got 'pixel'"),
        (dict(principal_point=(float("nan"), 0.0)), r"principal_point must be 2 finite numbers \(m\)"),
        (dict(index="tree"), r"index must be 'grid' or 'dense', got 'tree'"),
    ],
)
def test_bad_camera_settings_raise(default_catalog, kwargs, message):
    with pytest.raises(ValueError, match=message):
        StarCamera(default_catalog, **kwargs)


def test_camera_requires_a_catalog():
    with pytest.raises(ValueError, match="catalog must be a StarCatalog"):
        StarCamera([[0.0, 0.0, 1.0]])  # type: ignore[arg-type]


def test_the_sky_index_is_kept_on_disk_and_rebuilt_when_unreadable(default_catalog, tmp_path, monkeypatch):
    from envs import sky_index as camera

    monkeypatch.setenv("AGSF_CACHE_DIR", str(tmp_path))
    half = math.atan(math.hypot(math.tan(math.radians(4.0)), math.tan(math.radians(4.0))))
    built = camera.build_grid(default_catalog.r, 32, half)
    first = camera.stored_grid(default_catalog.r, 32, half)
    (stored,) = tmp_path.glob("sky-grid-*.npz")
    calls = []
    monkeypatch.setattr(camera, "build_grid", lambda *a: calls.append(a) or built)
    again = camera.stored_grid(default_catalog.r, 32, half)
    assert torch.equal(first, built) and torch.equal(again, built) and calls == []  # read back, not rebuilt
    other = camera.stored_grid(default_catalog.r, 31, half)  # another grid: another key
    assert len(calls) == 1 and len(list(tmp_path.glob("sky-grid-*.npz"))) == 2 and other is built
    for damage in (b"", b"torn", b"PK\x03\x04 not a zip"):  # empty, torn, not this format
        stored.write_bytes(damage)
        assert torch.equal(camera.stored_grid(default_catalog.r, 32, half), built)
        with np.load(stored) as replaced:  # replaced whole
            assert replaced["table"].shape == tuple(built.shape)
    assert len(calls) == 4
    # a table whose bytes no longer match its digest (torn data under a whole header) is not used
    with np.load(stored) as whole:
        table, digest = whole["table"], whole["digest"]
    np.savez(stored, table=np.zeros_like(table), digest=digest)
    assert torch.equal(camera.stored_grid(default_catalog.r, 32, half), built) and len(calls) == 5


def test_the_sky_index_key_holds_the_catalogue_dtype(tmp_path, monkeypatch):
    from envs import sky_index as camera

    monkeypatch.setenv("AGSF_CACHE_DIR", str(tmp_path))
    half = math.atan(math.hypot(math.tan(math.radians(4.0)), math.tan(math.radians(4.0))))
    r = torch.nn.functional.normalize(torch.randn(200, 3, generator=torch.Generator().manual_seed(3)), dim=-1)
    for dtype in (torch.float64, torch.float32, torch.bfloat16):  # bfloat16 has no NumPy type: hashed as bytes
        assert torch.equal(camera.stored_grid(r.to(dtype), 8, half), camera.build_grid(r.to(dtype), 8, half))
    assert len(list(tmp_path.glob("sky-grid-*.npz"))) == 3


def test_an_unwritable_cache_leaves_the_sky_index_in_memory(default_catalog, tmp_path, monkeypatch):
    from envs import sky_index as camera

    monkeypatch.setattr(camera, "cache_dir", lambda: tmp_path / "missing")  # mkstemp there fails
    half = math.atan(math.hypot(math.tan(math.radians(4.0)), math.tan(math.radians(4.0))))
    assert torch.equal(camera.stored_grid(default_catalog.r, 32, half), camera.build_grid(default_catalog.r, 32, half))
    assert not (tmp_path / "missing").exists()
