"""The sky map rays read (environment.SkyMap): Blender's equirectangular layout, bilinear, with a
Mapping node's rotation, and what split_environment hands it."""

from __future__ import annotations

import numpy as np

from hybridgi_core.environment import SkyMap, downsample_equirect, equirect_directions, split_environment
from hybridgi_core.snapshot import World


def _field(d):
    """A smooth radiance with a bright horizon band and an azimuthal gradient (L2 cannot hold it)."""
    return np.stack([1.0 + 4.0 * np.exp(-(d[..., 2] / 0.08) ** 2), 0.5 + 0.5 * d[..., 0], 0.2 + 0 * d[..., 1]], -1)


def _random_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)


def test_map_reads_back_its_function_in_world_directions():
    dirs, _ = equirect_directions(128, 256)
    sky = SkyMap(_field(dirs).astype(np.float32))
    d = _random_dirs(5000)
    got, want = sky.radiance(d), _field(d.astype(np.float64))
    assert np.abs(got - want).mean() < 0.01 * np.abs(want).mean()


def test_rotated_map_reads_through_the_mapping():
    # to_world rotates texture directions by 90 degrees about Z: world +Y is texture +X.
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    dirs, _ = equirect_directions(128, 256)
    sky = SkyMap(_field(dirs).astype(np.float32), to_world=rot)
    d = _random_dirs(3000, 1)
    want = _field((d @ rot).astype(np.float64))  # texture direction = R^T world
    assert np.abs(sky.radiance(d) - want).mean() < 0.01 * np.abs(want).mean()


def test_downsampled_map_keeps_the_mean_radiance():
    dirs, solid = equirect_directions(512, 1024)
    f = _field(dirs)
    small = downsample_equirect(f, solid, 64)
    assert small.shape == (64, 128, 3)
    d2, s2 = equirect_directions(64, 128)
    big_mean = (f * solid[:, None, None]).sum(axis=(0, 1)) / (solid.sum() * 1024)
    small_mean = (small * s2[:, None, None]).sum(axis=(0, 1)) / (s2.sum() * 128)
    np.testing.assert_allclose(small_mean, big_mean, rtol=2e-3)


def test_split_sky_map_is_the_map_without_its_sun_and_worlds_read_it():
    h, w = 256, 512
    dirs, _ = equirect_directions(h, w)
    pixels = _field(dirs)
    sun = np.array([0.5, 0.2, 0.6]) / np.linalg.norm([0.5, 0.2, 0.6])
    disc = dirs @ sun > np.cos(np.radians(1.5))
    pixels[disc] = 5000.0
    split = split_environment(pixels)
    assert split.sun_direction is not None and split.sky_map is not None
    assert split.sky_map.max() < 100.0  # the sun is the lamp's now, not the map's
    world = World(color=split.sky, sky_sh=split.sky_sh, sky_map=SkyMap(split.sky_map, split.to_world))
    d = _random_dirs(4000, 2)
    d = d[d @ sun < 0.9]
    want = _field(d.astype(np.float64))
    err_map = np.abs(world.radiance(d) - want).mean()
    err_sh = np.abs(World(color=split.sky, sky_sh=split.sky_sh).radiance(d) - want).mean()
    assert err_map < 0.03 * np.abs(want).mean() and err_map < 0.5 * err_sh
