"""Per-pixel final-gather rays (hybridgi_core/pixel_gather.py): analytic sky and AO, the control
variate's unbiasedness, determinism, the edge-aware filter, and one real-engine render against
Cycles at a contact."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
import textwrap
from pathlib import Path

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


def test_partly_occluded_pixels_trace_more_ao_rays_and_stay_unbiased(wall_system):
    """At the black wall's foot (AO 1/2, a noisy estimate relative to its value) the AO takes extra
    occlusion-only rays: its spread over frames shrinks against the same rays without them, its
    mean stays the analytic 1/2; open ground (AO 1, no noise) traces none."""
    p, n = points_up(*[[0.01, y, 0.0] for y in np.linspace(-5.0, 5.0, 64)])
    vis = wall_system.corner_visibility(p, n)
    with_more = np.array([pixel_gather.trace_pixels(wall_system, p, n, 32, frame=f, corner_visible=vis).ao
                          for f in range(8)])
    saved = pixel_gather.AO_EXTRA
    try:
        pixel_gather.AO_EXTRA = 0.0
        without = np.array([pixel_gather.trace_pixels(wall_system, p, n, 32, frame=f, corner_visible=vis).ao
                            for f in range(8)])
    finally:
        pixel_gather.AO_EXTRA = saved
    assert with_more.mean() == pytest.approx(0.5, abs=0.01)
    assert with_more.std() < 0.85 * without.std(), (with_more.std(), without.std())
    open_p, open_n = points_up([80.0, 5.0, 0.0])
    assert "ao_rays" not in pixel_gather.trace_pixels(wall_system, open_p, open_n, 32, frame=0).steps_ms


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


def test_split_work_items_give_the_same_pixels_on_any_thread_count():
    """`min_chunks` splits a few thousand pixels into items for every worker (the detail pixels'
    rays): the split is fixed by the pixel and ray counts, so one worker and two give the same
    bits; and it does split (another item draws other random numbers than one item would)."""
    rng = np.random.default_rng(5)
    p = np.column_stack([rng.uniform(0.2, 30.0, 1200), rng.uniform(-15, 15, 1200), np.zeros(1200)]).astype(np.float32)
    n = np.tile(UP, (p.shape[0], 1))
    out = []
    for threads in (1, 2):
        with GISystem(ground_and_wall(albedo=0.5), CacheSettings(resolution=8, rays_per_cell=32, threads=threads)) as gi:
            gi.warm_up(8)
            split = pixel_gather.trace_pixels(gi, p, n, 32, frame=2, min_chunks=pixel_gather.DETAIL_MIN_CHUNKS)
            whole = pixel_gather.trace_pixels(gi, p, n, 32, frame=2)
            out.append((split.indirect, split.ao, whole.indirect))
    np.testing.assert_array_equal(out[0][0], out[1][0])
    np.testing.assert_array_equal(out[0][1], out[1][1])
    assert not np.array_equal(out[0][0], out[0][2])


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


def test_an_indirect_guide_keeps_a_faint_bounce_beside_noisy_sky_light():
    """Sky light of ~3 with noise of standard deviation 0.3 (the direct channels) and a faint
    bounce (+0.2 over a strip, a post's foot on sunlit ground) on indirect light of 0.05 with noise
    0.02, on one plane. One guide for all light (luminance of direct + indirect, its variance
    dominated by the sky's) averages the strip away as noise; with the indirect light's own
    luminance and variance as a second guide it stays, and the sky's noise is still smoothed."""
    pos, nrm = _plane_image()
    h, w = pos.shape[:2]
    rng = np.random.default_rng(3)
    res = np.zeros((h, w, 7), np.float32)
    res[..., 0:3] = 3.0 + 0.3 * rng.normal(size=(h, w, 1))
    res[..., 3:6] = 0.05 + 0.02 * rng.normal(size=(h, w, 1))
    res[..., 6] = 1.0
    strip = np.zeros((h, w), bool)
    strip[:, 30:33] = True
    res[strip, 3:6] += 0.2
    valid = np.ones((h, w), bool)
    eye = np.array([0.6, 0.5, 3.0], np.float32)
    # Variances of the means as the rays give them: luminance of all light, of the direct, of the
    # indirect, of AO.
    d, i = 0.3**2, 0.02**2
    joint = np.stack([np.full((h, w), d + i), np.zeros((h, w))], -1).astype(np.float32)
    split = np.stack([np.full((h, w), d + i), np.full((h, w), i), np.zeros((h, w))], -1).astype(np.float32)
    one = pixel_gather.filter_residual(res, pos, nrm, valid, eye, variance=joint, noise_sigma=1.0)
    two = pixel_gather.filter_residual(res, pos, nrm, valid, eye, variance=split, noise_sigma=1.0)
    bump = {k: float(v[strip, 4].mean() - 0.05) for k, v in (("one", one), ("two", two))}
    # Measured: the strip keeps 0.20 of its 0.2 with both guides, 0.10 with one; the sky's noise
    # drops to 0.75 of its standard deviation (0.61 with one guide: a tap must agree in both).
    assert bump["two"] > 0.17, bump
    assert bump["one"] < 0.12, bump
    outside = ~strip
    outside[:, 26:37] = False
    assert two[outside, 0].std() < 0.8 * res[outside, 0].std()


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


def _grazing_ground(h=48, w=32, eye_height=1.7):
    """(positions (h, w, 3), normals, eye (3,)) of a ground plane z = 0 seen from eye_height at
    grazing angles: row i looks down by 1.5 + 0.1 i degrees (rows from ~65 m to ~16 m away, a
    row spanning 0.3-4 m of ground), columns 0.1 degree apart."""
    eye = np.array([0.0, 0.0, eye_height], np.float32)
    down = np.radians(1.5 + 0.1 * np.arange(h))[:, None]
    az = np.radians(0.1 * (np.arange(w) - w / 2))[None, :]
    d = np.stack(np.broadcast_arrays(np.cos(down) * np.cos(az), np.cos(down) * np.sin(az), -np.sin(down)), -1)
    pos = (eye + d * (eye_height / np.sin(down))[..., None]).astype(np.float32)
    nrm = np.zeros((h, w, 3), np.float32)
    nrm[..., 2] = 1.0
    return pos, nrm, eye


def test_stretch_keeps_light_from_spreading_along_a_grazing_ground():
    """On a ground seen at a grazing angle a pixel spans metres along the view: the same a-trous
    taps that average a few centimetres of a facing floor average light from tens of metres
    apart. A glow on the near ground (rows up to 25 m away, light 1; beyond, 0): without the
    stretch term the far rows next to it take much of it; with it they stay dark, the glow keeps
    its light, and a floor facing the camera is filtered as before."""
    pos, nrm, eye = _grazing_ground()
    h, w = pos.shape[:2]
    dist = np.linalg.norm(pos - eye, axis=-1)
    glow = dist < 25.0
    res = np.zeros((h, w, 7), np.float32)
    res[glow] = 1.0
    valid = np.ones((h, w), bool)
    plain = pixel_gather.filter_residual(res, pos, nrm, valid, eye, passes=3)
    kept = pixel_gather.filter_residual(res, pos, nrm, valid, eye, passes=3, stretch=pixel_gather.STRETCH)
    beyond = ~glow & (dist < 35.0)  # ground 0-10 m beyond the glow's edge, 11 rows
    # Measured: 0.167 of the glow's light on those rows without the term, 0.008 with it; the glow
    # keeps 0.998 of its light with it, 0.923 without.
    assert plain[beyond, 4].mean() > 0.12
    assert kept[beyond, 4].mean() < 0.03
    assert kept[glow, 4].mean() > 0.97
    # A floor facing the camera: taps lie as far as their screen step, the term leaves them be.
    flat, fn = _plane_image()
    rng = np.random.default_rng(4)
    noise = rng.normal(size=flat.shape[:2] + (7,)).astype(np.float32)
    top = np.array([0.6, 0.5, 3.0], np.float32)
    ones = np.ones(flat.shape[:2], bool)
    np.testing.assert_allclose(pixel_gather.filter_residual(noise, flat, fn, ones, top, stretch=pixel_gather.STRETCH),
                               pixel_gather.filter_residual(noise, flat, fn, ones, top), atol=0.02)


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


# --- resolving the GI per full-res pixel (full_res_images, upsample_full) ------------------------


def _plane_grid(w, h, factor, pick=(0, 0), normal=(0.0, 0.0, 1.0), step=0.01):
    """A full-res w x h grid of points on the plane z = 0 (pixel (x, y) at ((x + .5) step, (y + .5)
    step)), its factor-downsampled GI pixels taking the block's pixel `pick` (as the nearest-depth
    pick takes one corner on a slope): (full points, full pix, low positions (h_lo, w_lo, 3))."""
    xs, ys = np.meshgrid(np.arange(w), np.arange(h))
    pts = np.stack([(xs + 0.5) * step, (ys + 0.5) * step, np.zeros_like(xs, float)], -1).astype(np.float32)
    low = pts[pick[1]::factor, pick[0]::factor]
    return pts.reshape(-1, 3), np.arange(w * h), np.ascontiguousarray(low)


def test_sample_pixels_finds_the_downsample_pick():
    w, h, f = 12, 8, 2
    full, pix, low = _plane_grid(w, h, f, pick=(1, 0))
    xy = pixel_gather.sample_pixels(low, full, pix, w, h, f)
    lw = w // f
    grid = np.arange(lw * (h // f))
    np.testing.assert_array_equal(xy[:, 0], (grid % lw) * f + 1)
    np.testing.assert_array_equal(xy[:, 1], (grid // lw) * f)


def _upsample(full, pix, low, w, f, sh_lo=None, cache_lo=None, residual=None, normals=None, low_normals=None,
              rep_xy=None):
    hl, wl = low.shape[:2]
    k = 9
    sh_lo = np.zeros((hl * wl, k, 7), np.float32) if sh_lo is None else sh_lo
    cache_lo = np.zeros((hl * wl, 7), np.float32) if cache_lo is None else cache_lo
    residual = np.zeros((hl * wl, 7), np.float32) if residual is None else residual
    up = np.tile(UP, (full.shape[0], 1))
    normals = up if normals is None else normals
    low_normals = np.tile(UP, (hl, wl, 1)) if low_normals is None else low_normals
    camera = np.array([0.06, 0.04, 5.0], np.float32)
    return pixel_gather.upsample_full(sh_lo, cache_lo, residual, low, low_normals, np.ones((hl, wl), bool), full,
                                      normals, pix, w, f, camera, rep_xy=rep_xy)


def test_upsampling_a_linear_correction_is_unbiased_from_the_picked_pixels():
    """A correction linear in x, sampled at the pixel each block's nearest-depth pick took (here
    always the same corner, as on a slope): with the taps placed at those pixels the picked pixels
    get their own value back and the mean shift over the image is less than half of what placing
    them at the block centres gives (a half-pixel shift of the slope, the same way everywhere)."""
    w, h, f = 24, 16, 2
    full, pix, low = _plane_grid(w, h, f, pick=(1, 1))
    slope = 3.0
    residual = np.zeros((low.shape[0] * low.shape[1], 7), np.float32)
    residual[:, 3] = slope * low.reshape(-1, 3)[:, 0]
    xy = pixel_gather.sample_pixels(low, full, pix, w, h, f)
    inner = (full[:, 0] > 0.03) & (full[:, 0] < 0.2) & (full[:, 1] > 0.03) & (full[:, 1] < 0.12)
    exact = slope * full[:, 0]
    good = _upsample(full, pix, low, w, f, residual=residual, rep_xy=xy).residual[:, 3]
    shifted = _upsample(full, pix, low, w, f, residual=residual).residual[:, 3]
    shift = float((shifted - exact)[inner].mean())
    assert shift == pytest.approx(slope * 0.005, rel=0.1)  # half a pixel (step 0.01) of the slope
    picked = inner & (pix % w % f == 1) & (pix // w % f == 1)
    np.testing.assert_allclose(good[picked], exact[picked], atol=1e-5)
    assert abs(float((good - exact)[inner].mean())) < 0.5 * abs(shift)


def test_upsampling_on_a_grazing_ground_keeps_a_glow_on_its_rows():
    """The full-res interpolation's taps on a ground seen at a grazing angle lie metres apart
    along the view: a glow (residual 1 on the ground nearer than 25 m, 0 beyond) keeps its light
    on its last rows only with the stretch term (`pixel_gather.STRETCH`), which weighs the farther
    GI pixels' taps down as the filter does."""
    pos, _, eye = _grazing_ground()
    h, w = pos.shape[:2]
    f = 2
    full, pix = pos.reshape(-1, 3), np.arange(h * w)
    low = np.ascontiguousarray(pos[0::f, 0::f])
    hl, wl = low.shape[:2]
    residual = np.zeros((hl * wl, 7), np.float32)
    residual[np.linalg.norm(low - eye, axis=-1).reshape(-1) < 25.0, 3] = 1.0
    args = (np.zeros((hl * wl, 9, 7), np.float32), np.zeros((hl * wl, 7), np.float32), residual, low,
            np.tile(UP, (hl, wl, 1)), np.ones((hl, wl), bool), full, np.tile(UP, (h * w, 1)), pix, w, f, eye)
    dist = np.linalg.norm(full - eye, axis=1)
    edge = (dist >= 20.0) & (dist < 25.0)  # the glow's last rows (10 of them)
    # Measured: 0.9997 of the glow's light there with the term, 0.944 without.
    assert pixel_gather.upsample_full(*args).residual[edge, 3].mean() > 0.99
    assert pixel_gather.upsample_full(*args, stretch=None).residual[edge, 3].mean() < 0.96


def test_upsampling_evaluates_the_cache_at_each_pixels_own_normal():
    """The taps' cache SH (a directional radiance lobe) is evaluated at every full-res pixel's own
    normal: on a curved surface each pixel gets sh.irradiance(SH, its normal), which the plain
    interpolation of the taps' irradiance (at their normals) does not."""
    from hybridgi_core import sh  # noqa: PLC0415

    w, h, f = 12, 8, 2
    full, pix, low = _plane_grid(w, h, f)
    hl, wl = low.shape[:2]
    rng = np.random.default_rng(3)
    # Normals that turn by up to ~15 degrees from pixel to pixel (a bevel), all within the taps' reach.
    tilt = rng.uniform(-0.25, 0.25, (full.shape[0], 2)).astype(np.float32)
    normals = np.concatenate([tilt, np.ones((full.shape[0], 1), np.float32)], 1)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    low_normals = normals.reshape(h, w, 3)[0::f, 0::f]
    one = np.zeros((9, 7), np.float32)
    one[:, 3] = sh.basis(np.array([[0.6, 0.0, 0.8]], np.float32), 2)[0] * 4.0  # a lobe towards +x+z
    sh_lo = np.tile(one, (hl * wl, 1, 1))
    cache_lo = sh.irradiance(sh_lo, low_normals.reshape(-1, 3))
    up = _upsample(full, pix, low, w, f, sh_lo=sh_lo, cache_lo=cache_lo, normals=normals, low_normals=low_normals)
    own = sh.irradiance(sh_lo[:1].repeat(full.shape[0], 0), normals)[:, 3]
    np.testing.assert_allclose(up.cache[:, 3], own, rtol=1e-4)
    interp = np.abs(up.cache[:, 3] - own).max()
    assert interp < 1e-3 * own.max()
    plain = _upsample(full, pix, low, w, f, cache_lo=cache_lo, normals=np.tile(UP, (full.shape[0], 1)),
                      low_normals=np.tile(UP, (hl, wl, 1))).cache[:, 3]
    assert np.abs(plain - own).max() > 0.05 * own.max()  # the irradiance interpolation misses it


def test_a_pixel_on_a_surface_no_gi_pixel_sampled_is_an_orphan():
    w, h, f = 12, 8, 2
    full, pix, low = _plane_grid(w, h, f)
    normals = np.tile(UP, (full.shape[0], 1))
    normals[40] = (1.0, 0.0, 0.0)  # a post's side among floor pixels
    full = full.copy()
    full[41, 2] = 0.5  # a rail half a metre above the floor, facing up
    up = _upsample(full, pix, low, w, f, normals=normals)
    assert up.best[40] == 0.0 and up.best[41] < 1e-6
    others = np.delete(np.arange(full.shape[0]), [40, 41])
    assert (up.best[others] > 0.5).all()
    np.testing.assert_allclose(up.cover[others], 1.0, atol=1e-5)  # every tap on their surface
    assert not up.turned[others].any()


def test_cover_drops_next_to_a_step_and_turned_marks_a_bend():
    """GI pixels of the right half lie on a step 0.5 m up: floor pixels next to it keep only part
    of their spatial tap weight (cover < 1, refinement candidates), floor pixels away from it all;
    a pixel whose normal is turned from its taps' is `turned`."""
    w, h, f = 16, 8, 2
    full, pix, low = _plane_grid(w, h, f)
    low = low.copy()
    low[:, low.shape[1] // 2:, 2] = 0.5
    normals = np.tile(UP, (full.shape[0], 1))
    normals[3] = (0.0, 0.6, 0.8)
    up = _upsample(full, pix, low, w, f, normals=normals)
    x = pix % w
    assert (up.cover[(x == 6) | (x == 7)] < 0.85).all()
    np.testing.assert_allclose(up.cover[(x <= 3) & (pix != 3)], 1.0, atol=1e-5)
    assert up.turned[3] and not np.delete(up.turned, 3)[(np.delete(x, 3) <= 3)].any()


def _patch_full_res(wall_system, wall: int | None = None, w: int = 8, h: int = 8, f: int = 2):
    """A w x h patch of the ground-and-wall scene's open ground, 5 cm pixels seen from 5 m above,
    GI pixels every `f` (one of them never the `wall` pixel, which lies on the wall's face), through
    `full_res_images`: (full-res points, normals, its result)."""
    xs, ys = np.meshgrid(np.arange(w), np.arange(h))
    full = np.stack([40.0 + xs * 0.05, ys * 0.05, np.zeros_like(xs, float)], -1).astype(np.float32).reshape(-1, 3)
    normals = np.tile(UP, (full.shape[0], 1))
    if wall is not None:
        full[wall] = (0.01, 0.0, 1.0)
        normals[wall] = (1.0, 0.0, 0.0)
    low_full = full.reshape(h, w, 3)[0::f, 0::f]
    hl, wl = low_full.shape[:2]
    position_lo = np.concatenate([low_full, np.ones((hl, wl, 1), np.float32)], -1)
    normal_lo = np.concatenate([np.tile(UP, (hl, wl, 1)), np.ones((hl, wl, 1), np.float32)], -1)
    points, lo_normals = low_full.reshape(-1, 3), np.tile(UP, (hl * wl, 1))
    view = np.eye(4, dtype=np.float32)
    view[:3, 3] = (-40.2, -0.2, -5.0)  # the camera 5 m above the patch
    vis = wall_system.corner_visibility(points, lo_normals)
    out = pixel_gather.full_res_images(wall_system, position_lo, normal_lo, np.arange(hl * wl), points, lo_normals,
                                       vis, view, 0, 256, full, normals, np.arange(w * h), (w, h))
    return full, normals, out


def test_full_res_images_trace_own_rays_on_thin_geometry(wall_system):
    """Through `full_res_images` on the ground-and-wall scene: GI pixels on the open ground, one
    full-res pixel on the wall's face among them (narrower than a GI pixel). The ground pixels get
    the open sky (pi); the wall pixel gets its own rays' estimate, half the sky (a vertical wall
    facing +x sees the sky above and the ground below), not the ground's pi."""
    w = 8
    wall = 3 * w + 3
    _, _, out = _patch_full_res(wall_system, wall, w=w)
    direct = out.direct.reshape(-1, 4)[:, 0]
    assert out.detail >= 1
    np.testing.assert_allclose(np.delete(direct, wall), np.pi, rtol=0.01)
    assert direct[wall] == pytest.approx(np.pi / 2, rel=0.1), direct[wall]


def test_the_preview_is_the_resolve_without_its_detail_pixels(wall_system):
    """`full_res_preview` (what the viewport's draw resolves on the GPU while its worker resolves
    the same rays) is `full_res_resolve` without the detail pixels' own rays: bit for bit where
    none traced; the wall pixel no GI pixel stands for reads the ground taps' cache at its own
    normal (about half the sky, as its own rays find) instead of nothing."""
    w = h = 8
    wall = 3 * w + 3
    full, normals, _ = _patch_full_res(wall_system, wall, w=w)
    low_full = full.reshape(h, w, 3)[0::2, 0::2]
    hl, wl = low_full.shape[:2]
    position_lo = np.concatenate([low_full, np.ones((hl, wl, 1), np.float32)], -1)
    points, lo_normals = low_full.reshape(-1, 3), np.tile(UP, (hl * wl, 1))
    pix = np.arange(hl * wl)
    view = np.eye(4, dtype=np.float32)
    view[:3, 3] = (-40.2, -0.2, -5.0)
    gi = pixel_gather.trace_pixels(wall_system, points, lo_normals, 64, 0,
                                   wall_system.corner_visibility(points, lo_normals))
    args = (position_lo, pix, points, lo_normals, view)
    full_args = (full, normals, np.arange(w * h), (w, h))
    preview = pixel_gather.full_res_preview(gi, *args, *full_args)
    none = pixel_gather.full_res_resolve(wall_system, dataclasses.replace(gi), *args, 0, 0, *full_args)
    traced = pixel_gather.full_res_resolve(wall_system, dataclasses.replace(gi), *args, 0, 256, *full_args)
    assert none.detail == traced.detail >= 1  # the same pixels are picked; only traced ones get rays
    rest = np.ones(w * h, bool)
    rest[wall] = False
    for a, b in ((preview[0], none.indirect), (preview[1], none.direct)):
        np.testing.assert_array_equal(a.reshape(-1, 4)[rest], b.reshape(-1, 4)[rest])
    changed = np.flatnonzero(np.any(preview[1].reshape(-1, 4) != traced.direct.reshape(-1, 4), axis=1))
    assert wall in changed and changed.size <= traced.detail
    assert none.direct.reshape(-1, 4)[wall, 0] == 0.0  # no tap shares its surface: nothing to interpolate
    # (The low-order SH of the open ground's radiance read sideways: 1.84, nearer half the sky
    # than the ground's pi.)
    assert 0.8 * np.pi / 2 < preview[1].reshape(-1, 4)[wall, 0] < 0.65 * np.pi
    assert traced.direct.reshape(-1, 4)[wall, 0] == pytest.approx(np.pi / 2, rel=0.1)


def test_a_subframe_sample_on_a_surface_the_centre_missed_gets_its_own_light(wall_system):
    """A jittered subframe (`subpixel.subframe_gi`) over the open ground of
    `test_full_res_images_trace_own_rays_on_thin_geometry`, the centre raster seeing only ground:
    where the subframe sees the ground too it keeps the centre's resolved GI; the pixel where it
    sees the wall's face (a bar between pixel centres) gets that face's light, half the sky, not
    the ground's pi that the centre's GI upsampled onto it gave before (Cycles' film weights each
    sample's light by its own colour, so an edge pixel needs each surface's own)."""
    from hybridgi_core.raster.subpixel import CentreSample, subframe_gi, subframe_surfaces  # noqa: PLC0415

    w = h = 8
    full, normals, out = _patch_full_res(wall_system, w=w, h=h)
    assert out.detail == 0  # the centre raster saw nothing but ground
    centre_pos = np.concatenate([full, np.ones((w * h, 1), np.float32)], 1)
    centre = CentreSample(np.zeros((w * h, 4), np.float32), centre_pos, normals, np.full(w * h, 5.0, np.float32))
    offset = (0.3, -0.2)
    sub_pos = centre_pos.copy()
    sub_pos[:, 0] += 0.05 * offset[0]
    sub_pos[:, 1] += 0.05 * offset[1]
    sub_nrm = normals.copy()
    wall = 3 * w + 3
    sub_pos[wall, :3] = (0.01, 0.0, 1.0)
    sub_nrm[wall] = (1.0, 0.0, 0.0)
    hit, same = subframe_surfaces(centre, sub_pos.reshape(h, w, 4), sub_nrm.reshape(h, w, 3))
    assert hit.all() and np.flatnonzero(~same).tolist() == [wall]
    indirect, direct, traced = subframe_gi(out.resolver, out.indirect, out.direct, hit, same,
                                           sub_pos.reshape(h, w, 4), sub_nrm.reshape(h, w, 3), offset, 5, 256)
    assert traced == 256
    centre_direct = out.direct.reshape(-1, 4)
    np.testing.assert_array_equal(np.delete(direct, wall, axis=0), np.delete(centre_direct, wall, axis=0))
    np.testing.assert_array_equal(np.delete(indirect, wall, axis=0),
                                  np.delete(out.indirect.reshape(-1, 4), wall, axis=0))
    assert centre_direct[wall, 0] == pytest.approx(np.pi, rel=0.01)  # what the subframe reused before
    assert direct[wall, 0] == pytest.approx(np.pi / 2, rel=0.1), direct[wall]
    # A pixel whose subframe sample sees no geometry takes the background's (no light, AO 1).
    hit[0] = False
    indirect, direct, _ = subframe_gi(out.resolver, out.indirect, out.direct, hit, same & hit,
                                      sub_pos.reshape(h, w, 4), sub_nrm.reshape(h, w, 3), offset, 5, 256)
    np.testing.assert_array_equal(indirect[0], (0.0, 0.0, 0.0, 1.0))
    np.testing.assert_array_equal(direct[0], 0.0)


@pytest.mark.blender
@pytest.mark.slow
def test_full_res_gi_against_cycles_on_the_car(tmp_path):
    """The bundled car (rounded red body on a floor under a sun and sky) at downsample 2: with the
    GI resolved per full-res pixel (Full-Res GI) the Diffuse Indirect is closer to Cycles than with
    the bilateral upsampling of GI-resolution light, on the body (whose bevels turn the normal
    within a GI pixel) and over the image; Combined too. Measured at 200x150 against Cycles 256 spp
    (upsampled -> full-res): body 0.174 -> 0.094, image 0.179 -> 0.128, Combined 0.0081 -> 0.0071."""
    from tests.cli_renders import layer, rendered  # noqa: PLC0415

    root = Path(__file__).resolve().parent.parent
    subprocess.run([sys.executable, str(root / "blend_scenes" / "build.py"), "--only", "car", "--out", str(tmp_path)],
                   check=True, capture_output=True)
    blend = tmp_path / "car.blend"
    res = "200x150"
    fast = ("--set", "downsample=2", "--set", "pixel_rays=32")
    cycles = rendered(blend, tmp_path / "cy", res, "--engine", "CYCLES", "--samples", "256")
    old = rendered(blend, tmp_path / "up", res, *fast, "--set", "pixel_full_res=0")
    new = rendered(blend, tmp_path / "full", res, *fast, "--set", "pixel_full_res=1")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    body = geometry & (layer(cycles, "Diffuse Color")[..., 0] > 0.5) & (layer(cycles, "Diffuse Color")[..., 1] < 0.2)
    assert body.sum() > 300

    def error(channels, mask, name="Diffuse Indirect"):
        ours, ref = layer(channels, name), layer(cycles, name)
        return float(np.abs(ours - ref)[mask].sum() / np.abs(ref)[mask].sum())

    for mask, name, share in ((body, "Diffuse Indirect", 0.75), (geometry, "Diffuse Indirect", 0.85),
                              (geometry, "Combined", 0.95)):
        before, after = error(old, mask, name), error(new, mask, name)
        assert after < share * before, (name, before, after)


def _trench(albedo=0.8, half=0.15, depth=0.3):
    """A 40 m ground with a trench 0.3 m wide and 0.3 m deep along y under a uniform sky of radiance 1,
    every surface of `albedo`: clutter-scale geometry (a crevice) far finer than the 5 m cells of
    resolution 8, where most of the floor's light has bounced between the walls more than once."""
    a, z = half, -depth
    q = [quad([[-20, -20, 0], [-a, -20, 0], [-a, 20, 0], [-20, 20, 0]]),
         quad([[a, -20, 0], [20, -20, 0], [20, 20, 0], [a, 20, 0]]),
         quad([[-a, -20, z], [-a, 20, z], [-a, 20, 0], [-a, -20, 0]]),  # wall facing +x
         quad([[a, -20, 0], [a, 20, 0], [a, 20, z], [a, -20, z]]),  # wall facing -x
         quad([[-a, -20, z], [a, -20, z], [a, 20, z], [-a, 20, z]])]  # floor
    mats = [Material("stone", np.full(3, albedo, np.float32))]
    return make_snapshot(concat_geometry(q), mats, [], World(color=np.ones(3, np.float32), ao_distance=1.0))


def _path_traced_irradiance(gi, points, normals, paths, bounces, rng):
    """Brute-force reference: irradiance at points (n, 3) from `paths` cosine paths each, every hit
    reflecting its albedo, up to `bounces` bounces (uniform sky of radiance 1, no lamps)."""
    eps = np.float32(gi.tracer.epsilon)
    n = points.shape[0]
    o = np.repeat(points + normals * eps, paths, axis=0)
    d = pixel_gather.cosine_directions(normals, paths, rng).reshape(-1, 3)
    weight = np.ones(o.shape[0], np.float32)
    total = np.zeros(o.shape[0], np.float32)
    alive = np.arange(o.shape[0])
    for _ in range(bounces):
        hits = gi.tracer.intersect(o, d, np.float32(np.inf), trusted=True)
        miss = hits.prim < 0
        total[alive[miss]] += weight[miss]
        keep = ~miss
        if not keep.any():
            break
        surf = gi.updater.scene.surfaces.probe_hits(hits.prim[keep], hits.u[keep], hits.v[keep], d[keep])
        p = o[keep] + d[keep] * hits.t[keep][:, None]
        alive, weight = alive[keep], weight[keep] * surf.brdf[:, 0] * np.float32(np.pi)
        o = p + surf.normal * eps
        d = pixel_gather.cosine_directions(surf.normal, 1, rng).reshape(-1, 3)
    return np.float32(np.pi) * total.reshape(n, paths).mean(axis=1)


def test_pixel_rays_bounce_light_in_a_crevice_finer_than_a_cell():
    """Issue #12: a pixel ray hitting the trench's wall read its further bounces from the cell in
    front of the hit, which lies above the trench (5 m cells, a 0.3 m slot) and sees the open sky:
    the floor's light came out 13.0% too bright against a path-traced reference. Hits nearer than
    NEAR_BOUNCE_CELLS trace one ray of their own instead: +8.4% (the second hit still reads the
    cell above; deeper slots keep more of the error)."""
    with GISystem(_trench(), CacheSettings(resolution=8, rays_per_cell=64)) as gi:
        gi.warm_up(8)
        p, n = points_up(*[[0.0, y, -0.3] for y in np.linspace(-3.0, 3.0, 16)])
        g = pixel_gather.trace_pixels(gi, p, n, 256, frame=0)
        ours = float((g.direct + g.indirect).mean())
        ref = float(_path_traced_irradiance(gi, p, n, 4096, 40, np.random.default_rng(5)).mean())
    assert abs(ours / ref - 1.0) < 0.10, (ours, ref)


def _path_traced(system, points, normals, bounces, rays, rng):
    """(n, 3) irradiance at points from emission reaching them over up to `bounces` diffuse
    bounces: a plain path tracer on the system's own ray mesh and hit shading (no cache)."""
    def radiance(p, n, depth, k):
        d = pixel_gather.cosine_directions(n, k, rng).reshape(-1, 3)
        o = np.repeat(p + n * np.float32(system.tracer.epsilon), k, axis=0)
        hits = system.tracer.intersect(o, d, np.float32(np.inf), trusted=True)
        out = np.zeros((o.shape[0], 3), np.float32)
        hit = np.flatnonzero(hits.prim >= 0)
        if hit.size:
            surf = system.updater.scene.surfaces.probe_hits(hits.prim[hit], hits.u[hit], hits.v[hit], d[hit])
            out[hit] = surf.emission
            if depth > 0:
                at = o[hit] + d[hit] * hits.t[hit][:, None]
                out[hit] += np.float32(np.pi) * surf.brdf * radiance(at, surf.normal, depth - 1, 1)
        return out.reshape(p.shape[0], k, 3).mean(axis=1)
    return np.float32(np.pi) * radiance(points, normals, bounces, rays)


def _glowing_ball_on_floor():
    """A glowing ball (radius 0.25 m, emission 4) resting on an 8 m grey floor, in the dark."""
    from blend_scenes.procedural import _placement, transformed, uv_sphere

    ball = transformed(uv_sphere(0.25, 48, 24), _placement((0.0, 0.0, 0.25)))
    ball = geometry_from_arrays(ball.positions, ball.triangles, 1, 1)
    floor = quad([[-4, -4, 0], [4, -4, 0], [4, 4, 0], [-4, 4, 0]])
    mats = [Material("floor", np.full(3, 0.7, np.float32)),
            Material("glow", np.full(3, 0.8, np.float32), emission=np.full(3, 4.0, np.float32))]
    return make_snapshot(concat_geometry([floor, ball]), mats, [], World(color=np.zeros(3, np.float32)))


def test_light_between_an_emitter_and_the_floor_it_touches_is_not_lost():
    """A glowing ball on a floor: light goes back and forth between them near the contact, each
    round about half the last, where the cache's cells (coarser than the contact) hold a third
    of it. The pixel rays' near bounces follow it (NEAR_BOUNCE_DEPTH) as a path tracer does:
    at depth 2 the indirect light 2-5 cm from the contact was 45% short."""
    scene = _glowing_ball_on_floor()
    with GISystem(scene, CacheSettings(resolution=48, rays_per_cell=32)) as gi:
        gi.warm_up(6)
        p, n = points_up([0.0, -0.02, 0.0], [0.0, -0.05, 0.0])
        truth = _path_traced(gi, p, n, 8, 20000, np.random.default_rng(1))
        emitted = _path_traced(gi, p, n, 0, 20000, np.random.default_rng(2))
        got = pixel_gather.trace_pixels(gi, p, n, 4096, frame=0)
    bounced = (truth - emitted).mean(axis=1)
    assert (bounced > 0.5 * emitted.mean(axis=1)).all()  # the case: bounces are most of the light
    np.testing.assert_allclose(got.direct.mean(axis=1), emitted.mean(axis=1), rtol=0.03)
    np.testing.assert_allclose(got.indirect.mean(axis=1), bounced, rtol=0.12)


def test_deep_near_bounces_go_on_by_roulette_without_losing_light(monkeypatch):
    """Past NEAR_BOUNCE_DEPTH near bounces (the glowing ball's contact) half the near hits trace
    one more and scale their difference to the cache up (`_near_roulette`): the contact's light
    is the full chain's within its noise, for far fewer deep rays."""
    scene = _glowing_ball_on_floor()
    deep = []
    near_bounce = pixel_gather._near_bounce

    def counted(system, lookup, position, *args):
        if args[-1] >= pixel_gather.NEAR_BOUNCE_DEPTH:  # level
            deep.append(position.shape[0])
        return near_bounce(system, lookup, position, *args)

    monkeypatch.setattr(pixel_gather, "_near_bounce", counted)
    with GISystem(scene, CacheSettings(resolution=48, rays_per_cell=32)) as gi:
        gi.warm_up(6)
        p, n = points_up([0.0, -0.02, 0.0], [0.0, -0.05, 0.0], [0.0, -0.1, 0.0])
        got, rays = {}, {}
        for survival in (1.0, pixel_gather.NEAR_SURVIVAL):
            monkeypatch.setattr(pixel_gather, "NEAR_SURVIVAL", survival)
            deep.clear()
            got[survival] = pixel_gather.trace_pixels(gi, p, n, 8192, frame=0).indirect.mean(axis=1)
            rays[survival] = sum(deep)
    assert pixel_gather.NEAR_SURVIVAL < 1.0
    np.testing.assert_allclose(got[pixel_gather.NEAR_SURVIVAL], got[1.0], rtol=0.05)
    assert rays[pixel_gather.NEAR_SURVIVAL] < 0.5 * rays[1.0], rays


def _ground_points(gi, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) points on the ground of `ground_and_wall` facing up, its cache warmed up first."""
    gi.warm_up(2)
    rng = np.random.default_rng(seed)
    points = np.zeros((n, 3), np.float32)
    points[:, 0] = rng.uniform(0.5, 5.0, n)
    points[:, 1] = rng.uniform(-10.0, 10.0, n)
    return points, np.tile(UP, (n, 1))


def test_trace_pixels_skips_the_work_items_after_a_stop():
    """`trace_pixels(stop=)` polls stop before each work item's rays are traced and again before a
    traced item is shaded: once it holds, what has not begun is skipped (zeros), whichever pool
    thread takes it; without a stop every item is traced and shaded, the same as before."""
    with GISystem(ground_and_wall(albedo=0.5), CacheSettings(resolution=8, rays_per_cell=16, threads=2)) as gi:
        points, normals = _ground_points(gi, 400, seed=3)
        polls = []

        def stop():
            polls.append(1)
            return len(polls) > 9  # the 8 items' rays and the first shading(s) run, the rest stop

        whole = pixel_gather.trace_pixels(gi, points, normals, 16, 1, chunk_rays=16 * 50)
        part = pixel_gather.trace_pixels(gi, points, normals, 16, 1, chunk_rays=16 * 50, stop=stop)
    assert len(polls) == 16  # 400 pixels, 50 an item: 8 before tracing, 8 before shading
    shaded = np.any(part.direct != 0, axis=1) | np.any(part.indirect != 0, axis=1)
    # The first item shaded, a second at most (two pool threads may poll in either order).
    assert shaded.sum() in (50, 100)
    np.testing.assert_array_equal(part.direct[shaded], whole.direct[shaded])
    np.testing.assert_array_equal(part.sh[shaded], whole.sh[shaded])
    assert np.all(whole.sh.any(axis=(1, 2)))


def test_pixel_rays_traced_ahead_and_shaded_later_are_the_same_rays(monkeypatch):
    """`begin_pixels` (the work items' cache gather and traced rays, trickled to the pool one at a
    time while the frame's lamp light runs) then `finish_pixels` (their shading) give bit for bit
    what one `trace_pixels` call gives; an error in a traced item reaches `finish_pixels`."""
    with GISystem(ground_and_wall(albedo=0.5), CacheSettings(resolution=8, rays_per_cell=16, threads=2)) as gi:
        points, normals = _ground_points(gi, 300, seed=4)
        whole = pixel_gather.trace_pixels(gi, points, normals, 16, 5, chunk_rays=16 * 40)
        for trickle in (False, True):
            begun = pixel_gather.begin_pixels(gi, points, normals, 16, 5, chunk_rays=16 * 40, trickle=trickle)
            assert len(begun.jobs) == 8
            later = pixel_gather.finish_pixels(begun)
            for name in ("direct", "indirect", "ao", "cache_direct", "sh", "variance"):
                np.testing.assert_array_equal(getattr(later, name), getattr(whole, name), err_msg=name)

        calls = []

        def failing(*args):
            calls.append(1)
            if len(calls) == 3:
                raise RuntimeError("a traced item failed")
            return real(*args)

        real = pixel_gather._chunk_trace
        monkeypatch.setattr(pixel_gather, "_chunk_trace", failing)
        begun = pixel_gather.begin_pixels(gi, points, normals, 16, 5, chunk_rays=16 * 40, trickle=True)
        with pytest.raises(RuntimeError, match="a traced item failed"):
            pixel_gather.finish_pixels(begun)


def test_a_kept_pass_shades_again_under_new_light_without_tracing_its_rays(monkeypatch):
    """`reshade_pixels` shades a finished pass's traced rays (`BegunPixels.traced`) over another
    system of the same geometry: under a sky twice as bright (its cache warmed up alike) every
    pixel's light is twice the re-shade's under the first sky, to float rounding (the same hits,
    the same random numbers: the light is linear in the sky), and the AO is the same. Over the
    first system the sky it sees is the pass's to the bit (its misses are that pass's; a pass of
    other directions sees another), and it traces none of the pass's rays again."""
    scene = ground_and_wall(albedo=0.5)
    brighter = dataclasses.replace(scene, world=World(color=np.full(3, 2.0, np.float32), ao_distance=1.0))
    settings = CacheSettings(resolution=8, rays_per_cell=16, threads=2)
    with GISystem(scene, settings) as gi, GISystem(brighter, settings) as gi2:
        for system in (gi, gi2):
            system.warm_up(4)
        points, normals = _ground_points(gi, 300, seed=4)
        rays = []
        for system in (gi, gi2):
            intersect = system.tracer.intersect
            monkeypatch.setattr(system.tracer, "intersect",
                                lambda o, *a, _f=intersect, **k: rays.append(len(o)) or _f(o, *a, **k))
        begun = pixel_gather.begin_pixels(gi, points, normals, 16, 5, chunk_rays=16 * 40)
        traced = pixel_gather.finish_pixels(begun)
        assert begun.traced
        begun.slim()  # as the viewport keeps them: the origins are made again
        pass_rays, rays[:] = sum(rays), []
        again = pixel_gather.reshade_pixels(begun, gi, 7)
        reshade_rays = sum(rays)
        twice = pixel_gather.reshade_pixels(begun, gi2, 7)
        other = pixel_gather.trace_pixels(gi, points, normals, 16, 6, chunk_rays=16 * 40)
    # The pass's own rays (16 a point) are not traced again: its hits' near bounces and AO rays are.
    assert again.rays == 0 and reshade_rays < pass_rays - 0.75 * traced.rays
    assert traced.direct.mean() > 0.5  # lit: the comparisons are not of zeros
    for name in ("direct", "indirect", "cache_direct", "cache_indirect"):
        np.testing.assert_allclose(getattr(twice, name), 2.0 * getattr(again, name), rtol=1e-3, atol=1e-4,
                                   err_msg=name)
    np.testing.assert_allclose(twice.ao, again.ao, atol=1e-6)
    # The sky each point sees through its rays is the pass's: its misses, not other directions'.
    np.testing.assert_array_equal(again.direct, traced.direct)
    assert np.abs(other.direct - traced.direct).mean() > 0.05


def test_a_cache_side_made_once_serves_the_carry_and_the_reshade():
    """`cache_side` is the cache's part of `trace_pixels` without rays, to the bit (what a lamp
    edit's carry reads), and a re-shade that takes it gives, to the bit, what one that gathers
    the cache itself gives; the shading does not write into it."""
    with GISystem(ground_and_wall(albedo=0.5), CacheSettings(resolution=8, rays_per_cell=16, threads=2)) as gi:
        points, normals = _ground_points(gi, 300, seed=4)
        normals[7] = 0.0  # a pixel without a usable normal is mended alike
        begun = pixel_gather.begin_pixels(gi, points, normals, 16, 5, chunk_rays=16 * 40)
        pixel_gather.finish_pixels(begun)
        begun.slim()
        side = pixel_gather.cache_side(gi, points, normals, chunk=128)
        before = {k: v.copy() for k, v in side.items() if isinstance(v, np.ndarray)}
        np.testing.assert_array_equal(side["res"][:, 9:16],
                                      pixel_gather.trace_pixels(gi, points, normals, 0, 0).channels()[1])
        own = pixel_gather.reshade_pixels(begun, gi, 7)
        shared = pixel_gather.reshade_pixels(begun, gi, 7, side=side)
    for name in ("direct", "indirect", "ao", "cache_direct", "cache_indirect", "cache_ao", "sh", "variance"):
        np.testing.assert_array_equal(getattr(shared, name), getattr(own, name), err_msg=name)
    for key, value in before.items():
        np.testing.assert_array_equal(side[key], value, err_msg=key)
