"""Textured metals per pixel. A metal's colour texture: its metallic lobe's colour follows the
texel (`glossy.metal_tint_basis`: the texel's coordinates along the texture's two main colour
axes ride in the G-buffer's spare alphas), where the lobe took the texture's mean colour before:
a metal sphere of orange / yellow stripes, 320x180 against Cycles 64 spp, Combined 0.114 ->
0.030 (at the test's size 0.098 -> 0.018); under a Metallic texture (an ORM texture's blue),
the metal half 0.131 -> 0.077. A Roughness texture is followed per pixel (`Material.roughness_map`): each pixel's glossy lobes
are its material's variant nearest its texel (`glossy.ROUGHNESS_STEPS` over the texture's range,
the G-buffer's material fraction picks it), where a lobe took the texture's mean before. A metal
sphere of roughness stripes 0.15 / 0.75 (an image, and the same image's green channel through
Separate Color as glTF imports wire an ORM texture), 320x180 against Cycles 64 spp + OIDN:
Combined 0.718 -> 0.065 over the sphere (the mean's one broad highlight against the sharp
stripes' small ones). At the test's size 0.719 -> 0.088: the stripes' edges weigh more there
(the G-buffer averages the roughness over a pixel's footprint, Cycles the light)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.cli_renders import CYCLES, LIT_SPHERE_STAGE, QUICK, layer, pass_error, rendered, run_bpy

RES = "240x135"
ROOT = Path(__file__).resolve().parents[1]

SCENES = "STAGE = " + repr("import math, bpy\n" + LIT_SPHERE_STAGE) + "\n" + textwrap.dedent("""
    import math, bpy
    import numpy as np
    out = OUT
    for kind in ("image", "separate", "colour", "mapped"):
        exec(STAGE)  # camera, sun, world, floor, the sphere (active)
        n = 64
        x = np.arange(n)[None, :].repeat(n, 0)
        stripes = np.where((x // 8) % 2 == 0, 0.15, 0.75).astype(np.float32)
        rgba = np.ones((n, n, 4), np.float32)
        rgba[..., 0] = rgba[..., 1] = rgba[..., 2] = stripes
        image = bpy.data.images.new("rough", n, n, float_buffer=True)
        image.colorspace_settings.name = "Non-Color"
        image.pixels.foreach_set(rgba.ravel())
        image.pack()
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
        if kind in ("colour", "mapped"):
            colours = np.ones((n, n, 4), np.float32)
            colours[..., 0], colours[..., 2] = 0.8, 0.2
            colours[..., 1] = np.where((x // 8) % 2 == 0, 0.5, 0.8)
            painted = bpy.data.images.new("stripes", n, n, float_buffer=True)
            painted.pixels.foreach_set(colours.ravel())
            painted.pack()
            tex.image = painted
            tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
            bsdf.inputs["Roughness"].default_value = 0.3
            if kind == "mapped":
                # Metal above the equator, paint below: a Metallic texture (the image's blue
                # through Separate Color, as glTF imports wire an ORM texture).
                y = np.arange(n)[:, None].repeat(n, 1)
                orm = np.ones((n, n, 4), np.float32)
                orm[..., 2] = np.where(y >= n // 2, 1.0, 0.0)
                metal = bpy.data.images.new("orm", n, n, float_buffer=True)
                metal.colorspace_settings.name = "Non-Color"
                metal.pixels.foreach_set(orm.ravel())
                metal.pack()
                source = tree.nodes.new("ShaderNodeTexImage")
                source.image = metal
                source.interpolation = "Closest"
                split = tree.nodes.new("ShaderNodeSeparateColor")
                tree.links.new(source.outputs["Color"], split.inputs[0])
                tree.links.new(split.outputs["Blue"], bsdf.inputs["Metallic"])
        elif kind == "image":
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
@pytest.mark.parametrize("kind", ["image", "separate", "colour", "mapped"])
def test_a_striped_metal_sphere_matches_cycles(spheres, tmp_path, kind):
    """Combined over the sphere against Cycles' (64 spp + OIDN): the sharp stripes' highlights and
    reflections and the rough ones' blur are there (with the texture's mean roughness: 0.72); the
    orange and yellow stripes of the colour texture are."""
    ours = rendered(spheres / f"{kind}.blend", tmp_path / "h", RES, *QUICK)
    cycles = rendered(spheres / f"{kind}.blend", tmp_path / "c", RES, *CYCLES)
    sphere = (layer(cycles, "Depth", "Z")[..., 0] < 4.5) & (layer(cycles, "Diffuse Color")[..., 0] < 0.01)
    assert sphere.sum() > 500
    err = pass_error(ours, cycles, "Combined", sphere)
    # With the texture's mean roughness 0.72, with its mean colour 0.098 (0.018 now); under a
    # Metallic texture (the metal half, the colour texture's mean before) 0.131 (0.077 now).
    assert err < {"colour": 0.05, "mapped": 0.1}.get(kind, 0.15), err


@pytest.mark.blender
@pytest.mark.slow
def test_the_settled_viewport_shows_the_textured_metals_colour(spheres, tmp_path):
    """The viewport's settled image (its worker computes the final render's glossy light at every
    pixel, the texels' coordinates read back with the albedo) against Cycles over the colour-
    striped sphere: 0.019 (0.098 when the worker took the mean colour), driven headless as
    `bench/ttq_viewport.py` drives it."""
    out = tmp_path / "viewport"
    run = subprocess.run([sys.executable, str(ROOT / "bench" / "ttq_viewport.py"), str(spheres / "colour.blend"),
                          "--res", RES, "--out", str(out), "--checkpoints", "4", "--timelines", "worker"],
                         capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert run.returncode == 0, run.stderr[-3000:]
    cycles = rendered(spheres / "colour.blend", tmp_path / "c", RES, *CYCLES)
    sphere = (layer(cycles, "Depth", "Z")[..., 0] < 4.5) & (layer(cycles, "Diffuse Color")[..., 0] < 0.01)
    shown = np.load(out / "settled_0.npy").astype(np.float32)[::-1, :, :3]  # rows bottom-up
    a, b = shown[sphere], layer(cycles, "Combined")[sphere]
    err = np.abs(a - b).sum() / np.abs(b).sum()
    assert err < 0.05, err
