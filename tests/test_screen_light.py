"""Lamp light at ray hits read from the frame's direct-light buffer (`screen_light`): hits on a
surface the camera shows take that pixel's light, anything else (occluders, back faces, off
screen, behind the eye) traces its own shadow rays, and the pixel rays' result does not change
beyond their noise."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import pixel_gather
from hybridgi_core.screen_light import ScreenLight
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Light, Material, World, concat_geometry, geometry_from_arrays, make_snapshot
from hybridgi_core.system import GISystem

UP = np.array([0.0, 0.0, 1.0], np.float32)
W, H = 64, 48


def perspective(fov_y: float, aspect: float, near: float = 0.1, far: float = 100.0) -> np.ndarray:
    f = 1.0 / np.tan(fov_y / 2)
    return np.array([[f / aspect, 0, 0, 0], [0, f, 0, 0],
                     [0, 0, (far + near) / (near - far), 2 * far * near / (near - far)], [0, 0, -1, 0]])


def look_down(height: float) -> np.ndarray:
    """View matrix of an eye at (0, 0, height) looking down -Z (image up = +Y)."""
    view = np.eye(4)
    view[2, 3] = -height
    return view


def ground_screen(height=10.0, fov_degrees=60.0):
    """The G-buffer of the ground z = 0 under the eye, every pixel's centre intersected
    analytically, with irradiance x + 10 (any function of the position)."""
    proj = perspective(np.radians(fov_degrees), W / H)
    ys, xs = np.mgrid[0:H, 0:W]
    ndc_x, ndc_y = (xs + 0.5) / W * 2 - 1, (ys + 0.5) / H * 2 - 1
    # The ray through a pixel centre: direction (ndc_x / P00, ndc_y / P11, -1) from the eye.
    px, py = ndc_x / proj[0, 0] * height, ndc_y / proj[1, 1] * height
    points = np.stack([px, py, np.zeros_like(px)], -1).reshape(-1, 3).astype(np.float32)
    normals = np.tile(UP, (points.shape[0], 1))
    light = np.repeat(points[:, :1] + 10.0, 3, axis=1).astype(np.float32)
    pix = np.arange(W * H)
    return ScreenLight.from_pixels(look_down(height), proj, (W, H), points, normals, pix, light), points


def test_hits_on_the_shown_surface_read_their_pixels_light():
    screen, centres = ground_screen()
    rng = np.random.default_rng(1)
    extent = np.abs(centres[:, :2]).max(axis=0) * 0.95
    q = np.zeros((500, 3), np.float32)
    q[:, :2] = rng.uniform(-extent, extent, (500, 2))
    found, light = screen.lookup(q, np.tile(UP, (500, 1)))
    assert found.size == 500
    # The pixel's light is the light at its centre: within a footprint (2 * 10 * tan 30 / 48 m).
    foot = 2 * 10 * np.tan(np.radians(30.0)) / H
    np.testing.assert_allclose(light[:, 0], q[found, 0] + 10.0, atol=0.75 * foot)


def test_occluders_back_faces_and_unseen_points_trace_their_own():
    screen, _ = ground_screen()
    q = np.array([[0.5, 0.5, 1.0],     # 1 m above the ground: an occluder the pixel does not show
                  [0.5, 0.5, 0.0],     # on the ground, but facing down (the ground's underside)
                  [50.0, 0.0, 0.0],    # on the ground, outside the frame
                  [0.0, 0.0, 20.0],    # behind the eye
                  [0.5, 0.5, 0.0]], np.float32)
    n = np.tile(UP, (5, 1))
    n[1] = -UP
    found, light = screen.lookup(q, n)
    assert found.tolist() == [4]
    assert light.shape == (1, 3)


def test_pixels_without_geometry_are_not_read():
    screen, centres = ground_screen()
    screen.valid[:] = False
    found, _ = screen.lookup(centres[:10], np.tile(UP, (10, 1)))
    assert found.size == 0


@pytest.fixture(scope="module")
def sunlit_corner():
    """A grey ground and a white wall along x = 0 under a sun (no sky): the pixel rays' indirect
    light at the wall's foot is the lamp light their hits reflect."""
    def quad(corners, obj, material):
        return geometry_from_arrays(corners, [[0, 1, 2], [0, 2, 3]], material, obj)
    ground = quad([[-20, -20, 0], [20, -20, 0], [20, 20, 0], [-20, 20, 0]], 0, 0)
    wall = quad([[0, -20, 0], [0, 20, 0], [0, 20, 5], [0, -20, 5]], 1, 1)
    mats = [Material("ground", np.full(3, 0.5, np.float32)), Material("wall", np.full(3, 0.8, np.float32))]
    tilt = np.radians(40.0)  # the sun from +x, 40 degrees off the zenith: lights ground and wall
    c, s = np.cos(tilt), np.sin(tilt)
    sun = Light("SUN", np.ones(3, np.float32), 3.0, np.array([[c, 0, s, 0], [0, 1, 0, 0], [-s, 0, c, 0], [0, 0, 0, 1.0]]))
    snap = make_snapshot(concat_geometry([ground, wall]), mats, [sun], World(color=np.zeros(3, np.float32)))
    with GISystem(snap, CacheSettings(resolution=8, rays_per_cell=64)) as gi:
        gi.warm_up(4)
        yield gi


