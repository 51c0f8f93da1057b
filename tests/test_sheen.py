"""Sheen (a Sheen BSDF, a Principled BSDF's sheen layer: fabric, velvet): Cycles counts it as a
diffuse closure weighted by the sheen lobe's albedo at the view angle, so a sheen surface
brightens towards grazing views (`hybridgi_core/sheen.py`). Before, a Principled BSDF's sheen was
not rendered (a note said so) and a lone Sheen BSDF was an unsupported shader, grey 0.8: three
spheres (Sheen, Toon, Diffuse) 320x180 against Cycles 64 spp, Combined 0.222, now 0.071 (the
Sheen sphere 0.018); a red sphere with sheen 1 0.039 -> 0.018."""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from hybridgi_core import sheen, surface_mix
from hybridgi_core.raster.gbuffer import weight_table
from hybridgi_core.snapshot import Material
from tests.cli_renders import CYCLES, QUICK, layer, pass_error, rendered, run_bpy

RES = "64x64"

#: A 2 m plane under a uniform grey world, seen 75 degrees off its normal (orthographic): a
#: Principled BSDF (base 0.5, no specular) with sheen weight 1 ("principled"), the same with its
#: specular layer (Specular IOR Level 1, roughness 0.3: "specular"), and a Sheen BSDF of colour
#: (0.9, 0.6, 0.3) ("sheen").
SCENES = textwrap.dedent("""
    import math, bpy
    out = OUT
    for kind in ("principled", "sheen", "specular"):
        bpy.ops.wm.read_homefile(use_empty=True)
        scene = bpy.context.scene
        cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
        cam.data.type = "ORTHO"
        cam.data.ortho_scale = 0.4
        angle = math.radians(75)
        cam.location, cam.rotation_euler = (0, -3 * math.sin(angle), 3 * math.cos(angle)), (angle, 0, 0)
        scene.collection.objects.link(cam)
        scene.camera = cam
        bpy.ops.mesh.primitive_plane_add(size=2)
        m = bpy.data.materials.new("cloth")
        if m.node_tree is None:
            m.use_nodes = True
        tree = m.node_tree
        if kind in ("principled", "specular"):
            p = tree.nodes["Principled BSDF"]
            p.inputs["Base Color"].default_value = (0.5, 0.5, 0.5, 1)
            p.inputs["Sheen Weight"].default_value = 1.0
            p.inputs["Specular IOR Level"].default_value = 0.0 if kind == "principled" else 1.0
            p.inputs["Roughness"].default_value = 0.3
        else:
            tree.nodes.remove(tree.nodes["Principled BSDF"])
            s = tree.nodes.new("ShaderNodeBsdfSheen")
            s.inputs["Color"].default_value = (0.9, 0.6, 0.3, 1)
            s.inputs["Roughness"].default_value = 0.5
            tree.links.new(s.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
        bpy.context.object.data.materials.append(m)
        scene.world = bpy.data.worlds.new("grey")
        if scene.world.node_tree is None:
            scene.world.use_nodes = True
        scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.3, 0.3, 1)
        bpy.ops.wm.save_as_mainfile(filepath=f"{out}/{kind}.blend")
""")


def test_the_albedo_grows_towards_grazing_views_and_with_roughness():
    """Cycles' values (a white Sheen BSDF, roughness 0.5, Diffuse Color under a uniform world):
    0.019 at mu = 1, 0.154 at mu = 0.5, 0.458 at mu = cos 80 degrees; none at roughness 0."""
    np.testing.assert_allclose(sheen.albedo(0.5, [1.0, 0.5, np.cos(np.radians(80))]), [0.019, 0.154, 0.458],
                               atol=0.004)
    assert sheen.albedo(0.0, 0.3) < 1e-3
    mu = np.linspace(0.0, 1.0, 9)
    assert np.all(np.diff(sheen.albedo(0.8, mu)) < 0)
    assert sheen.hemispherical_albedo(1.0) > sheen.hemispherical_albedo(0.5) > 0.05


def test_a_principled_sheen_weighs_its_base_and_a_sheen_bsdf_does_not():
    """Weight table: a Principled BSDF's layered sheen s multiplies its base by 1 - max(s) A and
    adds s A; a Sheen BSDF in a Mix adds its share without weighing the Diffuse BSDF beside it."""
    s = np.array([1.0, 0.5, 0.25], np.float32)
    layered = Material(name="cloth", sheen=s, sheen_roughness=0.5, sheen_layered=True)
    table = weight_table([Material(name="plain"), layered])
    mu = np.linspace(0.0, 1.0, table.shape[1])
    a = sheen.albedo(0.5, mu)
    np.testing.assert_allclose(table[0, :, 0], 1.0)
    np.testing.assert_allclose(table[0, :, 1:], 0.0)
    np.testing.assert_allclose(table[1, :, 0], 1.0 - a, atol=1e-6)
    np.testing.assert_allclose(table[1, :, 1:], a[:, None] * s[None, :], atol=1e-6)
    assert layered.hit_diffuse_weight < 1.0
    parts = [surface_mix.SurfacePart(base=np.full(3, 0.5, np.float32)),
             surface_mix.SurfacePart(base=np.zeros(3, np.float32), sheen=s, sheen_roughness=0.7)]
    part, _ = surface_mix.mix(parts, [surface_mix.constant_factor(0.5)] * 2)
    np.testing.assert_allclose(part.base, 0.25, rtol=1e-4)
    np.testing.assert_allclose(part.sheen, 0.5 * s, rtol=1e-4)
    assert part.sheen_roughness == pytest.approx(0.7) and not part.sheen_layered
    assert Material(name="none", sheen=[0.0, 0.0, 0.0]).sheen is None


@pytest.fixture(scope="module")
def planes(tmp_path_factory):
    out = tmp_path_factory.mktemp("sheen")
    run_bpy(SCENES, OUT=str(out))
    return out


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.smoke
@pytest.mark.parametrize("kind", ["principled", "sheen", "specular"])
def test_a_sheen_plane_at_a_grazing_view_matches_cycles(planes, tmp_path, kind):
    """Diffuse Color and Combined against Cycles' (64 spp + OIDN) over the plane, seen 75
    degrees off its normal: the sheen's brightening is there (without it the Principled plane's
    Diffuse Color was 0.5 against Cycles' 0.69, the Sheen BSDF's grey 0.8 against ~0.3), and the
    specular layer under it is dimmed as Cycles layers it (`glossy.under_sheen`; measured, the
    "specular" plane's Combined 0.116 at the specular's full weight -> 0.0025)."""
    ours = rendered(planes / f"{kind}.blend", tmp_path / "h", RES, *QUICK)
    cycles = rendered(planes / f"{kind}.blend", tmp_path / "c", RES, *CYCLES)
    mask = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    assert mask.sum() > 1000
    for name in ("Diffuse Color", "Combined"):
        err = pass_error(ours, cycles, name, mask)
        assert err < 0.03, (name, err)
