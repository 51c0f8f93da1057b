"""A sun's highlight smaller than a pixel through the real engine, against Cycles rendered in the
same test: a smooth ball (Principled, roughness 0.05) and a rough metal torus under a sun of 1
degree. One glossy sample per pixel read the ball's highlight several times Cycles' light
(specular_aa.py); widened by the spread of the pixel's normals it reads close to it."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core.penumbra import dilate
from tests.cli_renders import STAGE_HELPERS, layer, rendered, run_bpy

RES = "128x72"

pytestmark = [pytest.mark.blender, pytest.mark.slow]

SCENE = "import math, bpy\nfrom mathutils import Vector\n" + STAGE_HELPERS + """
bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
bpy.ops.mesh.primitive_plane_add(size=20.0)
bpy.context.active_object.data.materials.append(material("floor", (0.5, 0.5, 0.5), 0.6))
bpy.ops.mesh.primitive_uv_sphere_add(radius=0.8, location=(-0.9, 0.0, 0.8), segments=64, ring_count=32)
bpy.ops.object.shade_smooth()
bpy.context.active_object.data.materials.append(material("ball", (0.6, 0.05, 0.05), 0.05))
bpy.ops.mesh.primitive_torus_add(location=(1.0, 0.2, 0.5), major_radius=0.6, minor_radius=0.25)
bpy.ops.object.shade_smooth()
metal = material("torus", (0.9, 0.9, 0.92), 0.3)
metal.node_tree.nodes["Principled BSDF"].inputs["Metallic"].default_value = 1.0
bpy.context.active_object.data.materials.append(metal)
camera_at((0.0, -5.0, 2.2), (0.0, 0.0, 0.5))
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.data.energy = 4.0
sun.data.angle = math.radians(1.0)
sun.rotation_euler = (math.radians(50), 0.0, math.radians(150))
scene.collection.objects.link(sun)
scene.world = bpy.data.worlds.new("world")
scene.world.color = (0.3, 0.35, 0.4)
bpy.ops.wm.save_as_mainfile(filepath=PATH)
"""


def test_subpixel_sun_highlights_match_cycles(tmp_path):
    blend = tmp_path / "sun_highlight.blend"
    run_bpy(SCENE, PATH=str(blend))
    ours = layer(rendered(blend, tmp_path / "hg", RES), "Combined")
    cycles = layer(rendered(blend, tmp_path / "cy", RES, "--engine", "CYCLES", "--samples", "512"), "Combined")
    # The highlights: Cycles' pixels brighter than 5 (the lit floor is ~0.6), grown by 2 pixels.
    highlights = dilate(cycles.mean(axis=-1) > 5.0, 2)
    assert 50 < highlights.sum() < 400
    err = float(np.abs(ours - cycles)[highlights].sum() / cycles[highlights].sum())
    # Measured: 0.241; one glossy sample per pixel without widening 0.389 (the ball's highlight
    # missed: 1.4 against Cycles' 31 in its brightest pixel; the torus's 71 against 39).
    assert err < 0.3, err
    whole = float(np.abs(ours - cycles).sum() / np.abs(cycles).sum())
    assert whole < 0.12, whole  # measured 0.104 (0.137 without widening)
