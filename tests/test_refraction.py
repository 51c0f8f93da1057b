"""hybridgi_core/refraction.py: the camera's refraction paths through smooth glass."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import refraction
from hybridgi_core.levels import hit_lookup
from tests.cli_renders import STAGE_HELPERS


def test_snell_and_total_internal_reflection():
    d = np.array([[np.sin(0.5), 0.0, -np.cos(0.5)]])
    n = np.array([[0.0, 0.0, 1.0]])
    out, tir = refraction._refract(d, n, np.array([1.0 / 1.5]))
    assert not tir[0]
    np.testing.assert_allclose(np.hypot(out[0, 0], out[0, 1]), np.sin(0.5) / 1.5, rtol=1e-12)  # sin t = sin i / n
    assert out[0, 2] < 0  # on through the surface
    # From inside, beyond the critical angle (asin(1 / 1.5) = 41.8 degrees): mirrored.
    d = np.array([[np.sin(0.8), 0.0, -np.cos(0.8)]])
    out, tir = refraction._refract(d, n, np.array([1.5]))
    assert tir[0]
    np.testing.assert_allclose(out[0], [np.sin(0.8), 0.0, np.cos(0.8)], atol=1e-12)


def test_camera_rays_pass_through_their_pixels():
    from tests.test_screen_light import perspective

    eye, target = np.array([1.0, -4.0, 2.0]), np.array([0.0, 0.0, 0.5])
    back = (eye - target) / np.linalg.norm(eye - target)
    right = np.cross([0.0, 0.0, 1.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    view = np.eye(4)
    view[:3, :3] = np.stack([right, up, back])
    view[:3, 3] = -view[:3, :3] @ eye
    proj = perspective(0.8, 16 / 9, 0.1, 100.0)
    origins, dirs = refraction.camera_rays(view, proj, 16, 9, (0.5, 0.5))
    clip = np.concatenate([origins + 3.0 * dirs, np.ones((origins.shape[0], 1), np.float32)], axis=1) @ (proj @ view).T
    ndc = clip[:, :2] / clip[:, 3:4]
    x, y = np.meshgrid((np.arange(16) + 0.5) / 16 * 2 - 1, (np.arange(9) + 0.5) / 9 * 2 - 1)
    np.testing.assert_allclose(ndc, np.stack([x.ravel(), y.ravel()], axis=1), atol=1e-4)


def glass_ball_system(tint=None, ior=1.5, world=0.7, background=None, tint_reflection=False):
    """A GISystem of a smooth glass ball of radius 0.5 at the origin under a uniform world (seen
    by the camera as `background`'s uniform environment image where given)."""
    from blend_scenes.procedural import uv_sphere
    from hybridgi_core.environment import BackgroundMap
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.snapshot import Material, World, geometry_from_arrays, make_snapshot
    from hybridgi_core.system import GISystem

    ball = uv_sphere(0.5, 96, 48)
    geometry = geometry_from_arrays(ball.positions, ball.triangles, 0, 0, normals=ball.normals)
    glass = Material("glass", np.zeros(3, np.float32), clear=True, refractive=True, ior=ior, tint=tint,
                     tint_reflection=tint_reflection)
    seen = None if background is None else BackgroundMap(np.full((8, 16, 3), background, np.float16))
    scene = make_snapshot(geometry, [glass], [], World(color=np.full(3, world, np.float32), background_map=seen))
    return GISystem(scene, CacheSettings(resolution=8, rays_per_cell=8))


def rays_at_ball(count=64):
    """Rays from z = 3 straight down onto the ball, over its disc and beyond its edge."""
    x = np.linspace(-0.6, 0.6, count)
    origins = np.stack([x, np.zeros_like(x), np.full_like(x, 3.0)], axis=1).astype(np.float32)
    dirs = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (count, 1))
    return x, origins, dirs


