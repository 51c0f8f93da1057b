"""What an artist's scene holds that earlier rounds did not cover, through the real `hybridgi
render` command against Cycles rendered in the same test (64 spp + OIDN).

A sweep of 49 such scenes (`bench/artist_scenes.py`, `bench/artist_sweep.py`: 128x96, default
settings; the commit that added them has the table) found collection and Geometry Nodes
instances, modifiers, text and curve bevels, metaballs, negative scales, objects without a
material or with several, orthographic and shifted cameras, sensor fit, clipping, resolution
percentage, image-alpha leaves (Principled Alpha, Mix with a Transparent BSDF), colour attributes,
emission shaders, a Sky Texture, Filmic, a wide pixel filter and 1000x / 0.001x scenes within
Combined rel L1 0.03 of Cycles. The cases below were wrong and are fixed here.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from tests.cli_renders import CYCLES, QUICK, STAGE_HELPERS, layer, rendered

RES = "64x48"

pytestmark = [pytest.mark.blender, pytest.mark.slow]

#: A floor, a wall, a red cube and a blue ball under a sun and a grey world; argv[-2] names the
#: variant (`VARIANTS`), argv[-1] the .blend to write.
SCENE = "import math, os, sys, bpy\nimport numpy as np\nfrom mathutils import Vector\n" + STAGE_HELPERS + textwrap.dedent("""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    def add(op, name, mat, **kw):
        op(**kw)
        ob = bpy.context.active_object
        ob.name = name
        ob.data.materials.append(mat)
        return ob
    add(bpy.ops.mesh.primitive_plane_add, "floor", material("grey", (0.7, 0.7, 0.7)), size=10.0)
    add(bpy.ops.mesh.primitive_cube_add, "cube", material("red", (0.8, 0.15, 0.1)), size=1.0,
        location=(-1.2, 0.2, 0.5), rotation=(0, 0, 0.4))
    add(bpy.ops.mesh.primitive_uv_sphere_add, "ball", material("blue", (0.15, 0.35, 0.8)), radius=0.6,
        location=(1.1, 0.0, 0.6))
    cam = camera_at((0.0, -6.5, 2.0), (0.0, 0.3, 1.2))
    sun = sun_towards((0.5, 0.6, -1.0), 3.0)
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    tree = world.node_tree
    tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.3, 0.3, 1.0)
    scene.world = world
    variant = sys.argv[-2]
    floor = bpy.data.objects["floor"].active_material.node_tree
    def node(kind, tree=floor, **values):  # a new node of the floor's material, these input values
        made = tree.nodes.new(kind)
        for key, value in values.items():
            made.inputs[key].default_value = value
        return made
    def link(a, out, b, inp, tree=floor):
        tree.links.new(a.outputs[out], b.inputs[inp])
    principled, output = floor.nodes["Principled BSDF"], floor.nodes["Material Output"]
    if variant == "hdri_backdrop":
        # The common HDRI set-up: the HDRI lights, the camera sees a plain backdrop (Is Camera Ray).
        env = tree.nodes.new("ShaderNodeTexEnvironment")
        env.image = bpy.data.images.load(os.path.join(bpy.utils.system_resource("DATAFILES"), "studiolights",
                                                      "world", "sunrise.exr"))
        tree.links.new(env.outputs["Color"], tree.nodes["Background"].inputs["Color"])
        backdrop = tree.nodes.new("ShaderNodeBackground")
        backdrop.inputs["Color"].default_value = (0.05, 0.05, 0.08, 1.0)
        mix = tree.nodes.new("ShaderNodeMixShader")
        tree.links.new(tree.nodes.new("ShaderNodeLightPath").outputs["Is Camera Ray"], mix.inputs["Fac"])
        tree.links.new(tree.nodes["Background"].outputs[0], mix.inputs[1])
        tree.links.new(backdrop.outputs[0], mix.inputs[2])
        tree.links.new(mix.outputs[0], tree.nodes["World Output"].inputs["Surface"])
        bpy.data.objects.remove(sun)
    if variant == "ies_lamp":
        # A downlight's IES profile (type C, symmetric) on a point lamp's Emission Strength, in
        # place of the sun, under a dark world.
        profile = sys.argv[-1] + ".ies"
        with open(profile, "w") as handle:
            handle.write(chr(10).join(["IESNA:LM-63-2002", "TILT=NONE", "1 1000 1 7 1 1 2 0.1 0.1 0.0",
                                       "1.0 1.0 20", "0 15 30 45 60 75 90", "0", "3000 2500 1200 300 60 10 0", ""]))
        bpy.data.objects.remove(sun)
        tree.nodes["Background"].inputs["Color"].default_value = (0.02, 0.02, 0.02, 1.0)
        lamp = bpy.data.lights.new("downlight", "POINT")
        lamp.energy, lamp.shadow_soft_size, lamp.use_nodes = 20.0, 0.05, True
        texture = lamp.node_tree.nodes.new("ShaderNodeTexIES")
        texture.mode, texture.filepath = "EXTERNAL", profile
        emission = next(n for n in lamp.node_tree.nodes if n.type == "EMISSION")
        lamp.node_tree.links.new(texture.outputs[0], emission.inputs["Strength"])
        holder = bpy.data.objects.new("downlight", lamp)
        holder.location = (0.3, -0.5, 3.0)
        scene.collection.objects.link(holder)
    if variant == "mix_mask":
        # Two surfaces on the floor, a blue and the grey, mixed by a checker mask.
        mix = node("ShaderNodeMixShader")
        link(node("ShaderNodeTexChecker", Scale=5.0), "Fac", mix, "Fac")
        link(principled, 0, mix, 1)
        link(node("ShaderNodeBsdfPrincipled", **{"Base Color": (0.1, 0.3, 0.8, 1.0)}), 0, mix, 2)
        link(mix, 0, output, "Surface")
    if variant == "udim":
        # A UDIM image (two tiles: 1001 red, 1002 green) on the floor, whose UVs lie in tile 1002.
        stem = sys.argv[-1] + ".udim"
        for tile, rgb in ((1001, (0.8, 0.1, 0.1)), (1002, (0.1, 0.7, 0.2))):
            img = bpy.data.images.new(f"tile{tile}", 8, 8)
            img.pixels.foreach_set(np.tile([*rgb, 1.0], 64).astype(np.float32))
            img.filepath_raw, img.file_format = f"{stem}.{tile}.png", "PNG"
            img.save()
        udim = bpy.data.images.load(f"{stem}.1001.png")
        udim.source = "TILED"
        udim.filepath = f"{stem}.<UDIM>.png"
        udim.reload()
        for loop in bpy.data.objects["floor"].data.uv_layers.active.data:
            loop.uv = (loop.uv[0] + 1.0, loop.uv[1])
        image = node("ShaderNodeTexImage")
        image.image = udim
        link(image, "Color", principled, "Base Color")
    if variant == "shadow_catcher":
        bpy.data.objects["floor"].is_shadow_catcher = True
    if variant == "roughness_checker":
        # Roughness 0 and 1 in squares on the floor (a Roughness map, baked from the checker).
        link(node("ShaderNodeTexChecker", Scale=4.0), "Fac", principled, "Roughness")
    if variant == "depth_of_field":
        # A wide aperture focused on the cube over a checkered floor and wall: what lies nearer
        # and farther blurs.
        cam.data.dof.use_dof = True
        cam.data.dof.aperture_fstop = 0.05
        cam.data.dof.focus_object = bpy.data.objects["cube"]
        link(node("ShaderNodeTexChecker", Scale=30.0), "Color", principled, "Base Color")
    if variant == "displacement_wave":
        # A procedural height (Wave bands) into the Material Output's Displacement (Bump Only).
        displace = node("ShaderNodeDisplacement", Scale=0.3)
        link(node("ShaderNodeTexWave", Scale=3.0), "Fac", displace, "Height")
        link(displace, "Displacement", output, "Displacement")
    if variant == "bump_noise":
        # The common node set-up: a Noise texture's Fac into a Bump node on the BSDF's Normal.
        bump = node("ShaderNodeBump", Distance=1.0)
        link(node("ShaderNodeTexNoise", Scale=2.0), "Fac", bump, "Height")
        link(bump, "Normal", principled, "Normal")
    if variant == "metallic_checker":
        # A metallic mask from a texture (PBR assets' Metallic map): half the floor is metal.
        floor = bpy.data.objects["floor"].active_material.node_tree
        checker = floor.nodes.new("ShaderNodeTexChecker")
        checker.inputs["Scale"].default_value = 4.0
        floor.links.new(checker.outputs["Fac"], floor.nodes["Principled BSDF"].inputs["Metallic"])
    if variant == "metallic_image":
        # The same from a mask image (Non-Color) straight into Metallic, read without a bake.
        import numpy as np
        mask = bpy.data.images.new("mask", 32, 32)
        pixels = np.ones((32, 32, 4), np.float32)
        pixels[:, :16, :3] = 0.0
        mask.pixels.foreach_set(pixels.ravel())
        mask.filepath_raw, mask.file_format = sys.argv[-1] + ".mask.png", "PNG"
        mask.save()
        mask.colorspace_settings.name = "Non-Color"
        floor = bpy.data.objects["floor"].active_material.node_tree
        image = floor.nodes.new("ShaderNodeTexImage")
        image.image, image.interpolation = mask, "Closest"
        floor.links.new(image.outputs["Color"], floor.nodes["Principled BSDF"].inputs["Metallic"])
    if variant == "metal_reflecting_metal":
        # A rough metal floor and a rough metal ball (Metallic 1, roughness 0.5) under the sun.
        for name in ("floor", "ball"):
            tree = bpy.data.objects[name].active_material.node_tree
            tree.nodes["Principled BSDF"].inputs["Metallic"].default_value = 1.0
    if variant == "holdout_object":
        bpy.data.objects["ball"].is_holdout = True
    if variant == "holdout_collection":
        holes = bpy.data.collections.new("holes")
        scene.collection.children.link(holes)
        scene.collection.objects.unlink(bpy.data.objects["ball"])
        holes.objects.link(bpy.data.objects["ball"])
        scene.view_layers[0].layer_collection.children["holes"].holdout = True
    if variant == "holdout_shader":
        tree = bpy.data.objects["ball"].active_material.node_tree
        tree.links.new(tree.nodes.new("ShaderNodeHoldout").outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    if variant in ("pane_no_shadow", "pane_shadow_ray_mix"):
        # A 3 m pane over the objects that lets the sun through: hidden from shadow rays, or the
        # archviz glass trick, Mix(Principled, Transparent BSDF) by Light Path > Is Shadow Ray.
        pane = add(bpy.ops.mesh.primitive_plane_add, "pane", material("pane", (0.8, 0.8, 0.8)), size=3.0,
                   location=(0.0, 0.0, 2.3))
        if variant == "pane_no_shadow":
            pane.visible_shadow = False
        else:
            tree = pane.active_material.node_tree
            mix = tree.nodes.new("ShaderNodeMixShader")
            tree.links.new(tree.nodes.new("ShaderNodeLightPath").outputs["Is Shadow Ray"], mix.inputs["Fac"])
            tree.links.new(tree.nodes["Principled BSDF"].outputs[0], mix.inputs[1])
            tree.links.new(tree.nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[2])
            tree.links.new(mix.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    if variant in ("attribute_ramp", "color_attribute_ramp"):
        # A float attribute per point (what Geometry Nodes' Store Named Attribute leaves) read by
        # an Attribute node into a Color Ramp on the floor's Base Color, over a 16 x 16 grid.
        ground = bpy.data.objects["floor"]
        grid = ground.modifiers.new("grid", "SUBSURF")
        grid.subdivision_type, grid.levels, grid.render_levels = "SIMPLE", 4, 4
        bpy.context.view_layer.objects.active = ground
        bpy.ops.object.modifier_apply(modifier="grid")
        xs = np.array([v.co.x for v in ground.data.vertices])
        values = (0.5 + 0.5 * np.sin(2.0 * xs)).astype(np.float32)
        if variant == "attribute_ramp":
            ground.data.attributes.new("height", "FLOAT", "POINT").data.foreach_set("value", values)
        else:  # a colour attribute of the same values, grey
            rgba = np.stack([values, values, values, np.ones_like(values)], axis=1).ravel()
            ground.data.color_attributes.new("height", "FLOAT_COLOR", "POINT").data.foreach_set("color", rgba)
        ramp = node("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].color = (0.8, 0.1, 0.1, 1.0)
        ramp.color_ramp.elements[1].color = (0.1, 0.7, 0.2, 1.0)
        reader = node("ShaderNodeAttribute")
        reader.attribute_name = "height"
        link(reader, "Fac", ramp, "Fac")
        link(ramp, "Color", principled, "Base Color")
    if variant == "half_bright_world":
        # No sun: a world bright behind the camera only (Generated y < 0), the Glossy passes on.
        bpy.data.objects.remove(sun)
        coords, split = tree.nodes.new("ShaderNodeTexCoord"), tree.nodes.new("ShaderNodeSeparateXYZ")
        side = tree.nodes.new("ShaderNodeMath")
        side.operation = "LESS_THAN"
        side.inputs[1].default_value = 0.0
        tree.links.new(coords.outputs["Generated"], split.inputs[0])
        tree.links.new(split.outputs["Y"], side.inputs[0])
        colour = tree.nodes.new("ShaderNodeMix")
        colour.data_type = "RGBA"
        colour.inputs[6].default_value = (0.05, 0.05, 0.05, 1.0)
        colour.inputs[7].default_value = (1.0, 1.0, 1.0, 1.0)
        tree.links.new(side.outputs[0], colour.inputs[0])
        tree.links.new(colour.outputs[2], tree.nodes["Background"].inputs["Color"])
        for flag in ("glossy_direct", "glossy_indirect", "glossy_color"):
            setattr(scene.view_layers[0], f"use_pass_{flag}", True)
    if variant == "material_override":
        # View Layer > Filter > Material Override: a clay render of every surface.
        scene.view_layers[0].material_override = material("clay", (0.5, 0.5, 0.5))
    if variant == "displacement_image":
        # A height image into the Material Output's Displacement (Bump Only, Cycles' default).
        import numpy as np
        height = bpy.data.images.new("height", 64, 64)
        pixels = np.ones((64, 64, 4), np.float32)
        pixels[..., :3] = (0.5 + 0.5 * np.sin(np.arange(64) / 64 * 2 * np.pi * 4))[None, :, None]
        height.pixels.foreach_set(pixels.ravel())
        height.filepath_raw, height.file_format = sys.argv[-1] + ".height.png", "PNG"
        height.save()
        height.colorspace_settings.name = "Non-Color"
        floor = bpy.data.objects["floor"].active_material.node_tree
        image = floor.nodes.new("ShaderNodeTexImage")
        image.image = height
        displace = floor.nodes.new("ShaderNodeDisplacement")
        displace.inputs["Scale"].default_value = 0.3
        floor.links.new(image.outputs["Color"], displace.inputs["Height"])
        floor.links.new(displace.outputs["Displacement"], floor.nodes["Material Output"].inputs["Displacement"])
    if variant == "particle_hair":
        # Old-style hair: a Hair particle system (400 strands, 0.6 m) on a patch of ground.
        patch = add(bpy.ops.mesh.primitive_plane_add, "patch", material("green", (0.2, 0.7, 0.2)), size=1.8,
                    location=(-0.2, -0.8, 0.01))
        settings = patch.modifiers.new("hair", "PARTICLE_SYSTEM").particle_system.settings
        settings.type, settings.count, settings.hair_length = "HAIR", 400, 0.6
        settings.root_radius, settings.radius_scale = 1.0, 0.04
    if variant in ("hair", "hair_melanin"):
        # A patch of grass as a Curves (hair) object: 400 strands of 6 points, 2 cm radius.
        import numpy as np
        hair = bpy.data.hair_curves.new("grass")
        rng = np.random.default_rng(1)
        hair.add_curves([6] * 400)
        roots = np.column_stack([rng.uniform(-1.1, 0.7, 400), rng.uniform(-1.2, -0.4, 400), np.zeros(400)])
        points = roots[:, None, :] + np.array([0.0, 0.0, 0.12])[None, None, :] * np.arange(6)[None, :, None]
        hair.position_data.foreach_set("vector", points.astype(np.float32).ravel())
        radius = hair.attributes.get("radius") or hair.attributes.new("radius", "FLOAT", "POINT")
        radius.data.foreach_set("value", np.full(2400, 0.02, np.float32))
        hair.materials.append(material("green", (0.2, 0.7, 0.2)))
        if variant == "hair_melanin":
            # Brown hair: a Principled Hair BSDF of melanin 0.6, redness 0.5.
            fibre = hair.materials[0].node_tree
            hair_bsdf = node("ShaderNodeBsdfHairPrincipled", tree=fibre)
            hair_bsdf.parametrization = "MELANIN"
            hair_bsdf.inputs["Melanin"].default_value = 0.6
            hair_bsdf.inputs["Melanin Redness"].default_value = 0.5
            link(hair_bsdf, 0, fibre.nodes["Material Output"], "Surface", tree=fibre)
        scene.collection.objects.link(bpy.data.objects.new("grass", hair))
    bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
""")


def build(tmp_path: Path, variant: str) -> Path:
    blend = tmp_path / f"{variant}.blend"
    subprocess.run([sys.executable, "-c", SCENE, variant, str(blend)], check=True, capture_output=True)
    return blend


def both(tmp_path: Path, blend: Path, *extra):
    """(HybridGI, Cycles) channels of `blend` at RES; a cache folder of the test's own, so world
    and material bakes run rather than come from an earlier run."""
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    return (rendered(blend, tmp_path / "hg", RES, *QUICK, *extra, env=env),
            rendered(blend, tmp_path / "cy", RES, *CYCLES, *extra, env=env))


def rel_l1(a, b) -> float:
    return float(np.abs(a - b).sum() / np.abs(b).sum())


def variant_errors(tmp_path: Path, variant: str, names, *extra):
    """({pass: rel L1 over Cycles' geometry pixels}, ours, Cycles', geometry) of a variant's renders."""
    ours, cycles = both(tmp_path, build(tmp_path, variant), *extra)
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    errors = {name: rel_l1(layer(ours, name)[geometry], layer(cycles, name)[geometry]) for name in names}
    print(errors)
    return errors, ours, cycles, geometry


def test_world_mixing_a_backdrop_by_is_camera_ray_lights_with_the_hdri(tmp_path):
    """Light Path > Is Camera Ray mixing a backdrop colour (what the camera sees) with an HDRI
    (what lights): the world is baked once per ray kind. Measured at 64x48: Combined over geometry
    0.920 -> 0.042 (before, the dark backdrop lit the scene: mean 0.034 vs Cycles' 0.425). At
    128x96 with a uniform warm light colour instead of the HDRI: 0.494 -> 0.006."""
    ours, cycles = both(tmp_path, build(tmp_path, "hdri_backdrop"))
    sky = layer(cycles, "Depth", "Z")[..., 0] >= 1e9
    assert sky.any() and (~sky).any()
    combined, reference = layer(ours, "Combined"), layer(cycles, "Combined")
    error = rel_l1(combined[~sky], reference[~sky])
    print(f"Combined over geometry {error:.3f}, means {combined[~sky].mean():.3f} vs {reference[~sky].mean():.3f}")
    assert error < 0.08, error
    np.testing.assert_allclose(combined[sky].mean(0), reference[sky].mean(0), rtol=0.05)


@pytest.mark.parametrize("variant", ["metallic_checker", "metallic_image"])
def test_metallic_from_a_texture_is_followed_per_pixel(tmp_path, variant):
    """A Checker on the floor's Metallic: Cycles bakes it over the mesh's atlas with the base
    colour; the diffuse colour is base x (1 - metallic) per texel and each pixel's glossy lobes
    are its material's variant nearest the texel's metallic (`glossy.METALLIC_STEPS`). Before,
    the Metallic read as its socket's value, 0: the metal squares were diffuse grey. Measured
    here (64x48): Diffuse Color 0.633 -> 0.008, Diffuse Direct 0.430 -> 0.048, Combined 0.319 ->
    0.050 (0.207 with the diffuse per texel but every pixel's lobes at the mean metallic); with
    a wall behind, 128x96, default settings: 0.927 -> 0.011, 0.692 -> 0.059, 0.253 -> 0.112.
    Ray hits take their texel's glossy albedo too (`shading._metal_glossy`), and a hit on metal
    reflects the lamps only in its highlight (`pixel_gather._shiny_hits`): before, the mean
    metallic gave every hit of the floor half a metal's glossy light, spread as diffuse light.
    Measured here, checker / image: Diffuse Indirect 0.324 / 0.405 -> 0.240 / 0.222, Combined
    0.045 / 0.059 -> 0.035 / 0.038."""
    ours, cycles = both(tmp_path, build(tmp_path, variant))
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    errors = {name: rel_l1(layer(ours, name)[geometry], layer(cycles, name)[geometry])
              for name in ("Diffuse Color", "Diffuse Direct", "Diffuse Indirect", "Combined")}
    print(errors)
    assert errors["Diffuse Color"] < 0.05 and errors["Diffuse Direct"] < 0.1, errors
    assert errors["Diffuse Indirect"] < 0.3 and errors["Combined"] < 0.045, errors


def test_metal_reflects_the_sun_in_metal(tmp_path):
    """A rough metal floor reflecting a rough metal ball and itself under the sun: a reflection
    ray that meets the metal ball sees the sun in the ball's highlight (`pixel_gather.
    _add_shiny_highlights`); before, the metal's lamp light was dropped at reflection-ray hits
    (their glossy share reflects the cache's light only). bench/artist_scenes.py metallic_const
    (the same with a metal wall), 128x96: Combined 0.306 -> 0.087, Glossy Indirect 0.100 -> 0.317
    against Cycles' 0.291. Here (64x48): 0.100 -> 0.062."""
    ours, cycles = both(tmp_path, build(tmp_path, "metal_reflecting_metal"))
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    error = rel_l1(layer(ours, "Combined")[geometry], layer(cycles, "Combined")[geometry])
    print(f"Combined {error:.3f}")
    assert error < 0.08, error


@pytest.mark.parametrize("variant", ["hair", "particle_hair"])
def test_hair_curves_render_as_strands(tmp_path, variant):
    """A Curves object (hair, grass), or a Hair particle system on a patch of ground, was dropped
    without a word (Cycles renders their strands); now each strand is a tube through its points
    (`hybridgi_core.hair`; particle paths from `ParticleSystem.co_hair`). Measured here (64x48,
    quick settings), Curves / particles: Combined over geometry 0.269 / 0.176 -> 0.037 / 0.031,
    Diffuse Color on the grass 0.854 / 0.354 -> 0.011 / 0.014; smaller patches at 128x96, default
    settings: Combined 0.049 / 0.038 -> 0.012 / 0.013."""
    ours, cycles = both(tmp_path, build(tmp_path, variant))
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    colour = layer(cycles, "Diffuse Color")
    grass = geometry & (colour[..., 1] > 1.5 * colour[..., 0]) & (colour[..., 1] > 1.5 * colour[..., 2])
    assert grass.sum() > 50
    errors = {"Combined": rel_l1(layer(ours, "Combined")[geometry], layer(cycles, "Combined")[geometry]),
              "grass Diffuse Color": rel_l1(layer(ours, "Diffuse Color")[grass], colour[grass])}
    print(errors)
    assert errors["Combined"] < 0.07 and errors["grass Diffuse Color"] < 0.1, errors


@pytest.mark.parametrize("variant", ["holdout_object", "holdout_collection", "holdout_shader"])
def test_holdouts_cut_a_transparent_hole(tmp_path, variant):
    """The ball as a holdout (Object > Visibility > Holdout, a holdout collection, a Holdout
    shader): Cycles' Combined is 0 with alpha 0 there, even on an opaque film, and its Depth the
    background's; the ball still casts its shadow. Before, the object and collection rendered as
    any object (warned) and the shader black with alpha 1. Measured here (64x48): mean alpha
    1.000 -> 0.934 (Cycles 0.932), Combined over the hole 0.422 -> 0.012 (0.015; the shader's
    was 0.014 already); 128x96, default settings: Combined over the image 0.028 -> 0.010."""
    ours, cycles = both(tmp_path, build(tmp_path, variant))
    combined, reference = layer(ours, "Combined", "RGBA"), layer(cycles, "Combined", "RGBA")
    hole = reference[..., 3] < 0.5
    assert 20 < hole.sum() < 0.3 * hole.size
    print(f"alpha {combined[..., 3].mean():.3f} vs {reference[..., 3].mean():.3f}, "
          f"hole Combined {combined[hole][:, :3].mean():.3f} vs {reference[hole][:, :3].mean():.3f}")
    assert abs(float(combined[..., 3].mean() - reference[..., 3].mean())) < 0.01
    assert float(np.abs(combined[hole] - reference[hole]).mean()) < 0.02
    assert (layer(ours, "Depth", "Z")[hole] >= 1e9).mean() > 0.9
    geometry = ~hole & (layer(cycles, "Depth", "Z")[..., 0] < 1e9)
    assert rel_l1(combined[geometry][:, :3], reference[geometry][:, :3]) < 0.06


@pytest.mark.parametrize("variant", ["pane_no_shadow", "pane_shadow_ray_mix"])
def test_surfaces_shadow_rays_pass_let_the_sun_through(tmp_path, variant):
    """A pane over the objects hidden from shadow rays (Object > Visibility), or made of the
    glass trick Mix(Principled, Transparent) by Light Path > Is Shadow Ray: Cycles' lamps shine
    through it, every other ray sees it. Shadow rays now pass such triangles
    (`EmbreeTracer.occluded_shadow`). Before, the pane shadowed the scene (the object flag was
    warned about; the mix read its factor as 0.5 and the surface as half transparent). Measured
    here (64x48; hidden / mix): Diffuse Direct 0.202 / 0.200 -> 0.019 / 0.019 (mean 0.608 ->
    0.750, Cycles 0.750), Combined 0.159 / 0.214 -> 0.025 / 0.025."""
    ours, cycles = both(tmp_path, build(tmp_path, variant))
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    direct, reference = layer(ours, "Diffuse Direct")[geometry], layer(cycles, "Diffuse Direct")[geometry]
    errors = {"Diffuse Direct": rel_l1(direct, reference),
              "Combined": rel_l1(layer(ours, "Combined")[geometry], layer(cycles, "Combined")[geometry]),
              "Diffuse Direct mean": (float(direct.mean()), float(reference.mean()))}
    print(errors)
    assert errors["Diffuse Direct"] < 0.1 and errors["Combined"] < 0.1, errors


def test_a_principled_hair_bsdf_is_a_fibre_of_its_melanins_colour(tmp_path):
    """Grass curves under a Principled Hair BSDF of melanin 0.6 (brown hair): it was not
    supported (grey 0.8, warned). It is rendered as a diffuse fibre of the colour Cycles' melanin
    absorption gives, brightened as a lock scatters (`sync._hair_colour`). On the hair's pixels
    (no Diffuse Color in Cycles: hair is not a diffuse closure) the mean Combined was grey 0.57
    against Cycles' dark brown 0.05 and is now within 5%; the image's Combined, 64x48: 0.391 ->
    0.031 (128x96: 0.056 -> 0.011; on the hair's pixels rel L1 18.8 -> 0.30)."""
    errors, ours, cycles, geometry = variant_errors(tmp_path, "hair_melanin", ("Combined",))
    fibres = geometry & (layer(cycles, "Diffuse Color").sum(axis=-1) < 1e-4)
    assert fibres.sum() > 20
    mine, theirs = layer(ours, "Combined")[fibres].mean(axis=0), layer(cycles, "Combined")[fibres].mean(axis=0)
    print(mine, theirs)
    np.testing.assert_allclose(mine, theirs, rtol=0.25)
    assert errors["Combined"] < 0.04, errors


def test_an_ies_profile_shapes_its_lamps_light(tmp_path):
    """A point lamp whose Emission Strength is an IES Texture (a downlight's candela table):
    Cycles scales the lamp's radiance per direction by the table (`ies.py`, `Light.profile`).
    Before, the node was noted and the Strength's own value (1) used: the scene ~30x too dark.
    Measured here (64x48): Combined 0.987 -> 0.038; 128x96 against 128 spp + OIDN 0.965 -> 0.044.
    Cycles 4.2 and 4.5 render the same lamp 8% brighter than 5.0 (Diffuse Direct 3.71 against
    3.42; ours 3.39): 0.093 there."""
    errors = variant_errors(tmp_path, "ies_lamp", ("Combined", "Diffuse Direct"))[0]
    assert errors["Combined"] < 0.12 and errors["Diffuse Direct"] < 0.12, errors


def test_two_surfaces_mixed_by_a_mask_keep_each_texels_colour(tmp_path):
    """A Mix Shader of the grey and a blue Principled BSDF by a checker mask (a dirt or wear mask,
    a second material): Cycles mixes their closures per shading point. The mask is baked by
    Blender over the atlas and the parts' colours mixed per texel (`sync._texel_mix`; lobes and
    emission at its mean). Before, the factor took the socket's own value (warned). Measured here
    (64x48): Combined 0.219 -> 0.021, Diffuse Color 0.217 -> 0.006; 128x96 against 64 spp +
    OIDN: 0.266 -> 0.017."""
    errors = variant_errors(tmp_path, "mix_mask", ("Combined", "Diffuse Color"))[0]
    assert errors["Combined"] < 0.05 and errors["Diffuse Color"] < 0.03, errors


def test_a_udim_image_is_read_from_the_tile_its_uvs_pick(tmp_path):
    """A UDIM (tiled) image on the floor, whose UVs lie in its second tile: Cycles reads that
    tile. The image reader took the first tile's pixels for every UV (wrapped); a tiled image is
    now baked by Blender over the material's atlas, as colours through nodes are. Measured here
    (64x48): Combined 1.088 -> 0.021, Diffuse Color 0.936 -> 0.005."""
    errors = variant_errors(tmp_path, "udim", ("Combined", "Diffuse Color"))[0]
    assert errors["Combined"] < 0.05 and errors["Diffuse Color"] < 0.02, errors


@pytest.mark.parametrize("transparent", [False, True])
def test_a_shadow_catcher_shows_the_world_behind_it_times_its_shadows(tmp_path, transparent):
    """The floor as a shadow catcher: Cycles shows the world behind it times what the cube and
    ball do to its light (their shadows), writes no light passes there, and on a transparent film
    makes it black with the shadows as alpha (`catcher.py`). Before, it was rendered as a grey
    floor (warned): 128x96 against 64 spp + OIDN, Combined 0.431 -> 0.018, Diffuse Direct 1.23 ->
    0.018; transparent, alpha off by 0.004 on average. Here (64x48) the catcher's edge pixels
    weigh more: the film takes the centre raster's pixels as the catcher's, where Cycles' samples
    split an edge pixel (opaque Combined 0.039, Diffuse Direct 0.10 from the edges' dilution)."""
    extra = ("--set", "render.film_transparent=true") if transparent else ()
    errors, ours, cycles, geometry = variant_errors(tmp_path, "shadow_catcher", ("Combined", "Diffuse Direct"), *extra)
    alpha = float(np.abs(layer(ours, "Combined", "A") - layer(cycles, "Combined", "A"))[geometry].mean())
    print(alpha)
    assert errors["Combined"] < (0.12 if transparent else 0.06) and errors["Diffuse Direct"] < 0.15, errors
    assert alpha < 0.02, alpha


def test_a_roughness_texture_sets_each_pixels_diffuse_weight(tmp_path):
    """A checker of roughness 0 and 1 on the floor: Cycles' Principled BSDF weighs its diffuse
    base by what its specular layer leaves (less under a smooth layer at grazing views), per
    texel. The G-buffer interpolates the material's diffuse weights at roughnesses over its
    texture's range by the pixel's texel (`gbuffer.weight_table`, ROUGH_WEIGHT_ROWS); before,
    every pixel took the mean roughness's. Measured here (64x48): Diffuse Color 0.080 -> 0.003,
    Combined 0.083 -> 0.017; 128x96 against 64 spp + OIDN: 0.029 -> 0.002, 0.033 -> 0.008."""
    errors = variant_errors(tmp_path, "roughness_checker", ("Combined", "Diffuse Color"))[0]
    assert errors["Diffuse Color"] < 0.02 and errors["Combined"] < 0.04, errors


def test_a_view_layers_material_override_renders_every_surface_with_it(tmp_path):
    """View Layer > Filter > Material Override (a clay render): Cycles renders every surface with
    the override, the lamps and the world as they are (`sync.material_override`). Before, it was
    ignored without a word: the red cube and blue ball kept their colours. Measured here (64x48):
    Diffuse Color 0.467 -> 0.001, Combined 0.426 -> 0.013 (128x96 against 64 spp + OIDN: 0.451 ->
    0.008)."""
    errors = variant_errors(tmp_path, "material_override", ("Combined", "Diffuse Color"))[0]
    assert errors["Diffuse Color"] < 0.02 and errors["Combined"] < 0.04, errors


def test_reflection_rays_weigh_their_light_by_the_fresnel(tmp_path):
    """A floor (roughness 0.5, dielectric) reflecting a world bright only behind the camera, seen
    at a grazing angle: Cycles' Glossy Direct is the lobe's light over its albedo, Fresnel included in
    both, and a dielectric's Fresnel rises steeply towards the mirror direction; the reflection
    rays' samples are weighed by it (`glossy.traced_fresnel`). Before, by G2 / G1 alone, the lobe's
    tail (towards the bright side) weighed as much as its mirror direction. Measured here (64x48,
    the mean over geometry, Cycles' 64 samples): Glossy Direct 0.199 -> 0.150 (0.143); at 160x90
    against 512 spp 0.46 -> 0.08 (mean 0.160 -> 0.113, Cycles 0.110); city.exr 0.300 -> 0.048,
    night.exr 0.178 -> 0.051 (Combined 0.058 -> 0.021)."""
    errors, ours, cycles, geometry = variant_errors(tmp_path, "half_bright_world", ("Combined", "Glossy Direct"))
    mean, reference = layer(ours, "Glossy Direct")[geometry].mean(), layer(cycles, "Glossy Direct")[geometry].mean()
    print(f"Glossy Direct mean {mean:.4f} against {reference:.4f}")
    assert abs(mean / reference - 1.0) < 0.12 and errors["Combined"] < 0.04, (mean, reference, errors)


@pytest.mark.parametrize("variant", ["attribute_ramp", "color_attribute_ramp"])
def test_a_float_attribute_read_by_an_attribute_node_colours_the_floor(tmp_path, variant):
    """A per-point float attribute into a Color Ramp on a UV-mapped 16 x 16 floor: the material
    bake's mesh carries it (`sync._generic_attributes`), and the bake targets the atlas, not the
    mesh's own UV map (`material_bake_process`: Blender baked into the UV layout when the baked
    input read an attribute, and the G-buffer read that through the atlas: one colour per
    triangle; a Noise on the same floor baked right). Measured at 128x96 against 64 spp + OIDN: Combined 0.394 -> 0.012 (a colour
    attribute instead of the float: 0.217 -> 0.012)."""
    errors = variant_errors(tmp_path, variant, ("Combined", "Diffuse Color"))[0]
    assert errors["Diffuse Color"] < 0.03 and errors["Combined"] < 0.04, errors


def test_depth_of_field_blurs_as_cycles_thin_lens(tmp_path):
    """A camera with depth of field (f/0.05, focused on the cube by its focus object) over a
    checkered floor: each subframe of the pixel filter renders through its own lens point, the
    plane of focus kept in place (`raster/lens.py`). Before, everything was in focus (warned).
    Measured here (64x48): Combined 0.113 -> 0.047, Diffuse Color 0.114 -> 0.045; 160x120
    against 256 spp + OIDN 0.188 -> 0.049."""
    errors = variant_errors(tmp_path, "depth_of_field", ("Combined", "Diffuse Color"))[0]
    assert errors["Combined"] < 0.07 and errors["Diffuse Color"] < 0.07, errors


@pytest.mark.parametrize("variant, limit, ao_limit", [("displacement_image", 0.05, 0.038),
                                                      ("displacement_wave", 0.07, 0.055),
                                                      ("bump_noise", 0.024, 0.045)])
def test_displacement_renders_as_its_bump(tmp_path, variant, limit, ao_limit):
    """A height into a Displacement node on the Material Output (Cycles' default method, Bump
    Only, bends the shading normal as a Bump node of Distance = Scale), or into a Bump node on
    the BSDF's Normal. An image's height is read as it is; a procedural one (Wave bands, Noise)
    is baked by Blender over the material's atlas and bumped there (`sync.height_bakes`).
    Measured here (64x48; Diffuse Direct, Combined): the image 0.064 / 0.064 (ignored) -> 0.020
    / 0.019; the Wave 0.144 / 0.146 (the smooth normal) -> 0.040 / 0.036; the Noise bump 0.029 /
    0.036 -> 0.016 / 0.018. At 128x96 against Cycles 64 spp + OIDN, default settings, a wall
    behind, the Wave: Combined 0.199 -> 0.036. The AO pass counts the bent lobe's rays above the
    smooth surface only, as Cycles' does (`pixel_gather._ao_rays`): the Wave 0.084 -> 0.034, the
    image 0.042 -> 0.032 (128x96: 0.087 -> 0.028, 0.029 -> 0.024)."""
    ours, cycles = both(tmp_path, build(tmp_path, variant))
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    errors = {name: rel_l1(layer(ours, name)[geometry], layer(cycles, name)[geometry])
              for name in ("Diffuse Direct", "Combined", "Ambient Occlusion")}
    print(errors)
    assert errors["Diffuse Direct"] < limit and errors["Combined"] < limit, errors
    assert errors["Ambient Occlusion"] < ao_limit, errors
