"""The pixel GI a lamp edit carries over (`hybridgi_core.gi_carry`): exact for a change of power,
robust to the re-lit cache's noise, per surface orientation, bounded where the old light was dark."""

from __future__ import annotations

import numpy as np

from hybridgi_core import gi_carry

H, W = 24, 32  # the GI image (every pixel on geometry)


def _points(normal=(0.0, 0.0, 1.0)):
    pix = np.arange(H * W)
    normals = np.tile(np.asarray(normal, np.float32), (pix.size, 1))
    return pix, normals


def _textures(value: np.ndarray, ao: float = 0.7):
    """(indirect, direct) (H, W, 4) textures of per-pixel values (n, 6: direct rgb, indirect rgb)."""
    indirect = np.zeros((H * W, 4), np.float32)
    direct = np.zeros((H * W, 4), np.float32)
    indirect[:, :3], indirect[:, 3] = value[:, 3:6], ao
    direct[:, :3] = value[:, 0:3]
    return indirect.reshape(H, W, 4), direct.reshape(H, W, 4)


def _carry(old_value, cache_old, cache_new, normals, pix):
    indirect, direct = _textures(old_value)
    ratio, extra = gi_carry.smoothed_change(cache_old, cache_new, pix, normals, (H, W))
    new_i, new_d = gi_carry.carried(indirect, direct, ratio, extra, np.arange(pix.size), pix)
    return np.concatenate([new_d.reshape(-1, 4)[:, :3], new_i.reshape(-1, 4)[:, :3]], axis=1), new_i


def _cache(rng, n, level=1.0):
    c = np.zeros((n, 7), np.float32)
    c[:, 0:6] = level * (0.5 + rng.random((1, 6)))
    c[:, 6] = 0.8
    return c


def test_a_change_of_power_scales_the_rays_light_and_keeps_its_detail_and_ao():
    """Every channel's light times its own factor (a lamp's power and colour): the carried image
    is the old one times that factor, its residual detail over the cache included; AO untouched."""
    rng = np.random.default_rng(1)
    pix, normals = _points()
    cache_old = _cache(rng, pix.size)
    detail = rng.random((pix.size, 6)).astype(np.float32) * 0.3  # what the rays saw beyond the cache
    old = cache_old[:, 0:6] + detail
    factor = np.array([1.0, 1.0, 1.0, 2.5, 0.5, 4.0], np.float32)
    cache_new = cache_old.copy()
    cache_new[:, 0:6] *= factor
    new, new_i = _carry(old, cache_old, cache_new, normals, pix)
    # The floor (FLOOR of the mean cache light) bends the ratio by at most a few percent.
    np.testing.assert_allclose(new, old * factor, rtol=0.05)
    np.testing.assert_array_equal(new_i.reshape(-1, 4)[:, 3], np.float32(0.7))


def test_the_re_lit_caches_noise_is_not_printed_on_the_image():
    """A re-lit cache whose cells are noisy (30% per pixel): the carried image keeps the old
    image's smoothness, within a few percent of the true factor, where each pixel's own ratio
    would carry the noise."""
    rng = np.random.default_rng(2)
    pix, normals = _points()
    cache_old = _cache(rng, pix.size)
    old = cache_old[:, 0:6] * 1.1
    cache_new = cache_old.copy()
    cache_new[:, 0:6] *= 2.0 * (1.0 + 0.3 * rng.standard_normal((pix.size, 1)).astype(np.float32))
    new, _ = _carry(old, cache_old, cache_new, normals, pix)
    per_pixel = old * cache_new[:, 0:6] / cache_old[:, 0:6]
    err = np.abs(new / (2.0 * old) - 1.0)
    assert float(err.mean()) < 0.05
    assert float(np.abs(per_pixel / (2.0 * old) - 1.0).mean()) > 4 * float(err.mean())


def test_surfaces_facing_apart_take_their_own_change():
    """A floor and a wall in one image (left and right halves), the lamp's light doubled on the
    floor and halved on the wall: each side carries its own factor, up to the seam."""
    rng = np.random.default_rng(3)
    pix = np.arange(H * W)
    x = pix % W
    wall = x >= W // 2
    normals = np.where(wall[:, None], np.float32([1.0, 0.0, 0.0]), np.float32([0.0, 0.0, 1.0])).astype(np.float32)
    cache_old = _cache(rng, pix.size)
    old = cache_old[:, 0:6] * 1.2
    cache_new = cache_old.copy()
    cache_new[:, 0:6] *= np.where(wall, 0.5, 2.0)[:, None]
    new, _ = _carry(old, cache_old, cache_new, normals, pix)
    factor = new / old
    np.testing.assert_allclose(factor[~wall], 2.0, rtol=0.03)
    np.testing.assert_allclose(factor[wall], 0.5, rtol=0.03)


def test_light_where_the_old_cache_was_dark_is_bounded_and_still_arrives():
    """Where the old cache saw no light and the re-lit one does (a lamp moved into a dark
    corner): the ratio stops at RATIO_MAX and the rest of the new cache light is added, so the
    carried light is finite and at least the new cache's."""
    rng = np.random.default_rng(4)
    pix, normals = _points()
    cache_old = _cache(rng, pix.size)
    dark = pix // W < 16  # rows 0-15: four blocks of BLOCK rows
    cache_old[dark, 0:6] = 0.0
    old = cache_old[:, 0:6].copy()
    cache_new = cache_old.copy()
    cache_new[dark, 0:6] = 3.0
    new, _ = _carry(old, cache_old, cache_new, normals, pix)
    assert np.isfinite(new).all()
    # Rows whose box of blocks holds no lit pixel: the new cache's light there.
    rows = pix // W < 6
    np.testing.assert_allclose(new[rows], 3.0, rtol=1e-4)
    assert (new[dark] >= 0).all() and (new[dark] <= 3.0 + 1e-4).all()


def test_each_full_res_pixel_reads_the_gi_point_of_its_own_surface():
    """At a silhouette the GI pixel of a full-res pixel's 2x2 block can hold the surface behind
    it: the pixel takes the neighbour GI point on its own surface; a pixel with no GI geometry
    around it gets -1."""
    h, w, factor = 4, 4, 2
    lo_pix = np.arange(h * w)
    lo_points = np.zeros((h * w, 3), np.float32)
    lo_points[:, 2] = np.where(lo_pix % w < 2, 0.0, 5.0)  # left half near, right half far
    lo_points[:, 0] = lo_pix % w
    full_w = w * factor
    # A full-res pixel in the block of GI pixel (x=2, y=1) (far), whose own point is near (z=0).
    q = (1 * factor) * full_w + 2 * factor
    near = gi_carry.nearest_lo_point(np.float32([[1.6, 0.0, 0.0]]), np.array([q]), full_w, lo_points, lo_pix, (h, w))
    assert lo_points[near[0], 2] == 0.0 and near[0] == 1 * w + 1
    # With GI geometry only in the top row, a pixel at the bottom finds none within its reach.
    top = lo_pix[lo_pix < w]
    far = gi_carry.nearest_lo_point(np.float32([[0.0, 0.0, 0.0]]), np.array([(h * factor - 1) * full_w]), full_w,
                                    lo_points[top], top, (h, w))
    assert far[0] == -1
