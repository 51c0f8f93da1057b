"""The sky's light at pixels by the ratio estimator (`sky_ratio`): the unshadowed irradiance table
against direct integration, the estimator's limits, and pixel rays on an open ground and under
an overhang against converged integrals (bpy-free)."""

from __future__ import annotations

import numpy as np

from hybridgi_core import pixel_gather
from hybridgi_core.environment import SkyMap, equirect_directions
from hybridgi_core.settings import CacheSettings
from hybridgi_core.sky_ratio import OPEN_FULL, OPEN_NONE, SkyIrradiance, open_share, open_sky_estimate, sky_irradiance
from hybridgi_core.snapshot import Material, World, concat_geometry, geometry_from_arrays, make_snapshot
from hybridgi_core.system import GISystem


def _field(d):
    """A bright horizon band, an azimuthal gradient and a darker ground: what L2 SH cannot hold."""
    up = np.clip(d[..., 2], -1.0, 1.0)
    return np.stack([0.3 + 4.0 * np.exp(-(up / 0.1) ** 2) + 0.8 * (up > 0), 0.5 + 0.5 * d[..., 0] + 0.3 * (up > 0),
                     0.4 + 0.2 * d[..., 1]], -1)


def _sky(rows=64, to_world=None):
    dirs, _ = equirect_directions(rows, 2 * rows)
    return SkyMap(_field(dirs).astype(np.float32), to_world)


def _integral(sky, normal, n=400_000, seed=1):
    """Monte Carlo of the integral of L max(0, n . w) dw over the sphere (uniform directions)."""
    d = np.random.default_rng(seed).normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    cos = np.maximum(d @ normal, 0.0)
    return (sky.radiance(d.astype(np.float32)) * cos[:, None]).mean(axis=0) * 4.0 * np.pi


def test_the_table_is_the_cosine_integral_of_the_map():
    rot = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    for sky in (_sky(), _sky(to_world=rot)):
        table = SkyIrradiance(sky)
        normals = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0.6, 0.8], [0.3, -0.9, 0.3], [0, 0, -1.0]])
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        got = table.irradiance(normals.astype(np.float32))
        want = np.array([_integral(sky, n) for n in normals])
        np.testing.assert_allclose(got, want, rtol=0.02)


def test_a_world_keeps_one_table_and_a_uniform_sky_has_none():
    sky = _sky()
    world = World(color=np.ones(3, np.float32), sky_sh=np.zeros((9, 3), np.float32), sky_map=sky)
    assert sky_irradiance(world) is sky_irradiance(world)
    assert sky_irradiance(World(color=np.ones(3, np.float32))) is None


def test_the_open_estimate_is_exact_in_the_open_and_the_blend_follows_the_cache():
    rng = np.random.default_rng(0)
    unshadowed = rng.random((3, 3)).astype(np.float32) + 1.0
    sky = rng.random((3 * 8, 3)).astype(np.float32) + 0.1
    escaped = np.ones(24, bool)
    escaped[8:16] = False  # the second pixel sees no sky
    escaped[16:20] = False  # the third half of it
    est, terms = open_sky_estimate(unshadowed, sky, escaped, 8)
    np.testing.assert_allclose(est[0], unshadowed[0], rtol=1e-6)
    np.testing.assert_allclose(est[1], unshadowed[1] - np.pi * sky[8:16].mean(0), rtol=1e-5)
    np.testing.assert_allclose(est[2], unshadowed[2] - np.pi * sky[16:20].sum(0) / 8, rtol=1e-5)
    assert np.allclose(terms[0], 0.0) and terms.shape == (3, 8) and (terms[1] < 0).all()
    mid = 0.5 * (OPEN_FULL + OPEN_NONE)
    share = open_share(np.array([[1.0, 1, 1], [mid, mid, mid], [0.2, 0.2, 0.2]]), np.ones((3, 3)))
    np.testing.assert_allclose(share, [1.0, 0.5, 0.0], atol=1e-6)


