"""A room lit only by an emissive panel, through the real engine against Cycles rendered in the
same test: the pixels sample the emitter (`hybridgi_core/emitters.py`) instead of waiting for
their rays to hit it."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from tests.cli_renders import STAGE_HELPERS, layer, rendered

pytestmark = [pytest.mark.blender, pytest.mark.slow]

RES = "128x72"

SCENE = "import sys, math, bpy\nfrom mathutils import Vector\n" + STAGE_HELPERS + textwrap.dedent("""
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    def matte(name, color, emit=0.0):
        m = material(name, color, 0.8)
        if emit:
            bsdf = m.node_tree.nodes["Principled BSDF"]
            bsdf.inputs["Emission Color"].default_value = (1.0, 0.95, 0.85, 1.0)
            bsdf.inputs["Emission Strength"].default_value = emit
        return m
    def box(location, size, mat, inward=False):
        bpy.ops.mesh.primitive_cube_add(size=1.0, location=location)
        obj = bpy.context.object
        obj.scale = size
        obj.data.materials.append(mat)
        if inward:
            bpy.ops.object.mode_set(mode="EDIT")
            bpy.ops.mesh.flip_normals()
            bpy.ops.object.mode_set(mode="OBJECT")
    white = matte("white", (0.75, 0.75, 0.75))
    box((0, 0, 1.5), (5, 6, 3), white, inward=True)
    box((0.3, 0.8, 0.4), (1.2, 0.8, 0.8), white)
    box((-1.5, 2.0, 0.9), (0.8, 0.6, 1.8), matte("red", (0.7, 0.1, 0.1)))
    bpy.ops.mesh.primitive_plane_add(size=0.6, location=(0, 0.5, 2.98))
    panel = bpy.context.object
    panel.rotation_euler = (math.pi, 0, 0)
    if int(sys.argv[-2]) > 0:  # cut into many triangles: sampled by power, not in closed form
        bpy.ops.object.mode_set(mode="EDIT")
        bpy.ops.mesh.subdivide(number_cuts=int(sys.argv[-2]))
        bpy.ops.object.mode_set(mode="OBJECT")
    panel.data.materials.append(matte("panel", (0.8, 0.8, 0.8), emit=60.0))
    cam = camera_at((0.5, -2.7, 1.6), (0, 1.0, 1.0), lens=24)
    if "ortho" in sys.argv[-3]:  # an orthographic view beside a sun of strength 0
        cam.data.type = "ORTHO"
        cam.data.ortho_scale = 5.0
        sun_towards((0.3, 0.2, -1.0), 0.0)
    if "dome" in sys.argv[-3]:  # the room's roof gone, under a glowing sphere all around it
        bpy.data.objects["Cube"].scale = (5, 6, 0.02)
        bpy.ops.mesh.primitive_uv_sphere_add(radius=30, segments=32, ring_count=16)
        bpy.context.object.data.materials.append(matte("sky", (0.0, 0.0, 0.0), emit=1.0))
    world = bpy.data.worlds.new("w")
    world.color = (0, 0, 0)
    if world.node_tree is None:
        world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (0, 0, 0, 1)
    scene.world = world
    bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
""")


@pytest.mark.parametrize("cuts", [0, 6])
def test_a_room_lit_by_an_emissive_panel_has_cycles_direct_light(cuts):
    """Against the 128 spp here, pixels sampling the panel / rays alone: Diffuse Direct 0.028 /
    0.227, Combined 0.141 / 0.174 (its Diffuse Indirect is the rays' either way). The panel's two
    triangles in closed form, shadowed by the samples' share (`MeshLights._ratio_block`):
    Diffuse Direct 0.026 -> 0.010. Cut into 98 triangles it is sampled by power (`_block`), its
    light without shadows and its visibility filtered apart (`penumbra.filter_emitter_light`):
    Diffuse Direct 0.026 -> 0.018 (Combined 0.144 either way). The cache's probe hits sample the
    panel too (`solver.GISolver.hit_emitters`): Diffuse Indirect's sum against Cycles' 0.858 ->
    0.912 (two triangles) and 0.858 -> 0.870 (98); the ceiling 2 cm over the panel is lit many
    times brighter than the cell in front of it said."""
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as tmp:
        blend = Path(tmp) / "panel.blend"
        subprocess.run([sys.executable, "-c", SCENE, "room", str(cuts), str(blend)], check=True, capture_output=True)
        ours = rendered(blend, Path(tmp) / "hg", RES)
        cycles = rendered(blend, Path(tmp) / "cy", RES, "--engine", "CYCLES", "--samples", "128")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    errors = {}
    for name in ("Diffuse Direct", "Combined"):
        mine, reference = layer(ours, name), layer(cycles, name)
        errors[name] = float(np.abs(mine - reference)[geometry].sum() / np.abs(reference)[geometry].sum())
    mine, reference = layer(ours, "Diffuse Direct")[geometry], layer(cycles, "Diffuse Direct")[geometry]
    ratio = float(mine.sum() / reference.sum())
    bounce = float(layer(ours, "Diffuse Indirect")[geometry].sum() / layer(cycles, "Diffuse Indirect")[geometry].sum())
    print(errors, f"Diffuse Direct sum ratio {ratio:.3f}, Diffuse Indirect {bounce:.3f}")
    assert abs(ratio - 1.0) < 0.05, ratio  # the emitter's light counted once
    assert errors["Diffuse Direct"] < (0.015 if cuts == 0 else 0.022), errors
    assert errors["Combined"] < 0.16, errors
    if cuts == 0:
        assert bounce > 0.89, bounce


def test_many_triangle_emitters_under_an_orthographic_view_or_beside_a_sun_render(tmp_path):
    """Emitters sampled by power have their light filtered around the eye (`filter_emitter_light`);
    an orthographic view has none, and the lamps' eye is withheld beside any sun: both crashed
    the frame (IndexError) before. The panel's light still reaches the floor."""
    blend = tmp_path / "ortho.blend"
    subprocess.run([sys.executable, "-c", SCENE, "ortho", "6", str(blend)], check=True, capture_output=True)
    ours = rendered(blend, tmp_path / "hg", "96x54")
    geometry = layer(ours, "Depth", "Z")[..., 0] < 1e9
    assert geometry.any() and float(layer(ours, "Diffuse Direct")[geometry].mean()) > 0.05


def test_an_emitter_all_around_the_scene_is_left_to_the_rays(tmp_path):
    """A glowing sphere around the scene stands in for a world (`shading._enclosing_emitters`):
    sampled by area its light was grainy (160x90 against Cycles 1024 spp, Combined 0.054; by the
    rays 0.011). Against Cycles here, Diffuse Direct's sum within 5% and the image close."""
    blend = tmp_path / "dome.blend"
    subprocess.run([sys.executable, "-c", SCENE, "dome", "0", str(blend)], check=True, capture_output=True)
    ours = rendered(blend, tmp_path / "hg", RES)
    cycles = rendered(blend, tmp_path / "cy", RES, "--engine", "CYCLES", "--samples", "64")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    mine, reference = layer(ours, "Diffuse Direct")[geometry], layer(cycles, "Diffuse Direct")[geometry]
    ratio = float(mine.sum() / reference.sum())
    error = float(np.abs(layer(ours, "Combined") - layer(cycles, "Combined"))[geometry].sum()
                  / np.abs(layer(cycles, "Combined"))[geometry].sum())
    print(f"Diffuse Direct sum ratio {ratio:.3f}, Combined {error:.4f}")
    assert abs(ratio - 1.0) < 0.05, ratio
    assert error < 0.08, error
