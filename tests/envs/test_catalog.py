"""Hipparcos catalogue: parsing, magnitude cut, cache, and bad values."""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import pytest
import torch

import envs.catalog as catalog_mod
from envs.catalog import DEFAULT_MAX_MAGNITUDE, StarCatalog, cache_dir, load_hipparcos_table, radec_to_unit
from tests.helpers import assert_within

EPS = np.finfo(np.float64).eps


def _write_hip2(path: Path, rows: list[tuple[int, float, float, float]]) -> None:
    """A file in hip2.dat's layout (41 whitespace columns) with the given HIP, α, δ, Hp."""
    lines = []
    for hip, ra, dec, mag in rows:
        cols = ["0"] * 41
        cols[0], cols[4], cols[5], cols[19] = str(hip), f"{ra:.10f}", f"{dec:.10f}", f"{mag:.4f}"
        lines.append(" ".join(cols))
    path.write_text("\n".join(lines) + "\n")


def test_default_cut_and_sorting(default_catalog):
    cat = default_catalog
    assert len(cat) == 13943  # stars with Hp ≤ 7.0 (the default cut) in hip2.dat
    assert cat.magnitude.dtype == torch.float64 and cat.r.shape == (13943, 3)
    assert bool((cat.magnitude <= DEFAULT_MAX_MAGNITUDE).all())
    assert bool((cat.magnitude[1:] >= cat.magnitude[:-1]).all())
    assert len(torch.unique(cat.ids)) == len(cat)


def test_brightest_star_is_sirius(default_catalog):
    cat = default_catalog
    assert int(cat.ids[0]) == 32349  # HIP 32349 = Sirius, Hp = −1.0876
    assert_within(cat.magnitude[0], -1.0876, 1e-12, "Sirius's magnitude as parsed")
    # Sirius at J2000: α = 101.2872°, δ = −16.7161°; hip2 is at epoch J1991.25 and
    # Sirius moves (−0.55″, −1.22″)/yr, i.e. by (+0.0014°, +0.0030°) over 8.75 yr.
    assert_within(math.degrees(float(cat.ra[0])), 101.2872 + 0.0014, 3e-4, "Sirius's right ascension (°)")
    assert_within(math.degrees(float(cat.dec[0])), -16.7161 + 0.0030, 3e-4, "Sirius's declination (°)")


def test_unit_vectors_match_radec_formula(default_catalog):
    cat = default_catalog
    ra, dec = cat.ra.numpy(), cat.dec.numpy()
    ref = np.stack((np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)), -1)
    assert_within(cat.r, ref, 1e-15, "unit vectors against the formula")  # 2 roundings an entry on either side
    # 2 roundings an entry, the norm 4 more (within 4ε of 1); 2× that
    assert_within(np.linalg.norm(cat.r.numpy(), axis=1), 1.0, 8 * EPS, "norm of the unit vectors")


def test_full_table_and_monotone_cuts():
    table = load_hipparcos_table()
    assert table["ids"].shape == (117955,)
    counts = [len(StarCatalog.from_hipparcos(m)) for m in (6.0, 6.5, 7.0, 7.5)]
    assert counts == [4559, 7982, 13943, 23270]
    assert len(StarCatalog.from_hipparcos(math.inf)) == 117955


def test_cache_written_then_used_without_parsing(tmp_path, monkeypatch):
    src = tmp_path / "hip2.dat"
    _write_hip2(src, [(1, 0.1, 0.2, 5.0), (2, 1.0, -0.5, 3.0), (3, 2.0, 0.3, 8.0)])
    cache = tmp_path / "cache"
    t1 = load_hipparcos_table(src, cache)
    files = list(cache.glob("hip2-*.npz"))
    assert len(files) == 1
    catalog_mod._load_cached.cache_clear()  # drop the in-process copy

    def boom(path):
        raise AssertionError("parsed again although the cache is valid")

    monkeypatch.setattr(catalog_mod, "_parse_hip2", boom)
    t2 = load_hipparcos_table(src, cache)
    for k in t1:
        np.testing.assert_array_equal(t1[k], t2[k])


def test_changed_source_file_is_parsed_again(tmp_path):
    src = tmp_path / "hip2.dat"
    cache = tmp_path / "cache"
    _write_hip2(src, [(1, 0.1, 0.2, 5.0), (2, 1.0, -0.5, 3.0)])
    assert load_hipparcos_table(src, cache)["magnitude"].tolist() == [5.0, 3.0]
    _write_hip2(src, [(1, 0.1, 0.2, 4.5), (2, 1.0, -0.5, 3.0)])
    st = src.stat()
    os.utime(src, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))
    assert load_hipparcos_table(src, cache)["magnitude"].tolist() == [4.5, 3.0]
    assert len(list(cache.glob("hip2-*.npz"))) == 2
    cat = StarCatalog.from_hipparcos(4.0, path=src, cache=cache)
    assert cat.ids.tolist() == [2]
    want = radec_to_unit(torch.tensor(1.0, dtype=torch.float64), torch.tensor(-0.5, dtype=torch.float64))
    assert_within(cat.r[0], want, 1e-10, "the star's unit vector from the reparsed file")


def test_cache_dir_env_var_and_fallback(tmp_path, monkeypatch):
    monkeypatch.setenv("AGSF_CACHE_DIR", str(tmp_path / "mine"))
    assert cache_dir() == tmp_path / "mine" and (tmp_path / "mine").is_dir()
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("AGSF_CACHE_DIR", str(blocker / "sub"))  # cannot be created
    fallback = cache_dir()
    assert fallback != blocker / "sub" and fallback.is_dir() and os.access(fallback, os.W_OK)


@pytest.mark.parametrize("bad", [-5.0, -1.2])
def test_cut_leaving_no_stars_raises(bad):
    with pytest.raises(ValueError, match=rf"max_magnitude={bad}.*leaves no stars"):
        StarCatalog.from_hipparcos(bad)


def test_nan_cut_raises():
    with pytest.raises(ValueError, match="max_magnitude must not be NaN, got nan"):
        StarCatalog.from_hipparcos(float("nan"))


def test_bad_columns_raise(tmp_path):
    with pytest.raises(ValueError, match="ra has 1 entries, ids has 2"):
        StarCatalog([1, 2], [0.1], [0.1, 0.2], [1.0, 2.0])
    with pytest.raises(ValueError, match="dec holds non-finite"):
        StarCatalog([1], [0.1], [float("nan")], [1.0])
    with pytest.raises(ValueError, match="path=.*is not a file"):
        load_hipparcos_table(tmp_path / "missing.dat")
    with pytest.raises(ValueError, match="finite non-zero"):
        StarCatalog.from_vectors([[0.0, 0.0, 0.0]])


def test_from_vectors_keeps_order_and_directions():
    r = torch.tensor([[0.0, 0.0, 2.0], [1.0, 1.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    cat = StarCatalog.from_vectors(r)
    assert cat.ids.tolist() == [0, 1, 2]
    # normalised, then through (α, δ) and back: a few roundings of unit entries
    assert_within(cat.r, r / r.norm(dim=1, keepdim=True), 1e-15, "directions of a catalogue from vectors")
