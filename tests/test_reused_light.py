"""The centre's direct light as jittered subframes reuse it (`hybridgi_core/raster/reused_light.py`):
the filter share their jitter does not sample, kept on each pixel's own surface. bpy-free."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core.raster.reused_light import filter_on_surface, reuse_taps
from hybridgi_core.raster.subpixel import SAME_COS, SAME_PLANE, reconstruction_taps


def _plane(h: int, w: int, z: float = 0.0, normal=(0.0, 0.0, 1.0), spacing: float = 0.01):
    """A plane of pixels at height z, its points spacing apart, seen from 5 units away."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    pos = np.stack([xx * spacing, yy * spacing, np.full_like(xx, z), np.ones_like(xx)], -1).reshape(-1, 4)
    nrm = np.tile(np.asarray(normal, np.float32), (h * w, 1))
    return pos, nrm, np.full(h * w, 5.0, np.float32)


@pytest.mark.parametrize("count", [2, 4, 8])
def test_the_taps_add_what_the_film_leaves_out(count):
    one = reconstruction_taps(1, 1.5, "BLACKMAN_HARRIS")
    film = reconstruction_taps(count, 1.5, "BLACKMAN_HARRIS")
    taps = reuse_taps(count, 1.5, "BLACKMAN_HARRIS")
    assert taps.sum() == pytest.approx(1.0)
    # a neighbour's share: the reuse's plus the film's is one sample's (to first order in the shares)
    assert taps[0] + film[0] == pytest.approx(one[0])
    assert taps[0] == pytest.approx(one[0] * (1 - 1 / count))


def test_one_subframe_or_a_narrow_filter_keeps_the_light():
    assert reuse_taps(1, 1.5, "BLACKMAN_HARRIS").tolist() == [1.0]
    assert reuse_taps(4, 0.0, "BLACKMAN_HARRIS").tolist() == [1.0]
    assert reuse_taps(4, 1.0, "BOX").tolist() == [1.0]
    pos, nrm, depth = _plane(6, 7)
    light = np.random.default_rng(0).random((42, 3)).astype(np.float32)
    assert np.array_equal(filter_on_surface(light, pos, nrm, depth, (6, 7), np.ones(1)), light)


def test_noise_on_a_plane_averages_by_the_taps_squared():
    """Independent noise on one plane: an inner pixel's variance falls to (sum of taps^2)^2 of it
    (separable), and the mean stays."""
    h, w = 120, 160
    pos, nrm, depth = _plane(h, w)
    rng = np.random.default_rng(1)
    light = (1.0 + 0.2 * rng.standard_normal((h * w, 3))).astype(np.float32)
    taps = reuse_taps(2, 1.5, "BLACKMAN_HARRIS")
    out = filter_on_surface(light, pos, nrm, depth, (h, w), taps).reshape(h, w, 3)[2:-2, 2:-2]
    inner = light.reshape(h, w, 3)[2:-2, 2:-2]
    assert out.mean() == pytest.approx(inner.mean(), abs=2e-3)
    assert out.var() / inner.var() == pytest.approx(float((taps**2).sum()) ** 2, rel=0.05)


def test_light_does_not_cross_to_another_surface():
    """A floor beside a wall-like step (another height, then another facing): each keeps its own
    constant light exactly, though they are neighbours on screen."""
    h, w = 8, 12
    pos, nrm, depth = _plane(h, w)
    pos = pos.reshape(h, w, 4)
    nrm = nrm.reshape(h, w, 3)
    pos[:, 6:, 2] = 0.5  # a ledge half a unit up: off the floor's tangent plane
    nrm[:, 9:] = (1.0, 0.0, 0.0)  # and a face turned away: another normal
    light = np.zeros((h, w, 3), np.float32)
    light[:, :6], light[:, 6:9], light[:, 9:] = 1.0, 3.0, 7.0
    out = filter_on_surface(light.reshape(-1, 3), pos.reshape(-1, 4), nrm.reshape(-1, 3), depth, (h, w),
                            reuse_taps(4, 1.5, "BLACKMAN_HARRIS")).reshape(h, w, 3)
    assert np.allclose(out, light, rtol=1e-6, atol=0.0)


