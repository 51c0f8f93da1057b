"""`filter_at_pixels` gathering taps at a few kept pixels gives the whole-image filter's bits."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import pixel_gather
from hybridgi_core.pixel_gather import filter_at_pixels


@pytest.mark.parametrize("passes, channels", [(1, 3), (2, 6), (3, 1)])
def test_sparse_equals_whole_image(passes, channels):
    h, w = 60, 110
    rng = np.random.default_rng(passes)
    pix = np.sort(rng.choice(h * w, h * w // 10, replace=False))
    y, x = np.divmod(pix, w)
    # Two planes a step apart (taps across the step do not count) and slightly tilted normals.
    points = np.stack([x * 0.01, y * 0.01, (x > 50) * 0.5 + rng.normal(0, 1e-3, pix.size)], 1).astype(np.float32)
    normals = np.array([0, 0, 1], np.float32) + 0.2 * rng.normal(size=(pix.size, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    values = rng.random((pix.size, channels)).astype(np.float32)
    keep = rng.random(pix.size) > 0.2
    eye = np.array([0.5, 0.3, 3.0])
    assert np.count_nonzero(keep) <= pixel_gather.SPARSE_FILTER_SHARE * h * w  # the sparse path
    sparse = filter_at_pixels(values, keep, points, normals, pix, (h, w), eye, passes)
    np.testing.assert_array_equal(sparse, pixel_gather._filter_dense(values, keep, points, normals, pix, (h, w), eye, passes))
    assert not np.array_equal(sparse[keep], values[keep])  # it did filter
    np.testing.assert_array_equal(sparse[~keep], values[~keep])


def test_sparse_halves_on_a_pool_equal_one_piece():
    from concurrent.futures import ThreadPoolExecutor

    h, w = 180, 200
    rng = np.random.default_rng(9)
    pix = np.sort(rng.choice(h * w, pixel_gather.SPARSE_SPLIT_PIXELS + 100, replace=False))
    y, x = np.divmod(pix, w)
    points = np.stack([x * 0.01, y * 0.01, (y > 60) * 0.3 + 0 * x], 1).astype(np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (pix.size, 1))
    values = rng.random((pix.size, 3)).astype(np.float32)
    keep = np.ones(pix.size, bool)
    assert pix.size <= pixel_gather.SPARSE_FILTER_SHARE * h * w  # the sparse path
    eye = np.array([0.8, 0.6, 3.0])
    one = filter_at_pixels(values, keep, points, normals, pix, (h, w), eye, 2)
    with ThreadPoolExecutor(2) as pool:
        split = filter_at_pixels(values, keep, points, normals, pix, (h, w), eye, 2, pool=pool)
    np.testing.assert_array_equal(split, one)