def _camera_screen(gi, scale=1.0):
    """The frame's direct light as the renderer computes it, seen from an eye at (6, 0, 3)
    looking at the corner, optionally scaled (a wrong buffer, to show that it is read)."""
    eye = np.array([6.0, 0.0, 3.0])
    fwd = -eye / np.linalg.norm(eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    view = np.eye(4)
    view[:3, :3] = np.stack([right, up, -fwd])
    view[:3, 3] = -view[:3, :3] @ eye
    proj = perspective(np.radians(70.0), W / H)
    ys, xs = np.mgrid[0:H, 0:W]
    d_cam = np.stack([((xs + 0.5) / W * 2 - 1) / proj[0, 0], ((ys + 0.5) / H * 2 - 1) / proj[1, 1],
                      -np.ones((H, W))], -1).reshape(-1, 3)
    dirs = (d_cam @ view[:3, :3]).astype(np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    hits = gi.tracer.intersect(np.repeat(eye[None].astype(np.float32), dirs.shape[0], 0), dirs, np.float32(1e3))
    pix = np.flatnonzero(hits.prim >= 0)
    points = (eye + dirs[pix] * hits.t[pix, None]).astype(np.float32)
    normals = np.where((np.abs(points[:, 0]) < 1e-3)[:, None], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]).astype(np.float32)
    light = gi.direct(points, normals, 0, samples=16) * np.float32(scale)
    return ScreenLight.from_pixels(view, proj, (W, H), points, normals, pix, light)


def test_pixel_rays_with_the_screens_light_match_their_own_shadow_rays(sunlit_corner):
    gi = sunlit_corner
    p = np.array([[0.05, y, 0.0] for y in np.linspace(-1.0, 1.0, 16)], np.float32)
    n = np.tile(UP, (p.shape[0], 1))
    own = pixel_gather.trace_pixels(gi, p, n, 512, frame=0)
    read = pixel_gather.trace_pixels(gi, p, n, 512, frame=0, screen=_camera_screen(gi))
    wrong = pixel_gather.trace_pixels(gi, p, n, 512, frame=0, screen=_camera_screen(gi, scale=2.0))
    assert own.indirect.mean() > 0.5  # the sunlit wall bounces onto its foot
    assert read.indirect.mean() == pytest.approx(own.indirect.mean(), rel=0.03)
    # The wrong buffer is read: most hits (on the wall the camera sees) double their light.
    assert wrong.indirect.mean() > 1.5 * own.indirect.mean()


def test_reflection_rays_with_the_screens_light_match_their_own_shadow_rays(sunlit_corner):
    """Glossy reflection rays (`reflection.traced_reflection`) read the lamp light of the hits the
    image shows from the frame's buffer too: the floor beside the wall, seen from the camera's
    side, reflects the sunlit wall as with the hits' own shadow rays, and a wrong buffer shows."""
    from hybridgi_core.evaluate import HitLookup
    from hybridgi_core.reflection import traced_reflection

    gi = sunlit_corner
    p = np.array([[0.3, y, 0.0] for y in np.linspace(-1.0, 1.0, 16)], np.float32)
    n = np.tile(UP, (p.shape[0], 1))
    to_eye = np.array([6.0, 0.0, 3.0], np.float32) - p
    to_eye /= np.linalg.norm(to_eye, axis=1, keepdims=True)
    rough = np.full(p.shape[0], 0.5)
    lookup = HitLookup(gi.cache, bounced=True)
    own, read, wrong = (traced_reflection(gi, lookup, p, n, to_eye, rough, 256, 0, screen=screen)[1]
                        for screen in (None, _camera_screen(gi), _camera_screen(gi, scale=2.0)))
    assert own.mean() > 0.1  # the sunlit wall in the floor's lobe
    assert read.mean() == pytest.approx(own.mean(), rel=0.03)
    assert wrong.mean() > 1.5 * own.mean()
