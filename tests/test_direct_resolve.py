"""The viewport's direct-light resolve (`DirectResolvePass`, `addon/direct_resolve_frag.glsl`):
the worker's light at its pixels, resolved at the pixels the draw rasterized. A plane seen
head-on, lit on one side of a hard shadow edge: a source at the frame's own resolution keeps
each pixel's own light (no blur across the edge) and interpolates a jittered subframe's
position between its two nearest pixels; a lower-resolution source (a moving view's coarse
pass) is interpolated smoothly."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

pytestmark = pytest.mark.blender

W, H = 24, 16
DEPTH = 5.0  # the plane z = -DEPTH, seen by a camera at the origin along -z
EDGE = 11  # pixels x < EDGE are lit


def _proj(fov_y: float = 0.8) -> np.ndarray:
    f = 1.0 / np.tan(fov_y / 2)
    near, far = 0.1, 100.0
    return np.array([[f * H / W, 0, 0, 0], [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]], np.float32)


def _plane(proj: np.ndarray, w: int, h: int, shift: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """(position, normal) (h, w, 4) of the plane at pixel centres shifted by `shift` pixels in x
    (row 0 at the bottom, as textures are uploaded)."""
    x_ndc = (np.arange(w) + 0.5 + shift) / w * 2 - 1
    y_ndc = (np.arange(h) + 0.5) / h * 2 - 1
    pos = np.zeros((h, w, 4), np.float32)
    pos[..., 0] = (x_ndc * DEPTH / proj[0, 0])[None, :]
    pos[..., 1] = (y_ndc * DEPTH / proj[1, 1])[:, None]
    pos[..., 2] = -DEPTH
    pos[..., 3] = 1.0
    nrm = np.zeros((h, w, 4), np.float32)
    nrm[..., 2] = 1.0
    return pos, nrm


@pytest.fixture
def passes(bpy_module, gpu_context):
    from hybridgi_cli import dev_install

    package = dev_install.enable()
    return importlib.import_module(f"{package.__name__}.viewport_passes")


def _resolve(passes, source_size: tuple[int, int], shift: float, edges=None, offsets=None, index: int = 0,
             lift: float = 0.0) -> np.ndarray:
    """The resolve at the plane's pixel centres shifted by `shift` px (lifted off the plane by
    `lift` at x >= EDGE), from a source of `source_size` lit at x < EDGE; edges : the result's
    `EdgeLight` (with the draw's `offsets` and subframe `index`), or None."""
    from hybridgi_core.raster.readback import upload_texture_2d

    proj, view = _proj(), np.eye(4, dtype=np.float32)
    sw, sh = source_size
    src_pos, src_nrm = _plane(proj, sw, sh)
    light = np.zeros((sh, sw, 4), np.float32)
    light[..., 3] = 1.0
    light[:, : EDGE * sw // W, :3] = 2.0
    source = passes.DirectSource(1, upload_texture_2d(light, "RGBA32F"), upload_texture_2d(src_pos, "RGBA32F"),
                                 upload_texture_2d(src_nrm, "RGBA16F"), view, proj, sw, sh,
                                 passes.pixel_footprint(proj, sh), edges)
    pos, nrm = _plane(proj, W, H, shift)
    pos[:, EDGE:, 2] += lift
    resolve = passes.DirectResolvePass("RGBA32F")
    resolve.resize(W, H)
    try:
        subframe = -1 if edges is None else source.edge_subframe(index, offsets)
        resolve.execute(upload_texture_2d(pos, "RGBA32F"), upload_texture_2d(nrm, "RGBA16F"), source,
                        subframe=subframe)
        return resolve.read()
    finally:
        resolve.free()


def test_same_resolution_source_keeps_each_pixels_light(passes):
    out = _resolve(passes, (W, H), 0.0)
    assert (out[..., 3] == 1.0).all()
    np.testing.assert_allclose(out[:, :EDGE, 0], 2.0, atol=1e-5)  # no blur across the edge
    np.testing.assert_allclose(out[:, EDGE:, 0], 0.0, atol=1e-5)


def test_jittered_subframe_interpolates_its_two_nearest_pixels(passes):
    out = _resolve(passes, (W, H), 0.5)  # half a pixel right: halfway between two centres
    np.testing.assert_allclose(out[:, EDGE - 1, 0], 1.0, atol=1e-3)
    np.testing.assert_allclose(out[:, : EDGE - 1, 0], 2.0, atol=1e-4)
    np.testing.assert_allclose(out[:, EDGE:-1, 0], 0.0, atol=1e-4)


def test_lower_resolution_source_is_interpolated_smoothly(passes):
    out = _resolve(passes, (W // 2, H // 2), 0.0)
    red = out[H // 2, :, 0]
    assert (out[..., 3] == 1.0).all()
    assert np.isfinite(out).all() and (red >= -1e-6).all() and (red <= 2.0 + 1e-5).all()
    ramp = red[EDGE - 3: EDGE + 3]
    assert ((ramp > 0.05) & (ramp < 1.95)).sum() >= 2  # a soft ramp, not a step
    assert (np.diff(ramp) <= 1e-5).all()


@pytest.mark.parametrize("list_width", [4096, 3])
def test_a_subframe_takes_the_workers_light_at_its_own_point_on_a_light_edge(passes, monkeypatch, list_width):
    """`EdgeLight` of two subframes at the two pixels either side of the shadow edge: subframe 1
    shows its own traced light there (where the raster sees the point its ray met), every other
    pixel the resolve of the centre light; a ray that met nothing, a point off the traced one's
    plane, a normal bent away from the traced one, another pattern or a subframe the worker did
    not trace fall back to the resolve. The list read right where it
    wraps onto its next line too."""
    monkeypatch.setattr(passes, "EDGE_LIST_WIDTH", list_width)  # 3: the list wraps onto a second line
    row = 3
    pix = np.array([row * W + EDGE - 1, row * W + EDGE], np.int32)
    light = np.array([[[0.3] * 3, [0.4] * 3], [[0.7] * 3, [0.9] * 3]], np.float32)
    offsets = np.array([[0.25, 0.1], [-0.3, 0.2]], np.float32)
    # What each subframe's ray met there: the draw below rasterizes the pixel centres (shift 0),
    # so the points are those; the second subframe met nothing at the second pixel.
    centres = _plane(_proj(), W, H)[0].reshape(-1, 4)[pix, :3]
    point = np.stack([centres, centres]).astype(np.float32)
    normal = np.zeros((2, 2, 3), np.float32)
    normal[..., 2] = 1.0
    edges = passes.worker.EdgeLight(pix, light, point, normal, offsets)
    missed = passes.worker.EdgeLight(pix, light, point, normal * np.array([[[1.0], [1.0]], [[1.0], [0.0]]], np.float32),
                                     offsets)

    out = _resolve(passes, (W, H), 0.0, edges, offsets, index=1)
    np.testing.assert_allclose(out[row, EDGE - 1 : EDGE + 1, 0], [0.7, 0.9], atol=1e-5)
    others = np.ones((H, W), bool)
    others[row, EDGE - 1 : EDGE + 1] = False
    expected = np.where(np.arange(W) < EDGE, 2.0, 0.0)[None, :].repeat(H, 0)
    np.testing.assert_allclose(out[..., 0][others], expected[others], atol=1e-5)
    np.testing.assert_allclose(_resolve(passes, (W, H), 0.0, edges, offsets, index=0)[row, EDGE - 1, 0], 0.3,
                               atol=1e-5)
    # Where the subframe's ray met nothing: the resolve's light.
    np.testing.assert_allclose(_resolve(passes, (W, H), 0.0, missed, offsets, index=1)[row, EDGE - 1 : EDGE + 1, 0],
                               [0.7, 0.0], atol=1e-5)
    # Off the traced point's plane (lifted 0.2 at 5 m): not what the ray met, the resolve's light.
    lifted = _resolve(passes, (W, H), 0.0, edges, offsets, index=1, lift=0.2)
    assert lifted[row, EDGE - 1, 0] == pytest.approx(0.7, abs=1e-5)
    assert abs(lifted[row, EDGE, 0] - 0.9) > 0.5
    # A normal the raster bent (a normal map) 5 degrees off the traced one: the resolve's light.
    tilt = np.radians(5.0)
    bent = passes.worker.EdgeLight(pix, light, point, np.broadcast_to(
        np.array([np.sin(tilt), 0.0, np.cos(tilt)], np.float32), normal.shape).copy(), offsets)
    np.testing.assert_allclose(_resolve(passes, (W, H), 0.0, bent, offsets, index=1)[row, EDGE - 1 : EDGE + 1, 0],
                               [2.0, 0.0], atol=1e-5)
    # Another subframe pattern, or a subframe past the traced ones: the resolve alone.
    for other, index in ((offsets[::-1].copy(), 1), (offsets, 2)):
        plain = _resolve(passes, (W, H), 0.0, edges, other, index=index)
        np.testing.assert_allclose(plain[row, EDGE - 1 : EDGE + 1, 0], [2.0, 0.0], atol=1e-5)
