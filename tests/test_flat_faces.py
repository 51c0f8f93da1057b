"""Flat-shaded faces that are not planar (hybridgi_core/flat_faces.py): each triangle shaded by its
own plane, as Cycles shades it; and a displaced flat-shaded grid through the real engine against
Cycles rendered in the same test."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import flat_faces
from hybridgi_core.corner_triangles import from_sizes
from tests.cli_renders import STAGE_HELPERS, against_cycles, layer, pass_error, run_bpy


def _quad(lift: float):
    """One quad's corners (0, 0, 0) (1, 0, 0) (1, 1, lift) (0, 1, 0), its two triangles, and the
    corners' normal as Blender gives a flat face (Newell's normal)."""
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, lift], [0, 1, 0]], np.float32)
    triangles, tri_face = from_sizes(np.array([4], np.int32), positions) or (np.array([[0, 1, 2], [0, 2, 3]]),
                                                                               np.zeros(2, np.int64))
    newell = np.zeros(3)
    for i in range(4):
        a, b = positions[i].astype(np.float64), positions[(i + 1) % 4].astype(np.float64)
        newell += [(a[1] - b[1]) * (a[2] + b[2]), (a[2] - b[2]) * (a[0] + b[0]), (a[0] - b[0]) * (a[1] + b[1])]
    normals = np.tile(newell / np.linalg.norm(newell), (4, 1)).astype(np.float32)
    return positions, normals, np.asarray(triangles), np.asarray(tri_face)


def test_a_folded_flat_quads_triangles_take_their_own_planes():
    positions, normals, triangles, tri_face = _quad(0.8)
    bent = flat_faces.bent_flat_triangles(np.array([False]), positions, normals, triangles, tri_face)
    assert bent.tolist() == [0, 1]
    uvs = np.arange(8, dtype=np.float32).reshape(4, 2)
    tris, pos, nrm, uv, source = flat_faces.own_corners(bent, triangles, positions, normals, uvs)
    assert pos.shape == (10, 3) and tris.min() == 4  # six corners appended, the quad's four kept
    np.testing.assert_array_equal(source[4:], triangles.ravel())
    np.testing.assert_array_equal(pos[tris], positions[triangles])
    np.testing.assert_array_equal(uv[tris], uvs[triangles])
    for t in range(2):
        p = pos[tris[t]].astype(np.float64)
        own = np.cross(p[1] - p[0], p[2] - p[0])
        own /= np.linalg.norm(own)
        for c in tris[t]:
            np.testing.assert_allclose(nrm[c], own, atol=1e-6)
    # The two planes part: neither is the face's normal.
    assert np.dot(nrm[tris[0][0]], nrm[tris[1][0]]) < 0.9


def test_planar_or_smooth_faces_keep_their_corners():
    positions, normals, triangles, tri_face = _quad(0.0)
    assert flat_faces.bent_flat_triangles(np.array([False]), positions, normals, triangles, tri_face).size == 0
    # Nearly planar (float rounding, a tiny warp): kept too.
    positions, normals, triangles, tri_face = _quad(1e-5)
    assert flat_faces.bent_flat_triangles(np.array([False]), positions, normals, triangles, tri_face).size == 0
    # A smooth face keeps its corner normals however folded.
    positions, normals, triangles, tri_face = _quad(0.8)
    assert flat_faces.bent_flat_triangles(np.array([True]), positions, normals, triangles, tri_face).size == 0


SCENE = "import bpy\nfrom mathutils import Vector\n" + STAGE_HELPERS + """
bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
bpy.ops.mesh.primitive_grid_add(x_subdivisions=12, y_subdivisions=12, size=6)
grid = bpy.context.active_object  # flat-shaded, as a new grid is
texture = bpy.data.textures.new("clouds", "CLOUDS")
texture.noise_scale = 0.8
displace = grid.modifiers.new("displace", "DISPLACE")
displace.texture = texture
displace.strength = 0.8
grid.data.materials.append(material("ground", (0.8, 0.8, 0.8)))
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
scene.collection.objects.link(sun)
sun.rotation_euler = (0.7, 0.0, 0.5)
sun.data.energy = 3.0
camera_at((5.0, -6.0, 5.0), (0.0, 0.0, 0.0))
scene.world = bpy.data.worlds.new("world")
scene.world.color = (0.2, 0.25, 0.3)
bpy.ops.wm.save_as_mainfile(filepath=PATH)
"""


@pytest.mark.blender
@pytest.mark.slow
def test_a_displaced_flat_grid_is_shaded_facet_by_facet_as_in_cycles(tmp_path):
    """Each folded quad of a displaced flat-shaded grid lit by a sun: Combined 0.019 against Cycles
    256 spp at 96x54 (the faces' own normals, as before: 0.084)."""
    blend = tmp_path / "flat_wave.blend"
    run_bpy(SCENE, PATH=str(blend))
    ours, cycles, geometry = against_cycles(blend, tmp_path, "96x54")
    error = pass_error(ours, cycles, "Combined", geometry)
    print(f"Combined {error:.4f}")
    assert error < 0.04, error
    # The Normal pass is Cycles' facet by facet.
    cos = (layer(ours, "Normal", "XYZ") * layer(cycles, "Normal", "XYZ")).sum(axis=-1)[geometry]
    assert np.median(cos) > 0.99
