"""bench/imagediff.py: metrics on synthetic images, the PNG writer read back chunk by chunk, heatmaps."""

import struct
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))

import imagediff  # noqa: E402


@pytest.fixture
def rng():
    return np.random.default_rng(7)


def test_identical_images_have_zero_error(rng):
    img = rng.random((24, 32, 3))
    assert imagediff.relative_l1(img, img.copy()) == 0.0
    assert imagediff.relative_bias(img, img.copy()) == 0.0


def test_scaled_image_has_error_of_the_scale(rng):
    ref = rng.random((24, 32, 3)) + 0.1
    assert imagediff.relative_l1(ref * 1.1, ref) == pytest.approx(0.1, rel=1e-9)
    assert imagediff.relative_l1(ref * 0.9, ref) == pytest.approx(0.1, rel=1e-9)
    assert imagediff.relative_bias(ref * 1.1, ref) == pytest.approx(0.1, rel=1e-9)
    assert imagediff.relative_bias(ref * 0.9, ref) == pytest.approx(-0.1, rel=1e-9)


def test_error_is_summed_over_all_channels():
    ref = np.ones((4, 4, 3))
    test = ref.copy()
    test[..., 0] = 2.0  # one channel of three off by 100%
    assert imagediff.relative_l1(test, ref) == pytest.approx(1 / 3)


def test_mask_excludes_pixels(rng):
    ref = rng.random((16, 16, 3)) + 0.5
    test = ref.copy()
    mask = np.zeros((16, 16), bool)
    mask[:, :8] = True
    test[:, 8:] = 100.0  # garbage only where the mask is off
    test[:, :8] *= 1.25
    assert imagediff.relative_l1(test, ref, mask) == pytest.approx(0.25)
    assert imagediff.relative_l1(test, ref) > 1.0


def test_degenerate_references():
    zero = np.zeros((4, 4))
    assert imagediff.relative_l1(zero, zero) == 0.0
    assert imagediff.relative_l1(zero + 1, zero) == float("inf")
    with pytest.raises(ValueError):
        imagediff.relative_l1(np.zeros((4, 4)), np.zeros((4, 5)))
    with pytest.raises(ValueError):
        imagediff.relative_l1(zero, zero, np.ones((3, 3), bool))


def test_masked_geometry_from_depth_and_alpha():
    depth = np.full((3, 4), 1e10, np.float32)  # Cycles' background depth
    depth[1, 1:3] = 2.5
    depth[2, 0] = np.inf
    assert imagediff.masked_geometry(depth).sum() == 2
    assert imagediff.masked_geometry(depth, "depth")[1, 1]
    alpha = np.zeros((3, 4), np.float32)
    alpha[0] = 1.0
    alpha[1, 0] = 0.4
    got = imagediff.masked_geometry(alpha)
    assert got[0].all() and got.sum() == 4
    small_scene = np.full((2, 2), 0.5, np.float32)  # depths under one unit read as alpha unless told
    assert imagediff.masked_geometry(small_scene, "depth").all()
    with pytest.raises(ValueError):
        imagediff.masked_geometry(alpha, "stencil")


def test_box_blur_keeps_constants_and_means(rng):
    const = np.full((20, 30, 3), 0.7)
    np.testing.assert_allclose(imagediff.box_blur(const, 3), const, rtol=1e-6)
    noise = rng.random((64, 80))
    blurred = imagediff.box_blur(noise, 2)
    assert blurred.shape == noise.shape
    assert blurred.mean() == pytest.approx(noise.mean(), rel=0.01)
    assert blurred.std() < 0.5 * noise.std()  # it does average
    # Interior pixels are exact 5x5 means.
    assert blurred[10, 10] == pytest.approx(noise[8:13, 8:13].mean(), rel=1e-5)
    np.testing.assert_array_equal(imagediff.box_blur(noise, 0), noise.astype(np.float32))


def test_box_blur_does_not_pull_in_masked_pixels():
    img = np.zeros((10, 10))
    img[:, :5] = 1.0
    img[:, 5:] = 1000.0  # background to keep out
    mask = np.zeros((10, 10), bool)
    mask[:, :5] = True
    blurred = imagediff.box_blur(img, 3, mask)
    np.testing.assert_allclose(blurred[:, :5], 1.0)
    assert np.all(blurred[:, 5:] == 0.0)
    img[3, 7] = np.nan  # a masked-out NaN (an engine's bad pixel) stays out too
    np.testing.assert_allclose(imagediff.box_blur(img, 3, mask)[:, :5], 1.0)


def test_error_map_mean_is_relative_l1(rng):
    ref = rng.random((12, 12, 3)) + 0.2
    test = ref + rng.normal(0, 0.05, ref.shape)
    mask = rng.random((12, 12)) > 0.3
    emap = imagediff.error_map(test, ref, mask)
    assert float(emap[mask].mean()) == pytest.approx(imagediff.relative_l1(test, ref, mask), rel=1e-5)


