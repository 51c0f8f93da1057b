"""The GPU full-res interpolation (`raster/upsample.py`) against its numpy reference
(`pixel_gather.upsample_full`): a floor meeting a wall at a crease, a bump whose normals turn
(the taps' SH read at each pixel's own normal), holes, at factor 4."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core.pixel_gather import tap_records, upsample_full

FACTOR = 4
H, W = 11, 15  # the GI resolution
HF, WF = H * FACTOR, W * FACTOR


def _surface(x, y):
    """Position and unit normal at full-res pixel coordinates (x, y): floor left, wall right, a
    bump on the floor."""
    floor = x < WF * 0.55
    pos = np.where(floor[..., None], np.stack([x * 0.05, y * 0.05, np.zeros_like(x)], -1),
                   np.stack([np.full_like(x, WF * 0.55 * 0.05), y * 0.05, (x - WF * 0.55) * 0.05], -1))
    nrm = np.where(floor[..., None], [0.0, 0.0, 1.0], [-1.0, 0.0, 0.0])
    bump = floor & ((x - 12.0) ** 2 + (y - 20.0) ** 2 < 64.0)
    tilt = np.stack([(x - 12.0) / 10.0, (y - 20.0) / 10.0, np.ones_like(x)], -1)
    nrm = np.where(bump[..., None], tilt / np.linalg.norm(tilt, axis=-1, keepdims=True), nrm)
    return pos.astype(np.float32), nrm.astype(np.float32)


def _inputs(order: int, seed: int = 5):
    rng = np.random.default_rng(seed)
    k = 4 if order == 1 else 9
    j, i = np.mgrid[0:H, 0:W].astype(np.float32)
    rep = np.stack([i * FACTOR + rng.integers(0, FACTOR, (H, W)), j * FACTOR + rng.integers(0, FACTOR, (H, W))], -1)
    position_lo, normal_lo = _surface(rep[..., 0].astype(np.float32), rep[..., 1].astype(np.float32))
    valid_lo = rng.random((H, W)) > 0.1
    sh_lo = rng.random((H * W, k, 7)).astype(np.float32) * 0.3
    cache_lo = rng.random((H * W, 7)).astype(np.float32)
    residual_lo = (rng.standard_normal((H * W, 7)) * 0.1).astype(np.float32)
    y, x = np.mgrid[0:HF, 0:WF].astype(np.float32)
    points, normals = _surface(x, y)
    keep = rng.random((HF, WF)) > 0.05
    pix = np.flatnonzero(keep.reshape(-1))
    rep_xy = rep.reshape(-1, 2).astype(np.float32)
    camera = np.array([1.0, -3.0, 2.5], np.float32)
    return (sh_lo, cache_lo, residual_lo, position_lo, normal_lo, valid_lo, points.reshape(-1, 3)[pix],
            normals.reshape(-1, 3)[pix], pix, WF, FACTOR, camera), rep_xy


@pytest.mark.parametrize("order", [1, 2])
def test_gpu_upsample_equals_upsample_full(gpu_context, order):
    from hybridgi_core.raster.upsample import UpsamplePass

    args, rep_xy = _inputs(order)
    records = tap_records(*args[1:6], rep_xy)
    ref = upsample_full(*args, rep_xy=rep_xy, records=records)
    assert ref.turned.any() and not ref.turned.all()  # the bump's pixels read the SH at their normals
    assert (ref.cover < 0.5).any()  # pixels by the crease: part of their taps on the other surface
    upsample = UpsamplePass()
    try:
        got = upsample(*args, rep_xy=rep_xy, records=records)
    finally:
        upsample.free()
    for field in ("cache", "residual", "spread", "best", "cover"):
        np.testing.assert_allclose(getattr(got, field), getattr(ref, field), rtol=2e-4, atol=2e-5, err_msg=field)
    np.testing.assert_array_equal(got.turned, ref.turned)


def test_gpu_upsample_hands_bent_normals_to_numpy(gpu_context):
    """Pixels a normal map bends read the bent lobe, which the GPU pass does not port: the numpy
    answer, the same object type."""
    from hybridgi_core.raster.upsample import UpsamplePass

    args, rep_xy = _inputs(2)
    surfaces = args[7].copy()
    ref = upsample_full(*args, rep_xy=rep_xy, surfaces=surfaces)
    upsample = UpsamplePass()
    try:
        got = upsample(*args, rep_xy=rep_xy, surfaces=surfaces)
    finally:
        upsample.free()
    np.testing.assert_array_equal(got.cache, ref.cache)


def test_gpu_upsample_hands_images_past_the_texture_limit_to_numpy(gpu_context, monkeypatch):
    """A GI image whose SH texture would exceed the GPU's texture size (a very large render) is
    interpolated by numpy, not refused by the driver."""
    from hybridgi_core.raster import upsample as up

    args, rep_xy = _inputs(2)
    monkeypatch.setattr(up, "max_texture_size", lambda: 8)
    ref = upsample_full(*args, rep_xy=rep_xy)
    upsample = up.UpsamplePass()
    try:
        got = upsample(*args, rep_xy=rep_xy)
        assert upsample.width == 0  # no GPU target was made
    finally:
        upsample.free()
    np.testing.assert_array_equal(got.cache, ref.cache)
