"""Environment maps split into a shadowed sun and a sky (hybridgi_core/environment.py): analytic
maps with a known sun, and the sky's radiance read back in every direction."""

import numpy as np
import pytest

from hybridgi_core.environment import equirect_directions, split_environment
from hybridgi_core.snapshot import World

H, W = 128, 256


SUN_RADIUS = np.radians(0.8)


def sky_with_sun(direction, sun_radiance=2000.0, sun_radius=SUN_RADIUS, sky=0.4):
    dirs, _solid = equirect_directions(H, W)
    d = np.asarray(direction, np.float64) / np.linalg.norm(direction)
    pixels = np.full((H, W, 3), sky, np.float64)
    disc = dirs @ d > np.cos(max(sun_radius, 1.5 * np.pi / H))  # at least a pixel or two
    pixels[disc] = sun_radiance
    return pixels, disc


def test_equirect_directions_cover_the_sphere_with_blender_conventions():
    dirs, solid = equirect_directions(H, W)
    assert np.allclose(np.linalg.norm(dirs, axis=-1), 1.0)
    assert solid.sum() * W == pytest.approx(4 * np.pi, rel=1e-3)
    assert dirs[0, W // 2, 2] < -0.99 and dirs[-1, W // 2, 2] > 0.99  # row 0 is the nadir
    middle = dirs[H // 2, W // 2 - 1: W // 2 + 1].mean(axis=0)
    assert middle[0] > 0.99  # the image centre faces +X
    quarter = dirs[H // 2, W // 4]
    assert quarter[1] > 0.99  # u = 0.25 faces +Y (u grows clockwise seen from above)


def test_a_sun_becomes_a_lamp_with_its_direction_and_irradiance():
    direction = np.array([0.3, -0.5, 0.6])
    pixels, disc = sky_with_sun(direction)
    split = split_environment(pixels)
    d = direction / np.linalg.norm(direction)
    assert np.degrees(np.arccos(np.clip(split.sun_direction @ d, -1, 1))) < 1.0
    dirs, solid = equirect_directions(H, W)
    weight = np.broadcast_to(solid[:, None], disc.shape)
    expected = 2000.0 * float((weight[disc] * np.clip(dirs[disc] @ d, 0, None)).sum())
    np.testing.assert_allclose(split.sun_irradiance, expected, rtol=0.02)
    np.testing.assert_allclose(split.sky, 0.4, rtol=0.01)  # the sun's pixels filled with the sky around
    world = World(color=split.sky, sky_sh=split.sky_sh)
    up_and_down = world.radiance(np.array([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]))
    np.testing.assert_allclose(up_and_down, 0.4, rtol=0.03)  # a uniform sky is uniform in SH too


def test_a_rotation_turns_the_sun_with_the_map():
    pixels, _ = sky_with_sun([1.0, 0.0, 0.3])
    quarter = np.array([[0, -1.0, 0], [1.0, 0, 0], [0, 0, 1.0]])  # +90 degrees about Z
    split = split_environment(pixels, to_world=quarter)
    expected = quarter @ (np.array([1.0, 0, 0.3]) / np.linalg.norm([1.0, 0, 0.3]))
    assert split.sun_direction @ expected > np.cos(np.radians(1.0))


def test_an_overcast_map_has_no_sun_and_keeps_its_gradient_in_the_sky():
    dirs, _ = equirect_directions(H, W)
    pixels = (0.2 + 0.8 * np.clip(dirs[..., 2], 0, None))[..., None].repeat(3, axis=-1)  # brighter overhead
    split = split_environment(pixels)
    assert split.sun_direction is None and not split.sun_irradiance.any()
    world = World(color=split.sky, sky_sh=split.sky_sh)
    zenith, horizon, nadir = world.radiance(np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, -1.0]]))[:, 0]
    assert zenith > horizon > 0.1 and nadir < horizon + 0.05
    # The uniform colour is what a surface facing up receives, / pi.
    up = np.clip(dirs[..., 2], 0, None) * np.cos(np.arcsin(dirs[..., 2]))
    np.testing.assert_allclose(split.sky[0], (pixels[..., 0] * up).sum() / up.sum(), rtol=1e-3)


def test_non_finite_pixels_do_not_reach_the_lamp_or_the_sky():
    pixels, _ = sky_with_sun([0, 0.5, 0.8])
    pixels[10, 20] = np.nan
    pixels[11, 20] = np.inf
    split = split_environment(pixels)
    assert np.isfinite(split.sun_irradiance).all() and np.isfinite(split.sky).all() and np.isfinite(split.sky_sh).all()