@pytest.mark.parametrize("ior", [1.5, 1.1, float("nan")])
def test_clear_glass_under_a_uniform_world_shows_the_world(ior):
    """Reflected or refracted, every path of clear glass ends on the same uniform world: the ball
    shows its radiance (energy kept by the Fresnel split and the paths' internal reflections).
    A non-finite index (a snapshot made without sync, which clamps it) is taken as 1.5."""
    x, origins, dirs = rays_at_ball()
    with glass_ball_system(ior=ior) as system:
        glass, light = refraction.glass_paths(system, hit_lookup(system, True), origins, dirs, np.random.default_rng(1))
    np.testing.assert_array_equal(glass, np.abs(x) < 0.495)  # the disc (a 96-gon's edge)
    inner = np.abs(x) < 0.45
    np.testing.assert_allclose(light[inner], 0.7, rtol=0.01)
    assert (light[~glass] == 0).all()


@pytest.mark.parametrize("hidden", ["camera_visible", "holdout"])
def test_glass_the_camera_does_not_see_stays_out_of_the_image(hidden):
    """A glass object hidden from the camera (or a holdout) is no refraction of the camera's:
    its pixels keep the raster's image (which never drew it)."""
    from dataclasses import replace

    x, origins, dirs = rays_at_ball(16)
    with glass_ball_system() as system:
        value = hidden == "holdout"
        system.scene.objects[0] = replace(system.scene.objects[0], **{hidden: value})
        glass, light = refraction.glass_paths(system, hit_lookup(system, True), origins, dirs, np.random.default_rng(5))
    assert not glass.any() and not light.any()


def test_paths_that_leave_see_the_world_as_the_camera_does():
    """A path that leaves the scene shows the environment image the camera sees (its own
    resolution), not the lighting's coarse sky map: here a uniform image of 0.9 over a lighting
    colour of 0.7."""
    x, origins, dirs = rays_at_ball(16)
    with glass_ball_system(background=0.9) as system:
        glass, light = refraction.glass_paths(system, hit_lookup(system, True), origins, dirs, np.random.default_rng(4))
    np.testing.assert_allclose(light[np.abs(x) < 0.45], 0.9, rtol=0.01)


@pytest.mark.parametrize("glass_bsdf", [False, True])
def test_coloured_glass_tints_what_it_refracts_and_a_glass_bsdf_what_it_reflects(glass_bsdf):
    """Through the ball's middle: the light refracted in is tinted at both interfaces, and what
    the far side reflects back inside leaves by the near side, tinted the same (the paths choose
    by the Fresnel). The Fresnel reflection (4% at normal incidence) keeps the world's colour under
    a Principled BSDF's Base Color and takes a Glass BSDF's Color, as in Cycles."""
    tint = np.array([1.0, 0.5, 0.25], np.float32)
    x, origins, dirs = rays_at_ball(9)
    with glass_ball_system(tint=tint, tint_reflection=glass_bsdf) as system:
        _glass, light = refraction.glass_paths(system, hit_lookup(system, True), origins, dirs,
                                               np.random.default_rng(2))
    f0 = ((1.5 - 1.0) / (1.5 + 1.0)) ** 2
    middle = light[4]
    expected = 0.7 * (f0 * (tint if glass_bsdf else 1.0) + (1.0 - f0) * tint**2)
    np.testing.assert_allclose(middle, expected, rtol=0.01)


