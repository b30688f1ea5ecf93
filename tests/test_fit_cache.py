"""Harmonic fits kept between runs: read back bit for bit, refitted whenever anything differs."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
from conftest import grid_nodes, write_map_csv

from cfm_fem.cli import main
from cfm_fem.io import fit_cache
from cfm_fem.models.harmonic import fit_harmonic


def source_free_field(p):
    """A source-free field, shape (m, 3), T, at ``p`` (m, 3) mm: a quadrupole and a sextupole."""
    x, y = p[:, 0] - 2.5, p[:, 1] - 2.5
    return np.c_[0.02 * y + 1e-3 * (x**2 - y**2), 0.02 * x - 2e-3 * x * y, 0.0 * x + 0.5]


@pytest.fixture
def env(tmp_path):
    return {fit_cache.ENV: str(tmp_path / "fits")}


def _same(a, b) -> bool:
    return all(
        np.array_equal(np.asarray(getattr(a, f.name)), np.asarray(getattr(b, f.name)))
        for f in dataclasses.fields(a)
    )


def test_a_stored_fit_is_read_back_bit_for_bit(env):
    pts = grid_nodes(6)
    B = source_free_field(pts)
    first, path1 = fit_cache.cached_fit(pts, B, env=env)
    again, path2 = fit_cache.cached_fit(pts, B, env=env)
    assert path1 is None and path2 is not None and path2.exists()
    assert _same(first, again) and _same(again, fit_harmonic(pts, B))
    assert isinstance(again.k, int) and isinstance(again.fallback_rule, str)
    inside = pts[np.all(pts < pts.max(0), axis=1)] + 0.05
    (b1, ok1), (b2, ok2) = first.field_at(inside), again.field_at(inside)
    assert (
        first.use.all()
        and ok1.all()
        and np.array_equal(ok1, ok2)
        and np.array_equal(b1[ok1], b2[ok2])
    )


def test_another_field_option_or_order_is_fitted_afresh(env):
    pts = grid_nodes(6)
    B = source_free_field(pts)
    fit_cache.cached_fit(pts, B, env=env)
    B2 = B.copy()
    B2[7, 1] += 1e-12  # one value in the last digits
    assert fit_cache.cached_fit(pts, B2, env=env)[1] is None
    assert fit_cache.cached_fit(pts, B, env=env, k=30)[1] is None
    assert fit_cache.cached_fit(pts, B, env=env, metric="grid")[1] is None
    assert fit_cache.cached_fit(pts[::-1], B[::-1], env=env)[1] is None
    assert fit_cache.cached_fit(pts, B, env=env, source="other.csv")[1] is not None
    assert len(list(fit_cache.cache_folder(env).glob("*.npz"))) == 5


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty"])
def test_a_damaged_file_is_fitted_again_and_replaced(env, damage):
    pts = grid_nodes(5)
    B = source_free_field(pts)
    fit_cache.cached_fit(pts, B, env=env)
    (path,) = fit_cache.cache_folder(env).glob("*.npz")
    data = path.read_bytes()
    path.write_bytes(
        {"truncated": data[: len(data) // 2], "garbage": b"x" * 99, "empty": b""}[damage]
    )
    fit, hit = fit_cache.cached_fit(pts, B, env=env)
    assert hit is None and _same(fit, fit_harmonic(pts, B))
    assert fit_cache.cached_fit(pts, B, env=env)[1] == path


def test_off_or_an_unwritable_folder_fits_without_a_cache(tmp_path):
    pts = grid_nodes(5)
    B = source_free_field(pts)
    blocker = tmp_path / "a_file"
    blocker.write_text("")
    for env in ({fit_cache.ENV: "off"}, {fit_cache.ENV: str(blocker / "fits")}):
        fit, hit = fit_cache.cached_fit(pts, B, env=env)
        assert hit is None and _same(fit, fit_harmonic(pts, B))
    assert fit_cache.cache_folder({fit_cache.ENV: "OFF"}) is None
    assert fit_cache.cache_folder({"HOME": "/h"}) == fit_cache.Path("/h/.cache/cfm_fem/fits")
    assert fit_cache.cache_folder({"XDG_CACHE_HOME": "/x", "HOME": "/h"}).parts[:2] == ("/", "x")


def test_the_folder_keeps_the_recently_read_fits_within_its_bound(env):
    folder = fit_cache.cache_folder(env)
    pts = grid_nodes(5)
    for i in range(3):
        fit_cache.cached_fit(pts, source_free_field(pts) * (1 + i), env=env)
    files = sorted(folder.glob("*.npz"), key=lambda p: p.stat().st_mtime)
    size = files[0].stat().st_size
    fit_cache._prune(folder, max_bytes=2 * size + size // 2)
    left = sorted(folder.glob("*.npz"))
    assert len(left) == 2 and files[0] not in left


def test_a_second_sweep_reads_the_fits_and_writes_the_same_maps(tmp_path, monkeypatch):
    import meshio

    monkeypatch.setenv(fit_cache.ENV, str(tmp_path / "fits"))
    pts = grid_nodes(7)
    path = write_map_csv(tmp_path / "map.csv", pts, source_free_field(pts))
    outs = []
    for run in ("first", "second"):
        out = tmp_path / run
        args = [str(path), "--up", "0,20", "--trials", "300", "--out", str(out)]
        assert main(["sweep", *args]) == 0
        outs.append(out)
    notes = [json.loads((o / "summary.json").read_text()).get("notes", []) for o in outs]
    assert not any("cache" in n for n in notes[0])
    assert any("read from the cache" in n for n in notes[1])
    for name in ("uf_up0um.vtu", "uf_up20um.vtu"):
        a, b = (meshio.read(o / name).point_data for o in outs)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=k)
