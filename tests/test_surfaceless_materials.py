"""Materials whose output has no Surface shader, rendered as Cycles renders them (measured with
Cycles: a Volume-only material's mesh is invisible, to the camera and to shadows alike, whatever the
volume; an output with nothing linked is an opaque black surface). A fog box around a scene or a
smoke domain was an opaque grey box that hid everything inside it."""

from __future__ import annotations

import numpy as np
import pytest

from tests.cli_renders import LIT_SPHERE_STAGE, QUICK, layer, rendered, run_bpy

#: The lit stage with a 1.6 m box around the sphere, its material a Volume shader only (a fog of
#: density 0: Cycles shows what the box holds, unchanged) or nothing at all (`argv[2]`).
SCENE = (
    "import math, sys, bpy\n"
    + LIT_SPHERE_STAGE
    + """
sphere = bpy.context.object
mode = sys.argv[2]
if mode != "none":
    bpy.ops.mesh.primitive_cube_add(size=2.6)
    box = bpy.context.object
    mat = bpy.data.materials.new(mode)
    if mat.node_tree is None:  # before 5.0
        mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    out = tree.nodes["Material Output"]
    if mode == "fog":
        fog = tree.nodes.new("ShaderNodeVolumePrincipled")
        fog.inputs["Density"].default_value = 0.0
        tree.links.new(fog.outputs[0], out.inputs["Volume"])
    box.data.materials.append(mat)
bpy.context.scene.render.resolution_x, bpy.context.scene.render.resolution_y = 96, 54
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[1])
"""
)


@pytest.mark.blender
@pytest.mark.slow
def test_a_volume_box_is_invisible_and_an_empty_output_is_black(tmp_path):
    renders = {}
    for mode in ("none", "fog", "empty"):
        blend = tmp_path / f"{mode}.blend"
        run_bpy(SCENE, str(blend), mode)
        renders[mode] = rendered(blend, tmp_path / mode, "96x54", *QUICK)
    plain, fog, empty = (layer(renders[m], "Combined") for m in ("none", "fog", "empty"))
    # The fog box is a boundary only: the sphere, the floor and their shadows as without it.
    assert np.abs(fog - plain).mean() < 0.02 * plain.mean()
    # Nothing linked: the box is black wherever the camera sees it (it fills the view's middle).
    h, w = empty.shape[:2]
    assert empty[h // 2 - 5 : h // 2 + 5, w // 2 - 5 : w // 2 + 5].max() < 1e-3
    assert plain[h // 2 - 5 : h // 2 + 5, w // 2 - 5 : w // 2 + 5].min() > 0.05
