"""Alpha cutouts: rays pass through the holes of an alpha-textured surface (hybridgi_core/cutout.py
and EmbreeTracer.set_cutouts), and through the real engine the camera and the sun see through
them as in Cycles."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hybridgi_core.cutout import Cutouts
from hybridgi_core.snapshot import Material, concat_geometry, geometry_from_arrays
from hybridgi_core.trace.embree import EmbreeTracer
from tests.cli_renders import STAGE_HELPERS, against_cycles, layer, pass_error, rendered


def _quad(z, material, uv=True):
    p = np.array([[0, 0, z], [1, 0, z], [1, 1, z], [0, 1, z]], np.float32)
    g = geometry_from_arrays(p, np.array([[0, 1, 2], [0, 2, 3]]), material, 0)
    if uv:
        g.uvs[:] = g.positions[:, :2]  # u = x, v = y
    return g


def _scene():
    """A screen at z = 1 whose left half (u < 0.5) is cut out, above a floor at z = 0."""
    alpha = np.ones((4, 8), np.float32)
    alpha[:, :4] = 0.0
    materials = [Material("screen", alpha=alpha), Material("floor")]
    return concat_geometry([_quad(1.0, 0), _quad(0.0, 1)]), materials


def test_rays_pass_through_holes_and_stop_on_the_solid_part():
    geometry, materials = _scene()
    cutouts = Cutouts(geometry, materials)
    assert cutouts.any
    with EmbreeTracer(geometry, threads=1) as tracer:
        origins = np.array([[0.2, 0.5, 2.0], [0.8, 0.5, 2.0], [0.3, 0.3, 2.0]], np.float32)
        down = np.array([[0, 0, -1.0]] * 3, np.float32)
        solid = tracer.intersect(origins, down)
        np.testing.assert_allclose(solid.t, 1.0, atol=1e-4)  # no cutouts yet: the screen stops all
        tracer.set_cutouts(cutouts)
        hits = tracer.intersect(origins, down)
        np.testing.assert_allclose(hits.t, [2.0, 1.0, 2.0], atol=1e-3)  # through the hole to the floor
        assert materials[geometry.material_index[hits.prim[0]]].name == "floor"
        occluded = tracer.occluded(origins, down, np.float32(1.5))
        assert occluded.tolist() == [False, True, False]
        assert tracer.intersect(origins, down, np.float32(1.5)).prim[0] == -1  # the floor is past tfar


def test_a_surface_seen_with_a_chance_stops_that_share_of_the_rays():
    """A veil of coverage 0.3 (`Material.coverage`: a constant alpha) over a floor: of rays down
    through random points, about 30% stop at the veil and the rest reach the floor, for closest
    hits and shadow rays alike; a given point of the veil stops every ray or none."""
    geometry = concat_geometry([_quad(1.0, 0), _quad(0.0, 1)])
    materials = [Material("veil", coverage=0.3), Material("floor")]
    cutouts = Cutouts(geometry, materials)
    assert cutouts.any
    rng = np.random.default_rng(3)
    origins = np.concatenate([rng.random((20000, 2)), np.full((20000, 1), 2.0)], axis=1).astype(np.float32)
    down = np.tile(np.array([[0, 0, -1.0]], np.float32), (20000, 1))
    with EmbreeTracer(geometry, threads=1) as tracer:
        tracer.set_cutouts(cutouts)
        hits = tracer.intersect(origins, down)
        stopped = np.isclose(hits.t, 1.0, atol=1e-3)
        assert np.all(stopped | np.isclose(hits.t, 2.0, atol=1e-3))
        assert abs(stopped.mean() - 0.3) < 0.02, stopped.mean()
        occluded = tracer.occluded(origins, down, np.float32(1.5))
        np.testing.assert_array_equal(occluded, stopped)  # the same points stop both kinds of ray
        again = tracer.intersect(origins, down)
        np.testing.assert_array_equal(again.t, hits.t)


def test_shadow_rays_pass_what_is_hidden_from_them_and_other_rays_do_not():
    """Three stacked quads: a glass pane transparent to shadow rays (z = 2), one object hidden
    from shadow rays (z = 1, object 1), a floor (z = 0, object 2)."""
    from hybridgi_core.snapshot import ObjectInfo

    quads = [_quad(2.0, 0), _quad(1.0, 1), _quad(0.0, 1)]
    for i, q in enumerate(quads):
        q.object_index[:] = i
    geometry = concat_geometry(quads)
    materials = [Material("glass", shadow_transparent=True), Material("plain")]
    objects = [ObjectInfo("pane"), ObjectInfo("ghost", casts_shadow=False), ObjectInfo("floor")]
    origin, down = np.array([[0.5, 0.5, 3.0]], np.float32), np.array([[0, 0, -1.0]], np.float32)
    with EmbreeTracer(geometry, threads=1) as tracer:
        tracer.set_cutouts(Cutouts(geometry, materials, objects))
        np.testing.assert_allclose(tracer.intersect(origin, down).t, [1.0], atol=1e-4)  # other rays: the pane
        assert tracer.occluded(origin, down).tolist() == [True]
        assert tracer.occluded_shadow(origin, down, np.float32(2.5)).tolist() == [False]  # pane and ghost passed
        assert tracer.occluded_shadow(origin, down).tolist() == [True]  # the floor still blocks
        tracer.set_cutouts(Cutouts(geometry, materials))  # without the objects: the ghost blocks
        assert tracer.occluded_shadow(origin, down, np.float32(2.5)).tolist() == [True]
    assert not Cutouts(geometry, [Material("a"), Material("b")], [ObjectInfo("x")] * 3).shadow_any


def test_triangles_without_uvs_or_alpha_stay_solid():
    geometry = concat_geometry([_quad(1.0, 0, uv=False), _quad(0.0, 1)])
    alpha = np.zeros((2, 2), np.float32)
    assert not Cutouts(geometry, [Material("screen", alpha=alpha), Material("floor")]).any
    assert not Cutouts(geometry, [Material("screen"), Material("floor")]).any


SCENE = textwrap.dedent("""
    import sys, bpy
    import numpy as np
    from mathutils import Vector
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=10.0)
    bpy.ops.mesh.primitive_plane_add(size=3.0, location=(0.0, 0.0, 1.2))
    screen = bpy.context.active_object
    n = 64
    c = ((np.arange(n)[:, None] // 16 + np.arange(n)[None, :] // 16) % 2).astype(np.float32)
    rgba = np.stack([np.full_like(c, 0.8), np.full_like(c, 0.3), np.full_like(c, 0.1), c], -1)
    image = bpy.data.images.new("holes", n, n, alpha=True, float_buffer=True)
    image.pixels.foreach_set(rgba.ravel())
    image.pack()
    material = bpy.data.materials.new("screen")
    material.use_nodes = True
    texture = material.node_tree.nodes.new("ShaderNodeTexImage")
    texture.image = image
    texture.interpolation = "Closest"
    bsdf = material.node_tree.nodes["Principled BSDF"]
    material.node_tree.links.new(texture.outputs["Color"], bsdf.inputs["Base Color"])
    material.node_tree.links.new(texture.outputs["Alpha"], bsdf.inputs["Alpha"])
    screen.data.materials.append(material)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location = (4.0, -5.0, 5.0)
    camera.rotation_euler = (Vector((0.0, 0.0, 0.4)) - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(camera)
    scene.camera = camera
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.data.angle = 0.01
    sun.rotation_euler = (0.3, 0.2, 0.0)
    scene.collection.objects.link(sun)
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.05, 0.05, 0.05)
    bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
""")


def _render(blend, prefix, *extra):
    return rendered(blend, prefix, "96x72", *extra)


@pytest.mark.blender
@pytest.mark.slow
def test_alpha_cutout_screen_against_cycles(tmp_path):
    blend = tmp_path / "cutout.blend"
    subprocess.run([sys.executable, "-c", SCENE, str(blend)], check=True, capture_output=True)
    ours = _render(blend, tmp_path / "hg", "--set", "warmup_iterations=4", "--set", "resolution=16")
    cycles = _render(blend, tmp_path / "cy", "--engine", "CYCLES", "--samples", "64")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    # The camera sees the floor through the holes: the orange screen covers what it covers in Cycles.
    orange = lambda ch: np.abs(layer(ch, "Diffuse Color") - np.array([0.8, 0.3, 0.1])).max(axis=-1) < 0.15  # noqa: E731
    mine, theirs = orange(ours), orange(cycles)
    assert 0.05 < theirs.mean() < 0.6
    assert (mine & theirs).sum() / (mine | theirs).sum() > 0.7
    # Through the holes the floor shows, not the texture's black (a solid screen's transparent texels).
    black = lambda ch: (layer(ch, "Diffuse Color").max(axis=-1) < 0.1) & geometry  # noqa: E731
    assert black(cycles).mean() < 0.01 and black(ours).mean() < 0.01, black(ours).mean()
    # The sun shines through the holes onto the floor: the checkered shadow matches.
    direct, reference = layer(ours, "Diffuse Direct"), layer(cycles, "Diffuse Direct")
    floor = geometry & ~theirs & ~mine
    error = float(np.abs(direct - reference)[floor].sum() / np.abs(reference)[floor].sum())
    # Measured 0.015 (the screen solid for the sun, before: 0.10).
    assert error < 0.05, error


VEIL = "import math, sys, bpy\nfrom mathutils import Vector\n" + STAGE_HELPERS + textwrap.dedent("""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=12.0)
    bpy.context.active_object.data.materials.append(material("floor", (0.6, 0.6, 0.6)))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.6, location=(0.2, 1.0, 0.6))
    bpy.context.active_object.data.materials.append(material("ball", (0.8, 0.3, 0.2)))
    # A veil of alpha 0.35 in front of the ball, casting a 65% shadow.
    veil = material("veil", (0.2, 0.4, 0.9))
    veil.node_tree.nodes["Principled BSDF"].inputs["Alpha"].default_value = 0.35
    bpy.ops.mesh.primitive_plane_add(size=2.0, location=(0.0, -0.3, 1.0), rotation=(math.radians(90), 0.0, 0.2))
    bpy.context.active_object.data.materials.append(veil)
    camera_at((0.0, -6.0, 2.5), (0.0, 0.0, 0.8))
    area_lamp_at((2.5, -2.5, 3.5), (0.0, 0.0, 0.8), 400.0, 1.5, name="key")
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.15, 0.17, 0.2)
    bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
