"""Per-pixel final-gather rays (hybridgi_core/pixel_gather.py): analytic sky and AO, the control
variate's unbiasedness, determinism, the edge-aware filter, and one real-engine render against
Cycles at a contact."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hybridgi_core import pixel_gather
from hybridgi_core.errors import SettingsError
from hybridgi_core.raster.settings import RasterSettings
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Material, World, concat_geometry, geometry_from_arrays, make_snapshot
from hybridgi_core.system import GISystem

UP = np.array([0.0, 0.0, 1.0], np.float32)


def quad(corners, obj=0, material=0):
    return geometry_from_arrays(corners, [[0, 1, 2], [0, 2, 3]], material, obj)


def ground_and_wall(albedo=0.0):
    """A 200 m ground plane and a 5 m tall, 40 m long wall along x = 0 facing +x, under a uniform
    sky of radiance 1 (AO distance 1 m). With a black wall, a point at the wall's foot sees half
    of the cosine-weighted sky (E = pi / 2, AO = 1/2, to 0.1%); 80 m away it sees all of it (to
    0.03%: the wall rises 3.6 degrees over 28 degrees of azimuth there)."""
    ground = quad([[-100, -100, 0], [100, -100, 0], [100, 100, 0], [-100, 100, 0]])
    wall = quad([[0, -20, 0], [0, 20, 0], [0, 20, 5], [0, -20, 5]], obj=1, material=1)
    mats = [Material("ground", np.full(3, 0.5, np.float32)), Material("wall", np.full(3, albedo, np.float32))]
    return make_snapshot(concat_geometry([ground, wall]), mats, [], World(color=np.ones(3, np.float32), ao_distance=1.0))


def points_up(*xyz):
    p = np.array(xyz, np.float32).reshape(-1, 3)
    return p, np.tile(UP, (p.shape[0], 1))


@pytest.fixture(scope="module")
def wall_system():
    with GISystem(ground_and_wall(), CacheSettings(resolution=8, rays_per_cell=64)) as gi:
        gi.warm_up(8)
        yield gi


def test_open_sky_irradiance_is_pi_times_the_radiance(wall_system):
    """Far from the wall the pixel sees the whole sky: E_direct = pi L, nothing bounced, AO 1."""
    p, n = points_up([80.0, 5.0, 0.0], [90.0, -60.0, 0.0])
    g = pixel_gather.trace_pixels(wall_system, p, n, 256, frame=0)
    np.testing.assert_allclose(g.direct, np.pi, rtol=2e-3)
    np.testing.assert_allclose(g.indirect, 0.0, atol=2e-3)  # the control variate's own noise
    np.testing.assert_allclose(g.ao, 1.0, atol=1e-3)


def test_foot_of_a_black_wall_sees_half_the_sky_which_the_cache_alone_misses(wall_system):
    """At the wall's foot the pixel's own rays give the analytic half sky (pi / 2) and AO 1/2;
    the cache gather there reads cells a fraction of a cell away, which see more sky."""
    p, n = points_up([0.01, 0.0, 0.0], [0.01, 7.0, 0.0])
    vis = wall_system.corner_visibility(p, n)
    g = pixel_gather.trace_pixels(wall_system, p, n, 1024, frame=0, corner_visible=vis)
    np.testing.assert_allclose(g.direct, np.pi / 2, rtol=0.02)
    np.testing.assert_allclose(g.ao, 0.5, atol=0.02)
    # The cache alone is off by more than the rays' error.
    assert (np.abs(g.cache_direct[:, 0] - np.pi / 2) > 0.1).all(), g.cache_direct
    # AO grows away from the wall (beyond the AO distance it is open).
    p2, n2 = points_up([0.01, 0.0, 0.0], [0.3, 0.0, 0.0], [0.8, 0.0, 0.0], [80.0, 0.0, 0.0])
    ao = pixel_gather.trace_pixels(wall_system, p2, n2, 1024, frame=0).ao
    assert (np.diff(ao) > 0).all() and ao[-1] == pytest.approx(1.0), ao


def test_control_variate_is_unbiased_whatever_the_cache_holds(wall_system):
    """The estimate must not depend on the cache's values, only its noise does: a cache scaled
    by 3 gives the same mean over many rays (E_c cancels against its own ray sum)."""
    p, n = points_up([0.2, 1.0, 0.0], [1.5, -3.0, 0.0], [6.0, 2.0, 0.0])
    a = pixel_gather.trace_pixels(wall_system, p, n, 4096, frame=0)
    cache = wall_system.cache
    saved = cache.sh_direct.copy()
    try:
        cache.sh_direct *= 3.0
        b = pixel_gather.trace_pixels(wall_system, p, n, 4096, frame=0)
    finally:
        cache.sh_direct[:] = saved
    np.testing.assert_allclose(b.direct, a.direct, rtol=0.01)
    assert not np.allclose(b.cache_direct, a.cache_direct)


def test_wall_bounce_is_indirect_light_and_corner_is_darker_than_open():
    """A white wall reflects the sky onto its foot: indirect light appears there, none far away."""
    with GISystem(ground_and_wall(albedo=0.8), CacheSettings(resolution=8, rays_per_cell=64)) as gi:
        gi.warm_up(8)
        p, n = points_up([0.01, 0.0, 0.0], [80.0, 0.0, 0.0])
        g = pixel_gather.trace_pixels(gi, p, n, 512, frame=0)
    assert g.indirect[0, 0] > 0.3, g.indirect
    assert g.indirect[1, 0] < 0.05 * g.indirect[0, 0], g.indirect
    assert g.ao[0] < g.ao[1]


def test_deterministic_per_frame(wall_system):
    p, n = points_up([0.3, 0.0, 0.0], [2.0, 1.0, 0.0])
    a = pixel_gather.trace_pixels(wall_system, p, n, 8, frame=3)
    b = pixel_gather.trace_pixels(wall_system, p, n, 8, frame=3)
    c = pixel_gather.trace_pixels(wall_system, p, n, 8, frame=4)
    np.testing.assert_array_equal(a.direct, b.direct)
    np.testing.assert_array_equal(a.ao, b.ao)
    assert not np.array_equal(a.direct, c.direct)


def test_a_pixel_without_a_usable_normal_still_gets_finite_light(wall_system):
    p = np.array([[3.0, 0.0, 0.0], [4.0, 0.0, 0.0]], np.float32)
    n = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]], np.float32)
    g = pixel_gather.trace_pixels(wall_system, p, n, 16, frame=0)
    assert np.isfinite(g.direct).all() and np.isfinite(g.ao).all()
    np.testing.assert_allclose(g.direct[0], g.direct[1], rtol=0.2)


def test_cosine_directions_are_cosine_distributed_and_stratified():
    rng = np.random.default_rng(0)
    nrm = np.tile(np.array([[0.0, 0.6, 0.8]], np.float32), (2000, 1))
    d = pixel_gather.cosine_directions(nrm, 16, rng)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-5)
    cos = d @ nrm[0]
    assert cos.min() >= -1e-6
    # Cosine-distributed: E[cos] = 2/3, E[cos^2] = 1/2.
    assert cos.mean() == pytest.approx(2 / 3, abs=3e-3)
    assert (cos**2).mean() == pytest.approx(0.5, abs=3e-3)
    # Stratified: each pixel's 16 rays estimate E[cos] far better than 16 independent ones.
    assert cos.mean(axis=1).std() < 0.3 * np.sqrt((0.5 - 4 / 9) / 16)


def _plane_image(h=48, w=64):
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    pos = np.stack([xx * 0.02, yy * 0.02, np.zeros_like(xx)], -1)
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[..., 2] = 1.0
    return pos, nrm


def test_filter_removes_noise_on_a_plane_and_keeps_background_out():
    pos, nrm = _plane_image()
    valid = np.ones(pos.shape[:2], bool)
    valid[:, :8] = False
    rng = np.random.default_rng(1)
    res = rng.normal(size=pos.shape[:2] + (7,)).astype(np.float32)
    res[~valid] = 100.0  # must never leak in
    f = pixel_gather.filter_residual(res, pos, nrm, valid, np.array([0.6, 0.5, 3.0], np.float32), passes=3)
    assert np.abs(f[valid]).std() < 0.15
    assert np.abs(f[valid]).max() < 1.0
    assert (f[~valid] == 0).all()


def test_variance_guided_filter_keeps_a_contact_sharp_on_one_plane():
    """On one plane, a strong correction (a contact: -1 over a strip) among noise of standard
    deviation 0.05: with the pixels' variance the filter averages the noise but leaves the strip's
    edge where it was; without it the strip bleeds into its surroundings."""
    pos, nrm = _plane_image()
    h, w = pos.shape[:2]
    rng = np.random.default_rng(2)
    res = (0.05 * rng.normal(size=(h, w, 7))).astype(np.float32)
    strip = np.zeros((h, w), bool)
    strip[:, 30:34] = True
    res[strip] -= 1.0
    var = np.full((h, w, 2), 0.05**2, np.float32)
    valid = np.ones((h, w), bool)
    eye = np.array([0.6, 0.5, 3.0], np.float32)
    guided = pixel_gather.filter_residual(res, pos, nrm, valid, eye, variance=var)
    plain = pixel_gather.filter_residual(res, pos, nrm, valid, eye)
    assert np.abs(guided[strip] + 1.0).mean() < 0.05
    assert np.abs(plain[strip] + 1.0).mean() > 0.3
    outside = ~strip
    outside[:, 26:38] = False
    assert guided[outside].std() < 0.5 * res[outside].std()


def test_filter_keeps_a_correction_on_its_own_surface():
    """A contact's correction (-1 on the floor) must not spread onto the wall meeting it at a
    right angle, nor onto a parallel surface 20 cm in front."""
    pos, nrm = _plane_image()
    h, w = pos.shape[:2]
    wall = np.zeros((h, w), bool)
    wall[:, w // 2:] = True
    nrm[wall] = (1.0, 0.0, 0.0)
    front = np.zeros((h, w), bool)
    front[: h // 4, : w // 2] = True
    pos[front, 2] += 0.2
    res = np.zeros((h, w, 7), np.float32)
    floor = ~wall & ~front
    res[floor] = -1.0
    f = pixel_gather.filter_residual(res, pos, nrm, np.ones((h, w), bool), np.array([0.6, 0.5, 3.0], np.float32))
    np.testing.assert_allclose(f[floor], -1.0, atol=1e-4)
    assert np.abs(f[wall]).max() < 1e-3
    assert np.abs(f[front]).max() < 1e-3


def test_pixel_rays_setting_is_range_checked():
    assert RasterSettings().pixel_rays == 0
    with pytest.raises(SettingsError, match="pixel_rays"):
        RasterSettings(pixel_rays=-1)
    with pytest.raises(SettingsError, match="pixel_filter"):
        RasterSettings(pixel_filter=9)


def test_no_rays_is_the_cache_gather(wall_system):
    """rays = 0 returns the cache gather itself (the control variate's own value; unclamped, the
    gather clamps negative irradiance to 0)."""
    p, n = points_up([0.3, 0.0, 0.0], [2.0, 1.0, 0.0])
    g = pixel_gather.trace_pixels(wall_system, p, n, 0, frame=0)
    ref = wall_system.gather(p, n, exact=False)
    np.testing.assert_allclose(np.maximum(g.direct, 0), ref.direct, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(np.maximum(g.indirect, 0), ref.indirect, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(g.ao, ref.ao, atol=1e-5)


# --- through the real engine, against Cycles ----------------------------------------------------

CONTACT_SCENE = textwrap.dedent("""
    import sys, bpy
    from mathutils import Vector
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=10.0)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.5))
    bpy.ops.mesh.primitive_cube_add(size=0.5, location=(1.1, 0.6, 0.25))
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.location = (3.2, -3.2, 2.4)
    cam.rotation_euler = (Vector((0.4, 0.2, 0.3)) - cam.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(cam)
    scene.camera = cam
    world = bpy.data.worlds.new("sky")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.8, 0.9, 1.0, 1.0)
    world.light_settings.distance = 0.5
    scene.world = world
    bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
