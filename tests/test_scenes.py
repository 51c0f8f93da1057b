"""The project's own scenes: procedural snapshots (bpy-free) and the .blend builder (one bpy test)."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # blend_scenes is a folder of scripts, not an installed package

from blend_scenes import procedural  # noqa: E402
from hybridgi_core.snapshot import geometry_from_arrays  # noqa: E402

EXPECTED_LIGHTS = {
    "cornell": {"ceiling_light": "AREA"},
    "atrium": {"sun": "SUN"},
    "spheres": {"area_light": "AREA", "point_light": "POINT"},
    "car": {"sun": "SUN"},
    "animated": {"moving_light": "POINT"},
}


@pytest.fixture(scope="module")
def snapshots():
    """Every static scene's snapshot and the animated scene at frame 1, built once."""
    return {name: procedural.describe(name).snapshot() for name in procedural.SCENE_NAMES}


def _object_bounds(snap, name):
    index = [o.name for o in snap.objects].index(name)
    g = snap.geometry
    p = g.positions[g.triangles[g.object_index == index]].reshape(-1, 3)
    return p.min(axis=0), p.max(axis=0)


@pytest.mark.parametrize("name", procedural.SCENE_NAMES)
def test_scene_builds_with_materials_lights_and_world(snapshots, name):
    snap = snapshots[name]
    desc = procedural.describe(name)
    assert snap.geometry.triangle_count == desc.triangle_count > 0  # nothing dropped as degenerate
    assert [o.name for o in snap.objects] == [p.name for p in desc.parts]
    assert {m.name for m in snap.materials} == {p.material for p in desc.parts}
    assert {light.name: light.kind for light in snap.lights} == EXPECTED_LIGHTS[name]
    assert snap.world.color.shape == (3,)
    assert desc.camera.resolution == (640, 360)


@pytest.mark.parametrize("name", procedural.SCENE_NAMES)
def test_shading_normals_agree_with_windings(snapshots, name):
    g = snapshots[name].geometry
    corner_mean = g.normals[g.triangles].mean(axis=1)
    assert (np.einsum("ij,ij->i", g.face_normals(), corner_mean) > 0.3).all()


def test_cornell_bounds_and_inward_walls(snapshots):
    snap = snapshots["cornell"]
    lo, hi = snap.bounds()
    np.testing.assert_allclose(lo, [-1, -1, 0], atol=1e-6)
    np.testing.assert_allclose(hi, [1, 1, 2], atol=1e-6)
    g = snap.geometry
    centre = np.array([0.0, 0.0, 1.0])
    wall_ids = [i for i, o in enumerate(snap.objects) if o.name.endswith(("wall", "floor", "ceiling"))]
    walls = np.isin(g.object_index, wall_ids)
    to_centre = centre - g.positions[g.triangles[walls]].mean(axis=1)
    assert (np.einsum("ij,ij->i", g.face_normals()[walls], to_centre) > 0).all()
    red = [m.name for m in snap.materials].index("red")
    np.testing.assert_allclose(snap.materials[red].base_color, [0.63, 0.065, 0.05])
    light = snap.lights[0]
    assert light.shape == "SQUARE" and light.size == pytest.approx(0.5)
    np.testing.assert_allclose(light.direction, [0, 0, -1], atol=1e-6)
    assert 1.9 < light.position[2] < 2.0
    assert not snap.world.color.any()


def test_atrium_size_bounds_and_speed(snapshots):
    snap = snapshots["atrium"]
    assert snap.geometry.triangle_count >= 250_000
    lo, hi = snap.bounds()
    np.testing.assert_allclose(lo, [-8.5, -16.5, 0.0], atol=1e-5)
    np.testing.assert_allclose(hi, [8.5, 16.5, 12.0], atol=1e-5)
    sun = snap.lights[0]
    assert 4.0 <= sun.power <= 5.0 and sun.angle == pytest.approx(np.radians(1.0))
    assert sun.direction[2] < -0.5  # shines down through the open roof
    np.testing.assert_allclose(snap.world.color, [0.35, 0.45, 0.6])
    assert {"drape_red", "drape_green", "drape_blue"} <= {m.name for m in snap.materials}
    t0 = time.perf_counter()
    procedural.atrium()
    assert time.perf_counter() - t0 < 2.0


def test_spheres_have_an_emitter(snapshots):
    assert sum(bool(m.emission.any()) for m in snapshots["spheres"].materials) == 1


def test_scenes_are_deterministic():
    a, b = procedural.car(), procedural.car()
    np.testing.assert_array_equal(a.geometry.positions, b.geometry.positions)
    np.testing.assert_array_equal(a.geometry.triangles, b.geometry.triangles)


