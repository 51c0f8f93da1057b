"""The pixel rays' residual filter gives the same image in bands on a pool as in one piece."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from hybridgi_core.pixel_gather import _power_into, filter_residual


@pytest.mark.parametrize("passes", [1, 3])
def test_bands_equal_one_piece(passes):
    h, w = 150, 90
    rng = np.random.default_rng(4)
    res = rng.normal(size=(h, w, 7)).astype(np.float32)
    pos = np.zeros((h, w, 3), np.float32)
    pos[..., 0], pos[..., 1] = np.meshgrid(np.arange(w) * 0.01, np.arange(h) * 0.01)
    pos[..., 2] = 3.0 + (np.arange(h)[:, None] > 70) * 0.5  # a step: taps across it do not count
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[..., 2] = 1.0
    valid = rng.random((h, w)) > 0.1
    var = np.abs(rng.normal(size=(h, w, 2))).astype(np.float32)
    eye = np.array([0.4, 0.7, 8.0], np.float32)
    whole = filter_residual(res, pos, nrm, valid, eye, passes, variance=var)
    with ThreadPoolExecutor(2) as pool:
        bands = filter_residual(res, pos, nrm, valid, eye, passes, variance=var, pool=pool)
    np.testing.assert_array_equal(bands, whole)
    assert np.abs(whole).std() < np.abs(res).std()  # it did filter


def test_power_by_squaring():
    x = np.linspace(0, 1, 11, dtype=np.float32)
    for e in (1, 2, 8, 16, 3, 2.5):
        out = np.empty_like(x)
        _power_into(x, e, out)
        np.testing.assert_allclose(out, x.astype(np.float64) ** e, rtol=1e-5, atol=1e-7)
