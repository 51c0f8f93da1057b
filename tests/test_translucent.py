"""Thin translucent surfaces (a Translucent BSDF, alone or mixed with a Diffuse BSDF: leaves,
paper): Cycles counts them as diffuse closures, their colour in Diffuse Color and the light they
diffuse from behind in Diffuse Direct. Before, a Translucent BSDF was black (a warning said its
light was not rendered): sunlit leaves over a ground, 320x180 against Cycles 256 spp, Combined
0.243; now 0.017, their back-lit glow included."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from hybridgi_core import surface_mix, translucent
from hybridgi_core.snapshot import Material
from tests.cli_renders import CYCLES, QUICK, layer, pass_error, rendered, run_bpy

RES = "64x36"

#: A 2 m plane facing the camera, lit from behind by a sun 0.3 rad off its normal, under a dim grey
#: world: a Translucent BSDF alone ("translucent") and mixed 0.4 into a Diffuse BSDF ("mix").
SCENES = textwrap.dedent("""
    import math, bpy
    out = OUT
    for kind in ("translucent", "mix"):
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.location, cam.rotation_euler = (0, -5, 0), (math.pi / 2, 0, 0)
        scene.collection.objects.link(cam)
        scene.camera = cam
        sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
        sun.data.energy = 3.0
        sun.rotation_euler = (-math.pi / 2 + 0.3, 0, 0)
        scene.collection.objects.link(sun)
        bpy.ops.mesh.primitive_plane_add(size=2, rotation=(math.pi / 2, 0, 0))
        m = bpy.data.materials.new("leaf")
        if m.node_tree is None:
            m.use_nodes = True
        tree = m.node_tree
        tree.nodes.remove(tree.nodes["Principled BSDF"])
        back = tree.nodes.new("ShaderNodeBsdfTranslucent")
        back.inputs["Color"].default_value = (0.8, 0.5, 0.2, 1)
        surface = back.outputs[0]
        if kind == "mix":
            front = tree.nodes.new("ShaderNodeBsdfDiffuse")
            front.inputs["Color"].default_value = (0.2, 0.6, 0.2, 1)
            mix = tree.nodes.new("ShaderNodeMixShader")
            mix.inputs["Fac"].default_value = 0.4
            tree.links.new(front.outputs[0], mix.inputs[1])
            tree.links.new(back.outputs[0], mix.inputs[2])
            surface = mix.outputs[0]
        tree.links.new(surface, tree.nodes["Material Output"].inputs["Surface"])
        bpy.context.object.data.materials.append(m)
        scene.world = bpy.data.worlds.new("dim")
        if scene.world.node_tree is None:
            scene.world.use_nodes = True
        scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.05, 0.05, 0.05, 1)
        bpy.ops.wm.save_as_mainfile(filepath=f"{out}/{kind}.blend")
""")


def test_a_mix_weighs_the_translucent_share_per_channel():
    """Mix(Diffuse c_d, Translucent c_t, 0.4): Diffuse Color 0.6 c_d + 0.4 c_t, of which the
    translucent share per channel is 0.4 c_t / that; a lone Translucent BSDF's is 1."""
    c_d, c_t = np.array([0.2, 0.6, 0.2]), np.array([0.8, 0.5, 0.2])
    parts = [surface_mix.SurfacePart(base=c_d.astype(np.float32)),
             surface_mix.SurfacePart(base=c_t.astype(np.float32), translucent=np.ones(3, np.float32))]
    part, _ = surface_mix.mix(parts, [surface_mix.constant_factor(0.6), surface_mix.constant_factor(0.4)])
    np.testing.assert_allclose(part.base, 0.6 * c_d + 0.4 * c_t, rtol=1e-4)
    np.testing.assert_allclose(part.translucent, 0.4 * c_t / (0.6 * c_d + 0.4 * c_t), rtol=1e-4)
    plain, _ = surface_mix.mix(parts[:1] * 2, [surface_mix.constant_factor(0.5)] * 2)
    assert plain.translucent is None


def test_back_light_mixes_by_share_and_only_where_needed():
    table = translucent.share_table([Material(name="wall"), Material(name="leaf", translucent=[1.0, 0.5, 0.0])])
    shares = translucent.pixel_shares(table, np.array([0.0, 1.0, 2.0, 2.25]))  # background, wall, leaf x 2
    asked = []

    def back(rows):
        asked.append(rows)
        return np.full((rows.size, 3), 10.0, np.float32)

    front = np.ones((4, 3), np.float32)
    out = translucent.mix_back(front, shares, back)
    np.testing.assert_array_equal(asked[0], [2, 3])
    np.testing.assert_allclose(out[:2], 1.0)
    np.testing.assert_allclose(out[2], [10.0, 5.5, 1.0])
    assert translucent.share_table([Material(name="wall")]) is None
    assert Material(name="none", translucent=[0.0, 0.0, 0.0]).translucent is None


@pytest.fixture(scope="module")
def planes(tmp_path_factory):
    out = tmp_path_factory.mktemp("translucent")
    run_bpy(SCENES, OUT=str(out))
    return out


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.parametrize("kind", ["translucent", "mix"])
def test_a_back_lit_translucent_plane_matches_cycles(planes, tmp_path, kind):
    """The plane's Diffuse Color, Diffuse Direct and Combined against Cycles' (64 spp + OIDN)
    over the plane: the sun's light from behind is there (it was 0: the plane was black, but for
    the world's front light in the mix)."""
    ours = rendered(planes / f"{kind}.blend", tmp_path / "h", RES, *QUICK)
    cycles = rendered(planes / f"{kind}.blend", tmp_path / "c", RES, *CYCLES)
    mask = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    assert mask.sum() > 200
    for name in ("Diffuse Color", "Diffuse Direct", "Combined"):
        err = pass_error(ours, cycles, name, mask)
        assert err < 0.05, (name, err)