def test_the_surface_tests_are_the_subframes():
    """A neighbour just inside SAME_PLANE x depth of the tangent plane (and SAME_COS) counts, one
    just outside does not."""
    h, w = 1, 2
    taps = reuse_taps(2, 1.5, "BLACKMAN_HARRIS")
    light = np.array([[0.0] * 3, [1.0] * 3], np.float32)
    for lift, counts in ((0.9, True), (1.1, False)):
        pos, nrm, depth = _plane(h, w)
        pos[1, 2] = lift * SAME_PLANE * depth[0]
        out = filter_on_surface(light, pos, nrm, depth, (h, w), taps)
        assert (out[0, 0] > 0) == counts
    tilt = np.arccos(SAME_COS)
    for angle, counts in ((0.9 * tilt, True), (1.1 * tilt, False)):
        pos, nrm, depth = _plane(h, w)
        nrm[1] = (np.sin(angle), 0.0, np.cos(angle))
        out = filter_on_surface(light, pos, nrm, depth, (h, w), taps)
        assert (out[0, 0] > 0) == counts


def test_kept_and_background_pixels_are_left_and_not_read():
    h, w = 10, 10
    pos, nrm, depth = _plane(h, w)
    rng = np.random.default_rng(2)
    light = rng.random((h * w, 3)).astype(np.float32)
    background = np.zeros(h * w, bool)
    background[:30] = True
    pos[background, 3] = 0.0
    light[background] = np.nan  # never read
    keep = np.zeros(h * w, bool)
    keep[55] = True
    out = filter_on_surface(light, pos, nrm, depth, (h, w), reuse_taps(2, 1.5, "BLACKMAN_HARRIS"), keep=keep)
    assert np.isfinite(out[~background]).all()
    assert np.isnan(out[background]).all()
    assert np.array_equal(out[55], light[55])
    assert not np.allclose(out[~background & ~keep], light[~background & ~keep])
    assert not np.shares_memory(out, light)


def test_it_is_the_separable_filter_of_its_definition():
    """Against a per-pixel loop: vertical taps then horizontal, each renormalised over the taps on
    the pixel's surface."""
    h, w = 7, 9
    rng = np.random.default_rng(3)
    pos, nrm, depth = _plane(h, w)
    pos[rng.random(h * w) < 0.3, 2] = 1.0  # scattered pixels on another plane
    light = rng.random((h * w, 3)).astype(np.float32)
    taps = reuse_taps(2, 3.0, "BLACKMAN_HARRIS")  # radius 3
    r = taps.size // 2
    img = light.reshape(h, w, 3).astype(np.float64)
    P, N, D = pos.reshape(h, w, 4), nrm.reshape(h, w, 3), depth.reshape(h, w)

    def on(y, x, y2, x2):
        d = P[y2, x2, :3] - P[y, x, :3]
        return N[y, x] @ N[y2, x2] >= SAME_COS and abs(d @ N[y, x]) <= SAME_PLANE * D[y, x]

    for axis in (0, 1):
        nxt = np.zeros_like(img)
        for y in range(h):
            for x in range(w):
                acc, tot = np.zeros(3), 0.0
                for k in range(-r, r + 1):
                    y2, x2 = (y, x + k) if axis == 1 else (y + k, x)
                    if 0 <= y2 < h and 0 <= x2 < w and on(y, x, y2, x2):
                        acc += taps[r + k] * img[y2, x2]
                        tot += taps[r + k]
                nxt[y, x] = acc / tot
        img = nxt
    out = filter_on_surface(light, pos, nrm, depth, (h, w), taps)
    assert np.allclose(out.reshape(h, w, 3), img, atol=1e-5)
