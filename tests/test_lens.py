"""The thin lens of depth of field (`hybridgi_core/raster/lens.py`): analytic checks, no Blender."""

import math

import numpy as np
import pytest

from hybridgi_core.raster.lens import (
    MIN_SUBFRAMES,
    Lens,
    centre_offsets,
    coc_pixels,
    concentric_disk,
    focus_offset,
    lens_points,
    lens_view,
    regular_polygon,
    subframes_for,
)
from hybridgi_core.raster.subpixel import jittered_projection

W, H = 64, 48


def _perspective(fov_deg=50.0, near=0.1, far=100.0):
    """Blender-like (OpenGL) perspective projection, camera looking down -z."""
    fx = 1.0 / math.tan(math.radians(fov_deg) / 2.0)
    fy = fx * W / H
    p = np.zeros((4, 4))
    p[0, 0], p[1, 1] = fx, fy
    p[2, 2], p[2, 3] = -(far + near) / (far - near), -2.0 * far * near / (far - near)
    p[3, 2] = -1.0
    return p


def _camera_view(eye=(0.3, -5.0, 1.2)):
    """A view (world to camera) of a camera at `eye`, axes turned so that it looks along +y."""
    rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # world -> camera axes
    view = np.eye(4)
    view[:3, :3] = rot
    view[:3, 3] = -rot @ np.asarray(eye)
    return view


def _pixel(view, proj, point):
    clip = proj @ view @ np.append(point, 1.0)
    ndc = clip[:2] / clip[3]
    return (ndc * 0.5 + 0.5) * np.array([W, H])


def test_lens_points_fill_the_aperture_uniformly():
    lens = Lens(radius=0.2, focus=4.0)
    pts = lens_points(64, lens)
    r = np.linalg.norm(pts, axis=1)
    assert r.max() <= 0.2 + 1e-12
    # Uniform over the disk: the mean is the centre and half the points lie inside r / sqrt(2).
    np.testing.assert_allclose(pts.mean(axis=0), 0.0, atol=0.02)
    assert abs((r < 0.2 / math.sqrt(2.0)).mean() - 0.5) < 0.1
    # The anamorphic ratio narrows x (Cycles divides the lens point's x by it).
    wide = lens_points(64, Lens(radius=0.2, focus=4.0, ratio=2.0))
    np.testing.assert_allclose(wide[:, 0], pts[:, 0] / 2.0)
    np.testing.assert_allclose(wide[:, 1], pts[:, 1])


def test_disk_and_polygon_maps_stay_inside_their_shapes():
    rng = np.random.default_rng(3)
    u, v = rng.random(4000), rng.random(4000)
    disk = concentric_disk(u, v)
    assert np.linalg.norm(disk, axis=1).max() <= 1.0 + 1e-12
    tri = regular_polygon(u, v, 3, 0.3)
    # Inside the triangle inscribed in the unit circle: each edge's inner distance is <= cos(60 deg).
    for k in range(3):
        mid = 0.3 + (k + 0.5) * 2.0 * math.pi / 3.0
        assert (tri @ np.array([math.cos(mid), math.sin(mid)])).max() <= 0.5 + 1e-9
    # Uniform: the triangle's centroid is the circle's centre.
    np.testing.assert_allclose(tri.mean(axis=0), 0.0, atol=0.03)


def test_the_plane_of_focus_keeps_its_pixels_from_every_lens_point():
    view, proj = _camera_view(), _perspective()
    lens = Lens(radius=0.3, focus=5.0)
    eye = np.linalg.inv(view)[:3, 3]
    axis = -np.linalg.inv(view)[:3, 2]  # the camera looks along -z of its frame
    right, up = np.linalg.inv(view)[:3, 0], np.linalg.inv(view)[:3, 1]
    on_plane = eye + axis * 5.0 + 0.7 * right - 0.4 * up
    nearer = eye + axis * 2.5 + 0.2 * right
    centre_focus, centre_near = _pixel(view, proj, on_plane), _pixel(view, proj, nearer)
    for point in lens_points(8, lens):
        moved = jittered_projection(proj, focus_offset(proj, point, lens, W, H), W, H).astype(np.float64)
        sub = lens_view(view, point).astype(np.float64)
        np.testing.assert_allclose(_pixel(sub, moved, on_plane), centre_focus, atol=1e-3)
        # Off the plane a point moves by its circle of confusion: the lens point's offset times
        # (1 / depth - 1 / focus) in focal-length units, as Cycles' thin lens gives.
        expected = -np.array([proj[0, 0] * W / 2.0, proj[1, 1] * H / 2.0]) * point * (1.0 / 2.5 - 1.0 / 5.0)
        np.testing.assert_allclose(_pixel(sub, moved, nearer) - centre_near, expected, atol=1e-3)


def test_centre_offsets_find_where_the_pinhole_image_shows_a_point():
    view, proj = _camera_view(), _perspective()
    rng = np.random.default_rng(5)
    eye = np.linalg.inv(view)[:3, 3]
    pts = eye + np.array([0.0, 1.0, 0.0]) * rng.uniform(2.0, 8.0, (50, 1)) + rng.uniform(-1.0, 1.0, (50, 3)) * [1, 0, 0.6]
    px = np.array([_pixel(view, proj, p) for p in pts])
    pix = (np.floor(px[:, 1]).astype(int) * W + np.floor(px[:, 0]).astype(int))
    dx, dy = centre_offsets(pts, pix, W, H, view, proj)
    # Pixel centre (i + 0.5) plus the offset is the projected point.
    np.testing.assert_allclose(pix % W + 0.5 + dx, px[:, 0], atol=1e-4)
    np.testing.assert_allclose(pix // W + 0.5 + dy, px[:, 1], atol=1e-4)
    assert np.abs(dx).max() < 1.0 and np.abs(dy).max() < 1.0


def test_a_lens_must_be_finite_and_positive():
    with pytest.raises(ValueError):
        Lens(radius=0.1, focus=0.0)
    with pytest.raises(ValueError):
        Lens(radius=float("nan"), focus=1.0)
    assert not Lens(radius=0.0, focus=1.0).active


def test_a_lens_that_blurs_nothing_visibly_keeps_the_frames_subframes():
    """The circle of confusion (pixels) of the nearest and farthest surfaces decides: under a
    pixel, the frame keeps its own subframes (a weak depth of field does not pay for 16)."""
    proj = _perspective()
    strong = Lens(radius=0.35, focus=6.7)
    depth = np.array([3.0, 6.7, 9.0, 1.0e10])  # the background's depth is left out
    coc = coc_pixels(strong, proj, depth, W)
    np.testing.assert_allclose(coc, 0.35 * (1 / 3.0 - 1 / 6.7) * proj[0, 0] * W / 2, rtol=1e-9)
    assert subframes_for(strong, 8, coc) == MIN_SUBFRAMES and subframes_for(strong, 32, coc) == 32
    weak = Lens(radius=0.001, focus=6.7)
    assert coc_pixels(weak, proj, depth, W) < 1.0
    assert subframes_for(weak, 8, coc_pixels(weak, proj, depth, W)) == 8
    assert subframes_for(None, 8, 100.0) == 8
    assert coc_pixels(strong, proj, np.array([1.0e10]), W) == 0.0  # nothing but the background
