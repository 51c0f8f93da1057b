"""A metal's colour where Metallic and Base Color are both textures (a PBR asset's metal parts in
one colour map): the G-buffer reads the metal's colour over a pixel's footprint from the metal
texels alone (`gbuffer.metal_texels`: colour x Metallic, Metallic in alpha), not from every texel
there. Red metal stripes a fifth of a blue-grey plate, 64x48 against Cycles 64 spp + OIDN, over
the plate: Glossy Color 0.294 -> 0.179 (over 4x4 blocks 0.271 -> 0.119; the rest is the stripes'
aliasing, Diffuse Color 0.059 either way), Combined 0.214 -> 0.098; at roughness 0.6 the lamps'
glossy light is filtered over the lobes' colour (`glossy_image.finish_glossy`): Combined 0.193 ->
0.076."""

from __future__ import annotations

import textwrap
from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from hybridgi_core import glossy
from hybridgi_core import specular as sp
from hybridgi_core.raster.gbuffer import metal_texels
from hybridgi_core.snapshot import Material
from tests.cli_renders import CYCLES, QUICK, STAGE_HELPERS, layer, pass_error, rendered, run_bpy

RES = "64x48"

#: A 4 m plate seen from 45 degrees under a sun and a grey world: Base Color an image of red
#: stripes (a fifth of it) on blue-grey, Metallic an image of the same stripes, Roughness ROUGH;
#: the view layer writes the glossy passes.
SCENE = "import bpy\nimport numpy as np\nfrom mathutils import Vector\n" + STAGE_HELPERS + textwrap.dedent("""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    camera_at((0, -3.0, 3.0), (0, 0, 0))
    sun_towards((0, -0.5, -0.866), 3.0)
    scene.world = bpy.data.worlds.new("grey")
    if scene.world.node_tree is None:
        scene.world.use_nodes = True
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.2, 0.2, 0.2, 1)
    bpy.ops.mesh.primitive_plane_add(size=4)
    n = 256
    stripe = ((np.arange(n) % 10) < 2)[None, :].repeat(n, axis=0)
    def image(name, rgb, colour):
        im = bpy.data.images.new(name, n, n, alpha=False, float_buffer=True)
        px = np.ones((n, n, 4), np.float32)
        px[..., :3] = rgb
        im.pixels.foreach_set(px.ravel())
        im.pack()
        if not colour:
            im.colorspace_settings.name = "Non-Color"
        return im
    colours = np.where(stripe[..., None], np.float32([0.9, 0.2, 0.1]), np.float32([0.2, 0.3, 0.5]))
    m = bpy.data.materials.new("plate")
    if m.node_tree is None:
        m.use_nodes = True
    tree = m.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    bsdf.inputs["Roughness"].default_value = ROUGH
    for name, rgb, socket, colour in (("colours", colours, "Base Color", True),
                                      ("metal", stripe[..., None].astype(np.float32), "Metallic", False)):
        node = tree.nodes.new("ShaderNodeTexImage")
        node.image = image(name, rgb, colour)
        tree.links.new(node.outputs["Color"], bsdf.inputs[socket])
    bpy.context.object.data.materials.append(m)
    for view_layer in scene.view_layers:
        view_layer.use_pass_glossy_color = view_layer.use_pass_glossy_direct = True
    bpy.ops.wm.save_as_mainfile(filepath=OUT)
""")


def test_metal_texels_are_premultiplied_by_their_metallic():
    """rgb = colour x Metallic and alpha = Metallic per texel, the Metallic brought to the colour
    texture's size (its box average): the footprint average of rgb over alpha is the metal's."""
    colour = np.zeros((4, 4, 3), np.float32)
    colour[:, :2] = (0.9, 0.2, 0.1)
    colour[:, 2:] = (0.2, 0.3, 0.5)
    metal = np.zeros((8, 8), np.float32)
    metal[:, :4] = 1.0
    metal[:, 2:4] = 0.5  # (8, 8) -> (4, 4): columns 0 and 1 average 1.0 and 0.5
    material = Material(name="plate", metallic_map=metal, metal_texture=colour)
    texels = metal_texels(material)
    assert texels.shape == (4, 4, 4)
    np.testing.assert_allclose(texels[:, 0, 3], 1.0)
    np.testing.assert_allclose(texels[:, 1, 3], 0.5)
    np.testing.assert_allclose(texels[:, 2:, 3], 0.0)
    np.testing.assert_allclose(texels[:, 1, :3], 0.5 * colour[:, 1], rtol=1e-6)
    mean = texels.reshape(-1, 4).mean(axis=0)
    np.testing.assert_allclose(mean[:3] / mean[3], (0.9, 0.2, 0.1), rtol=1e-6)