def test_heatmap_range():
    err = np.linspace(-1.0, 3.0, 50).reshape(5, 10)
    rgb = imagediff.heatmap(err, vmax=2.0)
    assert rgb.shape == (5, 10, 3) and rgb.dtype == np.uint8
    lo = tuple(imagediff.heatmap(np.zeros((1, 1)), 1.0)[0, 0])
    hi = tuple(imagediff.heatmap(np.ones((1, 1)), 1.0)[0, 0])
    assert lo == (68, 1, 84)  # viridis' ends
    assert hi == (253, 231, 37)
    assert tuple(rgb[0, 0]) == lo and tuple(rgb[-1, -1]) == hi  # clamped beyond the scale
    # Brightness rises monotonically with the error: the reading order of a heatmap.
    ramp = imagediff.heatmap(np.linspace(0, 1, 256)[None], 1.0)[0].astype(float)
    luma = ramp @ np.array([0.2126, 0.7152, 0.0722])
    assert np.all(np.diff(luma) >= -0.5)
    mask = np.zeros((5, 10), bool)
    masked = imagediff.heatmap(err, 2.0, mask)
    assert np.all(masked == 40)
    with pytest.raises(ValueError):
        imagediff.heatmap(err, 0.0)


def read_png(path):
    """Minimal PNG decoder for filter type 0 images: the inverse of write_png, by the spec."""
    data = Path(path).read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind = data[pos + 4 : pos + 8]
        payload = data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + payload), kind
        chunks.append((kind, payload))
        pos += 12 + length
    kinds = [k for k, _p in chunks]
    assert kinds[0] == b"IHDR" and kinds[-1] == b"IEND"
    w, h, depth, color, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (depth, comp, filt, interlace) == (8, 0, 0, 0)
    channels = {0: 1, 4: 2, 2: 3, 6: 4}[color]
    raw = zlib.decompress(b"".join(p for k, p in chunks if k == b"IDAT"))
    rows = np.frombuffer(raw, np.uint8).reshape(h, 1 + w * channels)
    assert np.all(rows[:, 0] == 0)
    return rows[:, 1:].reshape(h, w, channels)


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_png_writer_round_trips(tmp_path, rng, channels):
    img = rng.integers(0, 256, (7, 11, channels), dtype=np.uint8)
    path = imagediff.write_png(tmp_path / "sub" / "x.png", img[..., 0] if channels == 1 else img)
    np.testing.assert_array_equal(read_png(path), img)


def test_png_writer_rejects_other_types(tmp_path):
    with pytest.raises(ValueError):
        imagediff.write_png(tmp_path / "f.png", np.zeros((4, 4, 3), np.float32))
    with pytest.raises(ValueError):
        imagediff.write_png(tmp_path / "f.png", np.zeros((4, 4, 5), np.uint8))


def test_comparison_strip_layout(tmp_path, rng):
    ref = rng.random((9, 13, 3))
    strip = imagediff.comparison_strip(ref * 1.2, ref, mask=np.ones((9, 13), bool), gap=2)
    assert strip.shape == (9, 3 * 13 + 4, 3) and strip.dtype == np.uint8
    assert np.all(strip[:, 13:15] == 255)  # the spacer
    # The test panel (20% brighter) is never darker than the reference panel at the same exposure.
    assert np.all(strip[:, :13].astype(int) >= strip[:, 15:28].astype(int))
    np.testing.assert_array_equal(read_png(imagediff.write_png(tmp_path / "s.png", strip)), strip)


# --- bench/compare_cycles.py's spp-sweep models (pure functions; no renders) ---------------------


def _sweep(sigma=1.2, rate=0.04, spps=(16, 64, 256)):
    """Errors of an ideal Monte Carlo sweep, sigma / sqrt(spp), and seconds proportional to spp."""
    return [{"spp": n, "rel_l1": sigma / n**0.5, "seconds": rate * n} for n in spps]


def test_equal_quality_interpolates_in_log_spp():
    import compare_cycles

    got = compare_cycles.equal_quality(_sweep(), 1.2 / 100**0.5)
    assert not got["extrapolated"]
    assert got["spp"] == pytest.approx(100, rel=1e-3)
    assert got["seconds"] == pytest.approx(4.0, rel=1e-3)


def test_equal_quality_extrapolates_with_the_power_law():
    import compare_cycles

    ref = {"samples": 1024, "seconds": 0.04 * 1024}
    low = compare_cycles.equal_quality(_sweep(), 1.2 / 4**0.5, ref)  # worse than 16 spp
    assert low["extrapolated"] and low["spp"] == pytest.approx(4, rel=1e-3)
    assert low["seconds"] == pytest.approx(0.16, rel=1e-3)  # never negative: proportional below
    high = compare_cycles.equal_quality(_sweep(), 1.2 / 2048**0.5, ref)
    assert high["extrapolated"] and high["spp"] == pytest.approx(2048, rel=1e-3)
    assert high["seconds"] == pytest.approx(0.04 * 2048, rel=1e-3)
    assert compare_cycles.equal_quality(_sweep()[:1], 0.1) is None  # one point is no model


def test_equal_time_and_reference_noise():
    import compare_cycles

    got = compare_cycles.equal_time(_sweep(), 0.04 * 100)
    assert got["spp"] == pytest.approx(100, rel=1e-3)
    assert got["rel_l1"] == pytest.approx(0.12, rel=1e-3)
    # Errors measured against a 1024-spp reference carry its noise: sigma * sqrt(1/n + 1/N).
    noisy = [dict(p, rel_l1=1.2 * (1 / p["spp"] + 1 / 1024) ** 0.5) for p in _sweep()]
    assert compare_cycles.reference_noise(noisy, 1024) == pytest.approx(1.2 / 32, abs=1e-4)
