"""The Principled BSDF's specular layer through the real engine, against Cycles rendered in the same
test: a plane and a sphere with the default Principled settings (roughness 0.5, IOR 1.5, Specular
IOR Level 0.5) under an area lamp, in a black world (so the glossy light is the lamp's); its
area-lamp light is in closed form (`glossy_ltc`), the lamp samples' on smoother lobes (0.2)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from tests.cli_renders import layer, rendered

RES = "96x72"

pytestmark = [pytest.mark.blender, pytest.mark.slow]

SCENE = textwrap.dedent("""
    import sys, bpy
    from mathutils import Vector
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    def principled(name, colour):
        m = bpy.data.materials.new(name)
        m.use_nodes = True
        m.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (*colour, 1.0)
        m.node_tree.nodes["Principled BSDF"].inputs["Roughness"].default_value = float(sys.argv[-2])
        return m
    bpy.ops.mesh.primitive_plane_add(size=12.0)
    bpy.context.active_object.data.materials.append(principled("floor", (0.6, 0.5, 0.4)))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, location=(0.0, 0.0, 1.0), segments=64, ring_count=32)
    bpy.ops.object.shade_smooth()
    bpy.context.active_object.data.materials.append(principled("ball", (0.2, 0.4, 0.8)))
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location = (0.0, -7.0, 3.0)
    camera.rotation_euler = (Vector((0.0, 0.0, 0.8)) - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(camera)
    scene.camera = camera
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "AREA"))
    lamp.data.energy = 600.0
    lamp.data.size = 2.0
    lamp.location = (2.0, 2.0, 4.0)
    lamp.rotation_euler = (Vector((0.0, 0.0, 0.5)) - lamp.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(lamp)
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.0, 0.0, 0.0)
    for flag in ("use_pass_glossy_direct", "use_pass_glossy_indirect", "use_pass_glossy_color"):
        setattr(scene.view_layers[0], flag, True)
    bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
""")


def _error(mine, reference, mask):
    return float(np.abs(mine - reference)[mask].sum() / np.abs(reference)[mask].sum())


def _scene(folder, roughness: float):
    path = folder / "gloss.blend"
    subprocess.run([sys.executable, "-c", SCENE, str(roughness), str(path)], check=True, capture_output=True)
    return path


@pytest.fixture(scope="module")
def blend(tmp_path_factory):
    return _scene(tmp_path_factory.mktemp("gloss"), 0.5)


def test_diffuse_weight_and_glossy_direct_match_cycles(blend, tmp_path):
    ours = rendered(blend, tmp_path / "hg", RES)
    cycles = rendered(blend, tmp_path / "cy", RES, "--engine", "CYCLES", "--samples", "256")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    errors = {name: _error(layer(ours, name), layer(cycles, name), geometry)
              for name in ("Diffuse Color", "Glossy Color", "Glossy Direct", "Combined")}
    glossy = layer(cycles, "Glossy Direct") * layer(cycles, "Glossy Color")
    share = float(glossy[geometry].sum() / layer(cycles, "Combined")[geometry][:, :3].sum())
    # Measured against 512 spp: Diffuse Color 0.0025 (0.092 without the layer's weight), Glossy
    # Color 0.0094, Glossy Direct 0.047, Combined 0.0245 (0.161 without the glossy light, 17% of it).
    assert share > 0.1, share
    assert errors["Diffuse Color"] < 0.015, errors
    assert errors["Glossy Color"] < 0.03, errors
    assert errors["Glossy Direct"] < 0.15, errors
    assert errors["Combined"] < 0.06, errors
    # Glossy Indirect: the floor and ball reflect each other's bounced light (the cache's).
    bounced = layer(ours, "Glossy Indirect")
    assert np.isfinite(bounced).all() and bounced.min() >= 0.0 and bounced[geometry].max() > 0.0


def test_glossy_samples_trade_highlight_noise_for_rays(tmp_path):
    """Glossy Samples sets the lamp samples of the glossy lobes: 1 per pixel leaves the highlights
    noisy, the default 16 is close to a 128-sample render of the same frame. Roughness 0.2: the
    area lamp's light on rougher lobes is exact, with no samples (`glossy_ltc`)."""
    blend = _scene(tmp_path, 0.2)
    quick = ("--set", "warmup_iterations=2", "--set", "pixel_rays=8", "--set", "pixel_samples=1")
    many = layer(rendered(blend, tmp_path / "g128", RES, *quick, "--set", "glossy_samples=128"), "Glossy Direct")
    geometry = np.isfinite(many).all(axis=-1) & (many.max(axis=-1) > 0)
    errors = {k: _error(layer(rendered(blend, tmp_path / f"g{k}", RES, *quick, "--set", f"glossy_samples={k}"),
                              "Glossy Direct"), many, geometry)
              for k in (1, 16)}
    assert errors[1] > 2.0 * errors[16], errors