""")


@pytest.mark.blender
@pytest.mark.slow
def test_contacts_against_cycles_improve_with_pixel_rays(tmp_path):
    """Two cubes on a ground plane under a uniform sky. Where Cycles shows occlusion (its AO below
    0.75: the contacts and the ground between the cubes), the pixel rays' sky light (Diffuse
    Direct), AO and bounce (Diffuse Indirect) are closer to Cycles than the cache alone, and so is
    the whole image's Combined. Measured (cache alone -> 16 pixel rays): contact Diffuse Direct
    0.100 -> 0.055, AO 0.114 -> 0.088, Diffuse Indirect 0.143 -> 0.077; Combined over all
    geometry 0.045 -> 0.017."""
    from tests.cli_renders import layer, rendered  # noqa: PLC0415

    blend = tmp_path / "contact.blend"
    subprocess.run([sys.executable, "-c", CONTACT_SCENE, str(blend)], check=True, capture_output=True)
    res = "160x120"
    fast = ("--set", "resolution=16", "--set", "warmup_iterations=8", "--set", "downsample=2")
    cycles = rendered(blend, tmp_path / "cy", res, "--engine", "CYCLES", "--samples", "256")
    cache = rendered(blend, tmp_path / "c0", res, *fast, "--set", "pixel_rays=0")
    rays = rendered(blend, tmp_path / "c16", res, *fast, "--set", "pixel_rays=16")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    ref_ao = layer(cycles, "Ambient Occlusion", "R")[..., 0]
    contact = geometry & (ref_ao < 0.75)
    assert contact.sum() > 200

    def error(channels, name, components="RGB"):
        ours, ref = layer(channels, name, components), layer(cycles, name, components)
        return float(np.abs(ours - ref)[contact].sum() / np.abs(ref)[contact].sum())

    for name, comp, share in (("Diffuse Direct", "RGB", 0.7), ("Ambient Occlusion", "R", 0.9),
                              ("Diffuse Indirect", "RGB", 0.7)):
        before, after = error(cache, name, comp), error(rays, name, comp)
        assert after < share * before, (name, before, after)
    contact[:] = geometry
    before, after = error(cache, "Combined"), error(rays, "Combined")
    assert after < 0.6 * before, (before, after)