@pytest.mark.parametrize("mu", [1.0, 0.5, 0.25])
def test_a_textured_metals_texel_is_weighed_by_its_lobes_albedo(mu):
    """A rough metal lobe's albedo is not linear in its colour (multiple scattering): a texel of
    F0 0.9 on a lobe whose F0 is the texture's mean 0.34 scales its light by the lobe's albedo
    at 0.9 over at 0.34 at the view cosine (`glossy.metal_tint_scale`: 4.3 x at normal incidence
    at roughness 0.9, 3.7 x at cosine 0.5), not by 0.9 / 0.34 = 2.65 as before; a texel of the
    mean colour by 1."""
    layer = sp.SpecularLayer(roughness=0.9, metallic=1.0, weight=0.0, metal_color=np.full(3, 0.34, np.float32))
    mats = SimpleNamespace(metal_f0=np.full((1, 3), 0.34), metal_curve=glossy.metal_albedo_curve(layer)[None])
    rows, mus = np.zeros(2, np.int64), np.full(2, mu)
    ratio = np.array([[1.0, 1.0, 1.0], [0.9 / 0.34, 1.0, 0.5]])
    scale = glossy.metal_tint_scale(mats, rows, ratio, mus)
    np.testing.assert_allclose(scale[0], 1.0, rtol=1e-6)
    want = [sp.glossy_color(replace(layer, metal_color=np.full(3, f, np.float32)), mu).reshape(-1, 3)[0, 0]
            for f in (0.9, 0.34, 0.17)]
    np.testing.assert_allclose(scale[1], [want[0] / want[1], 1.0, want[2] / want[1]], rtol=0.03)
    assert scale[1, 0] > 0.9 / 0.34 * 1.2


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.parametrize("rough", [0.4, 0.6, 0.9])
def test_metal_stripes_reflect_their_own_colour_and_light(tmp_path, rough):
    """Glossy Color, Glossy Direct and Combined over the plate against Cycles: the stripes' red
    metal reflects red, not the plate's mean colour (mean red Glossy Color 0.138 against Cycles'
    0.198; now 0.220); at roughness 0.6, where the lamps' sampled glossy light is filtered, it is
    filtered over each lobe's colour at normal incidence (`glossy_image.finish_glossy`), so the
    stripes keep their highlight (Glossy Direct 0.584 -> 0.038, Combined 0.193 -> 0.076); at
    roughness 0.9 the stripes' texels are weighed by their lobe's albedo (`metal_tint_scale`):
    Combined 0.0707 -> 0.0607, the plate's mean red 0.298 -> 0.358 (Cycles 0.347). Cycles'
    Glossy Color pass of a rough metal leaves out its multiple scattering: not compared there."""
    blend = tmp_path / "plate.blend"
    run_bpy(SCENE, OUT=str(blend), ROUGH=rough)
    ours = rendered(blend, tmp_path / "h", RES, *QUICK)
    cycles = rendered(blend, tmp_path / "c", RES, *CYCLES)
    mask = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    assert mask.sum() > 1000
    errors = {name: pass_error(ours, cycles, name, mask) for name in ("Glossy Color", "Glossy Direct", "Combined")}
    if rough < 0.9:
        assert errors["Glossy Color"] < 0.23, errors
    assert errors["Glossy Direct"] < 0.1, errors
    assert errors["Combined"] < (0.066 if rough == 0.9 else 0.14), errors