""")



@pytest.mark.blender
@pytest.mark.slow
def test_a_veil_of_constant_alpha_against_cycles(tmp_path):
    """A Principled BSDF of Alpha 0.35: seen in 35% of the camera's samples and stopping 35% of the
    rays (`Material.coverage`), as Cycles mixes it with a Transparent BSDF. It was clear glass
    (invisible, no shadow): here Combined 0.218 against Cycles 256 spp, now 0.020; at 320x180
    against 1024 spp 0.0995 -> 0.0091 (Cycles 16 spp + OIDN 0.0058)."""
    blend = tmp_path / "veil.blend"
    subprocess.run([sys.executable, "-c", VEIL, str(blend)], check=True, capture_output=True)
    ours, cycles, geometry = against_cycles(blend, tmp_path, "128x72")
    error = pass_error(ours, cycles, "Combined", geometry)
    print(f"Combined {error:.4f}")
    assert error < 0.03, error
    # The veil's blue is in Diffuse Color where it covers the ball, at Cycles' share.
    colour, ref_colour = layer(ours, "Diffuse Color"), layer(cycles, "Diffuse Color")
    blue = geometry & (ref_colour[..., 2] > ref_colour[..., 0] + 0.05)
    assert blue.sum() > 100
    assert abs(colour[blue].mean() - ref_colour[blue].mean()) < 0.05 * ref_colour[blue].mean()