def test_camera_looks_at_its_target():
    cam = procedural.camera("cornell")
    m = cam.matrix()
    forward = np.subtract(cam.look_at, cam.location)
    np.testing.assert_allclose(-m[:3, 2], forward / np.linalg.norm(forward), atol=1e-12)
    assert m[2, 1] > 0  # camera up leans to world +Z
    np.testing.assert_allclose(m[:3, :3] @ m[:3, :3].T, np.eye(3), atol=1e-12)


def test_animated_ball_falls_squashes_and_bounces():
    frames = {f: procedural.animated_frame(f) for f in (1, 7, 13, 25)}
    lo1, hi1 = _object_bounds(frames[1], "ball")
    lo7, _ = _object_bounds(frames[7], "ball")
    lo13, hi13 = _object_bounds(frames[13], "ball")
    assert lo7[2] < lo1[2] - 0.5  # falling
    assert hi13[2] - lo13[2] < 0.8 * (hi1[2] - lo1[2])  # squashed at contact
    assert hi13[0] - lo13[0] > hi1[0] - lo1[0]  # and wider
    assert abs(lo13[2]) < 5e-3  # resting on the floor
    np.testing.assert_allclose(_object_bounds(frames[25], "ball")[0], lo1, atol=1e-5)  # bounced back up
    snap = frames[1]
    assert {o.name for o in snap.objects if o.dynamic} == {"ball", "bunny"}
    assert not np.allclose(frames[1].lights[0].position, frames[13].lights[0].position)


def test_animated_bunny_hops_and_accepts_a_real_mesh():
    lo1, _ = _object_bounds(procedural.animated_frame(1), "bunny")
    lo9, hi9 = _object_bounds(procedural.animated_frame(9), "bunny")
    assert abs(lo1[2]) < 1e-6 and lo9[2] > 0.1
    assert hi9[2] - lo9[2] == pytest.approx(procedural.BUNNY_HEIGHT, abs=1e-4)
    tetra = geometry_from_arrays([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0, 0, 0.1]],
                                 [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    snap = procedural.animated_frame(9, bunny=tetra)
    bunny = [o.name for o in snap.objects].index("bunny")
    assert int((snap.geometry.object_index == bunny).sum()) == 4


@pytest.mark.smoke
def test_build_cornell_blend(bpy_module, tmp_path):
    # This Python's bpy builds it: no Blender opens a file that a newer one saved.
    env = dict(os.environ, BLENDER_USER_RESOURCES=str(tmp_path / "bl_user"))
    result = subprocess.run(
        [sys.executable, str(ROOT / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(tmp_path)],
        capture_output=True, text=True, env=env, timeout=120,
    )
    assert result.returncode == 0, result.stderr
    path = tmp_path / "cornell.blend"
    assert path.exists()

    bpy = bpy_module
    bpy.ops.wm.open_mainfile(filepath=str(path))
    try:
        scene = bpy.context.scene
        desc = procedural.cornell_description()
        meshes = {o.name: o for o in scene.objects if o.type == "MESH"}
        assert set(meshes) == {p.name for p in desc.parts}
        lights = {o.name: o.data for o in scene.objects if o.type == "LIGHT"}
        assert set(lights) == {"ceiling_light"} and lights["ceiling_light"].type == "AREA"
        assert lights["ceiling_light"].energy == pytest.approx(40.0)
        assert scene.camera is not None and scene.camera.type == "CAMERA"
        assert (scene.render.resolution_x, scene.render.resolution_y) == (640, 360)
        assert meshes["left_wall"].material_slots[0].material.name == "red"
        assert scene.world.node_tree.nodes["Background"].inputs["Color"].default_value[:3] == pytest.approx((0, 0, 0))
        # Same world-space triangles, in the same order, as the procedural snapshot.
        snap = desc.snapshot()
        for i, part in enumerate(desc.parts):
            obj = meshes[part.name]
            me = obj.data
            me.calc_loop_triangles()
            loops = np.empty(3 * len(me.loop_triangles), np.int32)
            me.loop_triangles.foreach_get("loops", loops)
            corner_vert = np.empty(len(me.loops), np.int32)
            me.loops.foreach_get("vertex_index", corner_vert)
            co = np.empty(3 * len(me.vertices), np.float32)
            me.vertices.foreach_get("co", co)
            m = np.array(obj.matrix_world)
            world = co.reshape(-1, 3)[corner_vert[loops]] @ m[:3, :3].T + m[:3, 3]
            g = snap.geometry
            expected = g.positions[g.triangles[g.object_index == i]].reshape(-1, 3)
            np.testing.assert_allclose(world, expected, atol=1e-6)
    finally:
        bpy.ops.wm.read_homefile(use_empty=True)