def _ground(roof: bool):
    """A 20 m ground and, with `roof`, over its right half a roof 1 m above it (a covered walk)."""
    ground = geometry_from_arrays([[-10, -10, 0], [10, -10, 0], [10, 10, 0], [-10, 10, 0]], [[0, 1, 2], [0, 2, 3]])
    if not roof:
        return ground
    top = geometry_from_arrays([[2, -10, 1], [10, -10, 1], [10, 10, 1], [2, 10, 1]], [[0, 2, 1], [0, 3, 2]])
    return concat_geometry([ground, top])


def _direct(rays, frame, points, sky, roof=True):
    world = World(color=np.ones(3, np.float32), sky_sh=np.zeros((9, 3), np.float32), sky_map=sky)
    snap = make_snapshot(_ground(roof), [Material(base_color=np.full(3, 0.5, np.float32))], [], world)
    with GISystem(snap, CacheSettings(resolution=8, rays_per_cell=32)) as gi:
        gi.warm_up(1)
        normals = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (points.shape[0], 1))
        out = pixel_gather.trace_pixels(gi, points, normals, rays, frame)
        return out.direct


def test_pixel_rays_read_the_open_sky_without_noise_and_stay_unbiased_under_a_roof():
    sky = _sky()
    xs = np.linspace(-8.0, -2.0, 40, dtype=np.float32)
    open_pts = np.stack([xs, np.zeros_like(xs), np.zeros_like(xs)], axis=1)
    covered = open_pts + np.array([9.0, 0.0, 0.0], np.float32)  # under the roof, 1-7 m from its edge
    exact = _integral(sky, np.array([0.0, 0.0, 1.0]))
    got = _direct(16, 0, open_pts, sky, roof=False)
    # In the open: the exact unshadowed integral at every pixel (the table's 2% aside), no noise.
    np.testing.assert_allclose(got, np.broadcast_to(exact, got.shape), rtol=0.025)
    assert got.std(axis=0).max() < 1e-4 * exact.max()
    # Under the roof: the mean over frames of 16-ray estimates is the 1024-ray one (within three
    # standard errors of that mean, measured over the frames).
    frames = np.array([_direct(16, f, covered[-8:], sky).mean(axis=0) for f in range(24)])
    many = _direct(1024, 99, covered[-8:], sky)
    assert (many.max(axis=1) < 0.7 * exact.max()).all()  # the roof blocks part of the sky
    error = np.abs(frames.mean(axis=0) - many.mean(axis=0))
    assert (error < 3.0 * frames.std(axis=0) / np.sqrt(len(frames)) + 0.01 * many.mean(axis=0)).all(), error


def test_the_sky_is_read_where_the_open_estimate_or_an_escaped_ray_needs_it():
    """`pixel_gather._sky_along`: two pixels of 4 rays, the first open (its cache's direct light is
    the unshadowed sky's), the second under a roof (a tenth of it). The open pixel's rays all read
    the map, blocked or not; the roofed pixel's only where they escape (0 elsewhere: the open
    estimate weighs that pixel by 0)."""
    from types import SimpleNamespace

    sky = _sky()
    world = World(color=np.full(3, 0.5, np.float32), sky_map=sky, sky_sh=np.zeros((9, 3), np.float32))
    table = sky_irradiance(world)
    nrm = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (2, 1))
    unshadowed = table.irradiance(nrm)
    cache_direct = np.stack([unshadowed[0], 0.1 * unshadowed[1]])
    d = np.random.default_rng(2).normal(size=(8, 3)).astype(np.float32)
    d[:, 2] = np.abs(d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    prim = np.array([5, -1, 5, 5, 5, -1, 5, 5])  # rays 1 and 5 escape
    share = open_share(cache_direct, unshadowed)
    assert share[0] == 1.0 and share[1] == 0.0
    got = pixel_gather._sky_along(world, d, SimpleNamespace(prim=prim), share, 4)
    full = sky.radiance(d)
    np.testing.assert_array_equal(got[:4], full[:4])
    np.testing.assert_array_equal(got[5], full[5])
    assert not got[[4, 6, 7]].any()