@pytest.mark.parametrize("ior", [1.33, 1.5])
def test_a_ball_inverts_the_view_behind_it(ior):
    """A ball over a floor half dark, half bright: looking down through its middle, the rays cross
    on the way (a ball lens): the pixels left of the centre see the floor's right half."""
    from blend_scenes.procedural import uv_sphere
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.snapshot import Material, World, concat_geometry, geometry_from_arrays, make_snapshot
    from hybridgi_core.system import GISystem

    ball = uv_sphere(0.5, 96, 48)
    sphere = geometry_from_arrays(ball.positions + np.float32([0, 0, 1.0]), ball.triangles, 0, 0, normals=ball.normals)
    # Two floor halves: x < 0 black, x > 0 emitting (seen through the ball, lit or not).
    left = geometry_from_arrays([[-9, -9, 0], [0, -9, 0], [0, 9, 0], [-9, 9, 0]], [[0, 1, 2], [0, 2, 3]], 1, 1)
    right = geometry_from_arrays([[0, -9, 0], [9, -9, 0], [9, 9, 0], [0, 9, 0]], [[0, 1, 2], [0, 2, 3]], 2, 2)
    mats = [Material("glass", np.zeros(3, np.float32), clear=True, refractive=True, ior=ior),
            Material("black", np.zeros(3, np.float32)),
            Material("glow", np.zeros(3, np.float32), emission=np.full(3, 1.0, np.float32))]
    scene = make_snapshot(concat_geometry([sphere, left, right]), mats, [], World(color=np.zeros(3, np.float32)))
    x = np.array([-0.3, -0.15, 0.15, 0.3])
    origins = np.stack([x, np.zeros_like(x), np.full_like(x, 4.0)], axis=1).astype(np.float32)
    dirs = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (x.size, 1))
    with GISystem(scene, CacheSettings(resolution=8, rays_per_cell=8)) as system:
        glass, light = refraction.glass_paths(system, hit_lookup(system, True), origins, dirs, np.random.default_rng(3))
    assert glass.all()
    lum = light.mean(axis=1)
    assert (lum[x < 0] > 0.8).all() and (lum[x > 0] < 0.1).all(), lum  # straight through it was the other way


BALL_SCENE = "import math, sys, bpy\nfrom mathutils import Vector\n" + STAGE_HELPERS + """
bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
glass = material("glass", (1.0, 1.0, 1.0), 0.0)
glass.node_tree.nodes["Principled BSDF"].inputs["Transmission Weight"].default_value = 1.0
bpy.ops.mesh.primitive_plane_add(size=12)
bpy.context.object.data.materials.append(material("floor", (0.7, 0.7, 0.7), 0.7))
bpy.ops.mesh.primitive_cube_add(size=1, location=(0.0, 1.5, 0.5))
bpy.context.object.data.materials.append(material("box", (0.8, 0.2, 0.1), 0.7))
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=(-0.3, 0.0, 0.6), segments=48, ring_count=24)
bpy.ops.object.shade_smooth()
bpy.context.object.data.materials.append(glass)
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.data.energy = 3.0
sun.rotation_euler = (math.radians(40), 0, math.radians(-60))
scene.collection.objects.link(sun)
world = bpy.data.worlds.new("w")
world.use_nodes = True
world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.4, 0.45, 0.5, 1)
scene.world = world
cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
cam.location = (0.0, -4.0, 1.6)
cam.rotation_euler = (math.radians(75), 0, 0)
scene.collection.objects.link(cam)
scene.camera = cam
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
"""


@pytest.mark.blender
@pytest.mark.slow
def test_a_glass_ball_refracts_the_scene_as_cycles_does(tmp_path):
    """A Principled glass ball (transmission 1, roughness 0) on a floor in front of a red box,
    against Cycles 64 spp + OIDN rendered here: over the ball's pixels the Combined error is a
    fraction of what clear thin glass gave (the floor straight through it: 0.64; now 0.12), the
    ball is not counted in the Diffuse Color pass (Cycles' light through glass is Transmission),
    and the rest of the image is the same."""
    import subprocess
    import sys

    from tests.cli_renders import layer, rendered

    blend = tmp_path / "ball.blend"
    subprocess.run([sys.executable, "-c", BALL_SCENE, str(blend)], check=True, capture_output=True)
    ours = rendered(blend, tmp_path / "hg", "96x54")
    cycles = rendered(blend, tmp_path / "cy", "96x54", "--engine", "CYCLES", "--samples", "64",
                      "--set", "cycles.use_denoising=true")
    mine, reference = layer(ours, "Combined"), layer(cycles, "Combined")
    # The ball: pixels whose Cycles Diffuse Color is 0 (the first hit is glass) over geometry.
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    ball = geometry & (layer(cycles, "Diffuse Color").max(axis=-1) < 0.02)
    assert 400 < ball.sum() < 2000, ball.sum()  # ~1100 pixels of 5184
    error = float(np.abs(mine - reference)[ball].sum() / np.abs(reference)[ball].sum())
    print(f"ball Combined {error:.3f}")
    assert error < 0.15, error
    assert float(layer(ours, "Diffuse Color")[ball].max(axis=-1).mean()) < 0.1
