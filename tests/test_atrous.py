"""The GPU a-trous filter (`raster/atrous.py`) against its numpy reference
(`pixel_gather.filter_residual`): same weights, same answer, on an image with two planes, a
crease, holes and noise, with and without the variance guides."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core.pixel_gather import filter_residual

H, W = 37, 53


def _scene(seed: int = 3):
    """Positions/normals of a floor (left) meeting a wall (right) at a crease, a nearer box in the
    middle rows, background holes; a noisy 7-channel residual and its variances."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    position = np.zeros((H, W, 3), np.float32)
    normal = np.zeros((H, W, 3), np.float32)
    floor = x < W // 2
    position[floor] = np.stack([x[floor] * 0.1, y[floor] * 0.1, np.zeros(floor.sum())], axis=1)
    normal[floor] = (0.0, 0.0, 1.0)
    wall = ~floor
    position[wall] = np.stack([np.full(wall.sum(), W // 2 * 0.1), y[wall] * 0.1, (x[wall] - W // 2) * 0.1], axis=1)
    normal[wall] = (-1.0, 0.0, 0.0)
    box = (y > 12) & (y < 20) & (x > 20) & (x < 34)
    position[box] += (0.0, 0.0, 0.8)
    valid = rng.random((H, W)) > 0.1
    valid[:3, :5] = False
    light = np.where(floor[..., None], 1.0, 0.3) + 0.05 * rng.standard_normal((H, W, 7))
    residual = light.astype(np.float32)
    residual[..., 6] = np.clip(rng.random((H, W)), 0, 1)
    variance = (0.01 + 0.02 * rng.random((H, W, 3))).astype(np.float32)
    return residual, position, normal, valid, np.array([1.0, -4.0, 2.0], np.float32), variance


@pytest.mark.parametrize("case", ["plain3", "plain7", "guides2", "guides3", "guides3_stretch"])
def test_gpu_atrous_equals_filter_residual(gpu_context, case):
    from hybridgi_core.raster.atrous import AtrousPass

    residual, position, normal, valid, camera, variance = _scene()
    channels = 3 if case == "plain3" else 7
    var = {"guides2": variance[..., [0, 2]], "guides3": variance, "guides3_stretch": variance}.get(case)
    stretch = 4.0 if case.endswith("stretch") else None
    args = (residual[..., :channels], position, normal, valid, camera, 3, 0.02, 8.0)
    ref = filter_residual(*args, variance=var, noise_sigma=1.5, stretch=stretch)
    if stretch is not None:  # the term matters on this image (the floor is seen at a slant)
        assert np.abs(ref - filter_residual(*args, variance=var, noise_sigma=1.5)).max() > 1e-3
    atrous = AtrousPass()
    try:
        got = atrous(*args, variance=var, noise_sigma=1.5, stretch=stretch)
    finally:
        atrous.free()
    assert got.shape == ref.shape
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-5)
    # The filter did something: noise on the planes went down, the crease stayed.
    raw = np.where(valid[..., None], residual[..., :channels], 0.0)
    assert np.abs(np.diff(got[..., 0], axis=1))[valid[:, 1:] & valid[:, :-1]].mean() < \
        np.abs(np.diff(raw[..., 0], axis=1))[valid[:, 1:] & valid[:, :-1]].mean()
    assert np.all(got[~valid] == 0.0)


def test_gpu_atrous_without_passes_or_pixels_returns_the_masked_input(gpu_context):
    from hybridgi_core.raster.atrous import AtrousPass

    residual, position, normal, valid, camera, _variance = _scene()
    atrous = AtrousPass()
    try:
        out = atrous(residual, position, normal, valid, camera, 0)
        np.testing.assert_array_equal(out, np.where(valid[..., None], residual, 0.0))
        out = atrous(residual, position, normal, np.zeros_like(valid), camera, 3)
        assert not out.any()
    finally:
        atrous.free()


@pytest.mark.parametrize("channels", [3, 6])
def test_the_glossy_filters_take_the_gpu_pass_for_whole_images_only(gpu_context, channels):
    """`filter_at_pixels(filter=)`, as a final render's glossy light calls it (`finish_glossy`):
    a dense mask goes through the GPU pass with numpy's answer; a sparse one stays on numpy's
    gathered taps (the pass is not called)."""
    from hybridgi_core.pixel_gather import SPARSE_FILTER_SHARE, filter_at_pixels
    from hybridgi_core.raster.atrous import AtrousPass

    residual, position, normal, valid, camera, _ = _scene()
    pix = np.flatnonzero(valid.reshape(-1))
    values = np.ascontiguousarray(residual.reshape(-1, 7)[pix, :channels])
    points, normals = position.reshape(-1, 3)[pix], normal.reshape(-1, 3)[pix]
    dense = np.arange(pix.size) % 7 != 0
    sparse = np.arange(pix.size) % 10 == 0
    assert dense.sum() > SPARSE_FILTER_SHARE * H * W > sparse.sum()
    calls = []
    atrous = AtrousPass()

    def gpu(*args, **kwargs):
        calls.append(args[0].shape)
        return atrous(*args, **kwargs)

    try:
        results = [(filter_at_pixels(values, keep, points, normals, pix, (H, W), camera, 1),
                    filter_at_pixels(values, keep, points, normals, pix, (H, W), camera, 1, filter=gpu))
                   for keep in (dense, sparse)]
    finally:
        atrous.free()
    assert calls == [(H, W, channels)]
    for keep, (ref, got) in zip((dense, sparse), results, strict=True):
        np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-5)
        assert np.abs(got[keep] - values[keep]).max() > 1e-3  # filtered
        np.testing.assert_array_equal(got[~keep], values[~keep])  # the rest as it was


def test_gpu_atrous_takes_each_pixels_own_normal_exponent(gpu_context):
    """Per-pixel normal exponents (`reflection.reflection_power`) on normals that wobble by a few
    degrees: the GPU pass equals the numpy reference, and the sharp half's filter reaches less far
    than one exponent of 8 would (its pixels keep more of their own value)."""
    from hybridgi_core.raster.atrous import AtrousPass

    residual, position, normal, valid, camera, _ = _scene()
    rng = np.random.default_rng(5)
    normal = normal + 0.06 * rng.standard_normal(normal.shape).astype(np.float32)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    power = np.where(np.arange(H)[:, None] < H // 2, np.float32(2000.0), np.float32(8.0)) * np.ones((1, W), np.float32)
    args = (residual[..., :7], position, normal, valid, camera, 3, 0.02)
    ref = filter_residual(*args, power)
    atrous = AtrousPass()
    try:
        got = atrous(*args, power)
    finally:
        atrous.free()
    np.testing.assert_allclose(got, ref, rtol=2e-4, atol=2e-5)
    one = filter_residual(*args, 8.0)
    raw = np.where(valid[..., None], residual[..., :7], 0.0)
    sharp = (np.arange(H) < H // 2)[:, None] & valid
    assert np.abs(ref - raw)[sharp].mean() < 0.5 * np.abs(one - raw)[sharp].mean()
    # Beyond the passes' reach of the sharp half (2 + 4 + 8 rows), the exponent of 8 as before.
    far = (np.arange(H) >= H // 2 + 14)[:, None] & valid
    np.testing.assert_allclose(ref[far], one[far], rtol=1e-5, atol=1e-6)
