"""A Roughness texture is followed per pixel (`Material.roughness_map`): each pixel's glossy lobes
are its material's variant nearest its texel (`glossy.ROUGHNESS_STEPS` over the texture's range,
the G-buffer's material fraction picks it), where a lobe took the texture's mean before. A metal
sphere of roughness stripes 0.15 / 0.75 (an image, and the same image's green channel through
Separate Color as glTF imports wire an ORM texture), 320x180 against Cycles 64 spp + OIDN:
Combined 0.718 -> 0.065 over the sphere (the mean's one broad highlight against the sharp
stripes' small ones). At the test's size 0.719 -> 0.088: the stripes' edges weigh more there
(the G-buffer averages the roughness over a pixel's footprint, Cycles the light)."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from tests.cli_renders import CYCLES, QUICK, layer, rendered, run_bpy

RES = "240x135"

SCENES = textwrap.dedent("""
    import math, bpy
    import numpy as np
    out = OUT
    for kind in ("image", "separate"):
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.location, cam.rotation_euler = (0, -3.2, 1.2), (math.radians(80), 0, 0)
        scene.collection.objects.link(cam)
        scene.camera = cam
        sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
        sun.data.energy, sun.data.angle = 3.0, math.radians(3)
        sun.rotation_euler = (math.radians(-40), math.radians(25), 0)
        scene.collection.objects.link(sun)
        scene.world = bpy.data.worlds.new("grey")
        if scene.world.node_tree is None:
            scene.world.use_nodes = True
        scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.35, 0.4, 1)
        bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, -1))
        n = 64
        x = np.arange(n)[None, :].repeat(n, 0)
        stripes = np.where((x // 8) % 2 == 0, 0.15, 0.75).astype(np.float32)
        rgba = np.ones((n, n, 4), np.float32)
        rgba[..., 0] = rgba[..., 1] = rgba[..., 2] = stripes
        image = bpy.data.images.new("rough", n, n, float_buffer=True)
        image.colorspace_settings.name = "Non-Color"
        image.pixels.foreach_set(rgba.ravel())
        image.pack()
        bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, segments=64, ring_count=32)
        bpy.ops.object.shade_smooth()
        m = bpy.data.materials.new("metal")
        if m.node_tree is None:
            m.use_nodes = True
        tree = m.node_tree
        bsdf = tree.nodes["Principled BSDF"]
        bsdf.inputs["Base Color"].default_value = (0.9, 0.7, 0.4, 1)
        bsdf.inputs["Metallic"].default_value = 1.0
        bsdf.inputs["Roughness"].default_value = 1.0
        tex = tree.nodes.new("ShaderNodeTexImage")
        tex.image = image
        tex.interpolation = "Closest"
        if kind == "image":
            tree.links.new(tex.outputs["Color"], bsdf.inputs["Roughness"])
        else:
            split = tree.nodes.new("ShaderNodeSeparateColor")
            tree.links.new(tex.outputs["Color"], split.inputs[0])
            tree.links.new(split.outputs["Green"], bsdf.inputs["Roughness"])
        bpy.context.object.data.materials.append(m)
        bpy.ops.wm.save_as_mainfile(filepath=f"{out}/{kind}.blend")
""")


@pytest.fixture(scope="module")
def spheres(tmp_path_factory):
    out = tmp_path_factory.mktemp("roughness_texture")
    run_bpy(SCENES, OUT=str(out))
    return out


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["image", "separate"])
def test_a_striped_roughness_metal_sphere_matches_cycles(spheres, tmp_path, kind):
    """Combined over the sphere against Cycles' (64 spp + OIDN): the sharp stripes' highlights and
    reflections and the rough ones' blur are there (with the texture's mean roughness: 0.72)."""
    ours = rendered(spheres / f"{kind}.blend", tmp_path / "h", RES, *QUICK)
    cycles = rendered(spheres / f"{kind}.blend", tmp_path / "c", RES, *CYCLES)
    sphere = (layer(cycles, "Depth", "Z")[..., 0] < 4.5) & (layer(cycles, "Diffuse Color")[..., 0] < 0.01)
    assert sphere.sum() > 500
    a, b = layer(ours, "Combined")[sphere], layer(cycles, "Combined")[sphere]
    err = np.abs(a - b).sum() / np.abs(b).sum()
    assert err < 0.15, err
