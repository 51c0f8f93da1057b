"""Materials that read the Object Info node (a random tint per object: scattered rocks, crowds,
kit-bashed props): the colour bake (`material_bake`) runs per object, with the object's own
Random, Location, Color and pass index fed as constants (`sync.object_values`). Before, every
object sharing a mesh took one bake, made on the bake process's own object: sixteen cubes of a
random red-to-blue tint came out one purple (320x180 against Cycles 64 spp: Combined 0.172; now
0.014)."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from tests.cli_renders import CYCLES, QUICK, layer, pass_error, rendered, run_bpy

RES = "96x54"

#: Six linked duplicates of a cube and three instances of a collection holding one, a material
#: whose base colour is a Color Ramp from red to blue over Object Info > Random.
SCENE = textwrap.dedent("""
    import math, bpy
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    m = bpy.data.materials.new("tint")
    if m.node_tree is None:
        m.use_nodes = True
    tree = m.node_tree
    info = tree.nodes.new("ShaderNodeObjectInfo")
    ramp = tree.nodes.new("ShaderNodeValToRGB")
    ramp.color_ramp.elements[0].color = (0.8, 0.1, 0.1, 1)
    ramp.color_ramp.elements[1].color = (0.1, 0.3, 0.9, 1)
    tree.links.new(info.outputs["Random"], ramp.inputs["Fac"])
    tree.links.new(ramp.outputs["Color"], tree.nodes["Principled BSDF"].inputs["Base Color"])
    tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = 1.0
    bpy.ops.mesh.primitive_cube_add(size=0.8, location=(-3.0, 0, 0.4))
    first = bpy.context.object
    first.data.materials.append(m)
    for i in range(1, 6):
        other = first.copy()
        scene.collection.objects.link(other)
        other.location = (-3.0 + 1.2 * i, 0, 0.4)
    held = bpy.data.collections.new("held")
    bpy.ops.mesh.primitive_cube_add(size=0.8)
    cube = bpy.context.object
    cube.data.materials.append(m)
    scene.collection.objects.unlink(cube)
    held.objects.link(cube)
    for i in range(3):
        empty = bpy.data.objects.new(f"copy{i}", None)
        empty.instance_type, empty.instance_collection = "COLLECTION", held
        empty.location = (-1.8 + 1.8 * i, 1.6, 0.4)
        scene.collection.objects.link(empty)
    bpy.ops.mesh.primitive_plane_add(size=20)
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), math.radians(20), math.radians(30))
    scene.collection.objects.link(sun)
    scene.world = bpy.data.worlds.new("sky")
    if scene.world.node_tree is None:
        scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.35, 0.4, 1)
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    cam.location, cam.rotation_euler = (0, -6.5, 3.5), (math.radians(62), 0, 0)
    scene.collection.objects.link(cam)
    scene.camera = cam
    bpy.ops.wm.save_as_mainfile(filepath=OUT)
""")


@pytest.fixture(scope="module")
def tinted(tmp_path_factory):
    out = tmp_path_factory.mktemp("object_info") / "tinted.blend"
    run_bpy(SCENE, OUT=str(out))
    return out


@pytest.mark.blender
@pytest.mark.slow
def test_each_object_takes_its_own_random_tint(tinted, tmp_path):
    """Diffuse Color and Combined against Cycles' over the cubes (64 spp + OIDN): each object and
    each collection instance its own colour (one bake for all of them: Diffuse Color 0.43)."""
    ours = rendered(tinted, tmp_path / "h", RES, *QUICK)
    cycles = rendered(tinted, tmp_path / "c", RES, *CYCLES)
    colour = layer(cycles, "Diffuse Color")
    cubes = np.abs(colour[..., 0] - colour[..., 2]) > 0.05  # tinted, not the grey floor
    assert cubes.sum() > 300
    for name, bound in (("Diffuse Color", 0.05), ("Combined", 0.08)):
        err = pass_error(ours, cycles, name, cubes)
        assert err < bound, (name, err)
