"""Scenes of issue #12's kinds, built with bpy: fine detail that a cache cell cannot resolve.

    python bench/fine_detail_scenes.py OUT_DIR [NAME ...]

- yard: a 60 m courtyard under sun + sky: lamp posts (10 cm), railings (4 cm bars), a pavilion
  whose eaves overhang its columns, a low wall; the camera at eye height.
- contact: a room corner with a table on thin legs, a chair, a box and a ball resting on the
  floor, lit by an area lamp and a dim sky: contact shadows and colour bleeding finer than a cell.
- trusses: an attic under a gable roof with a row of 8 cm trusses, sun through a roof opening and
  a warm area lamp.
- scatter: 6,561 half-buried rocks 0.3 m across (a jittered 81 x 81 grid of icospheres, one mesh)
  on a ground plane under sun + a uniform sky: clutter far finer than a cache cell, where most of
  the bounce light between rocks comes from more than one bounce (issue #12's dense case).

Every surface is a plain diffuse Principled BSDF (no specular) so that Cycles' Diffuse passes hold
all of the light. Run in its own process (it resets the bpy module's file).
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

# ruff: noqa: I001  (bpy must come first: importing it makes bmesh and mathutils importable)
import bpy
import bmesh

WIDTH, HEIGHT = 320, 240


def _reset():
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    scene.frame_start = scene.frame_end = scene.frame_current = 1
    return scene


def _material(name, color):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bsdf.inputs["Roughness"].default_value = 1.0
    return mat


def _mesh_object(scene, name, build, material, location, smooth=False):
    """An object of a mesh that `build(bm)` makes with bmesh, in `material`, at `location`."""
    bm = bmesh.new()
    build(bm)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    if smooth:
        for poly in mesh.polygons:
            poly.use_smooth = True
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    scene.collection.objects.link(obj)
    return obj


def _box(scene, name, lo, hi, material, rot_z=0.0):
    """An axis-aligned box from corner lo to corner hi (metres), optionally turned about Z."""
    centre = [(a + b) / 2 for a, b in zip(lo, hi, strict=True)]
    obj = _mesh_object(scene, name, lambda bm: bmesh.ops.create_cube(bm, size=1.0), material, centre)
    obj.scale = [max(b - a, 1e-4) for a, b in zip(lo, hi, strict=True)]
    obj.rotation_euler = (0.0, 0.0, rot_z)
    return obj


def _cylinder(scene, name, x, y, radius, height, material, z0=0.0, segments=16):
    def build(bm):
        bmesh.ops.create_cone(bm, cap_ends=True, segments=segments, radius1=radius, radius2=radius, depth=height)

    return _mesh_object(scene, name, build, material, (x, y, z0 + height / 2))


def _sphere(scene, name, location, radius, material):
    def build(bm):
        bmesh.ops.create_uvsphere(bm, u_segments=32, v_segments=16, radius=radius)

    return _mesh_object(scene, name, build, material, location, smooth=True)


def _camera(scene, location, target, lens=24.0):
    cam = bpy.data.cameras.new("camera")
    cam.lens = lens
    cam.clip_start, cam.clip_end = 0.05, 500.0
    obj = bpy.data.objects.new("camera", cam)
    obj.location = location
    d = [t - p for t, p in zip(target, location, strict=True)]
    obj.rotation_euler = (math.atan2(math.hypot(d[0], d[1]), -d[2]), 0.0, math.atan2(d[1], d[0]) - math.pi / 2)
    scene.collection.objects.link(obj)
    scene.camera = obj


def _sun(scene, strength, elevation, azimuth, angle_deg=1.0):
    sun = bpy.data.lights.new("sun", "SUN")
    sun.energy = strength
    sun.angle = math.radians(angle_deg)
    obj = bpy.data.objects.new("sun", sun)
    obj.rotation_euler = (math.radians(90.0 - elevation), 0.0, math.radians(azimuth))
    scene.collection.objects.link(obj)


def _area(scene, name, location, size, power, color=(1.0, 1.0, 1.0)):
    lamp = bpy.data.lights.new(name, "AREA")
    lamp.energy, lamp.size, lamp.color = power, size, color
    obj = bpy.data.objects.new(name, lamp)
    obj.location = location
    scene.collection.objects.link(obj)


def _world(scene, color, strength=1.0):
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    bg.inputs["Color"].default_value = (*color, 1.0)
    bg.inputs["Strength"].default_value = strength
    scene.world = world


def yard():
    scene = _reset()
    stone = _material("stone", (0.55, 0.5, 0.45))
    metal = _material("iron", (0.12, 0.12, 0.13))
    wood = _material("wood", (0.45, 0.25, 0.12))
    plaster = _material("plaster", (0.8, 0.78, 0.72))
    _box(scene, "ground", (-30, -30, -0.2), (30, 30, 0.0), stone)
    for i in range(-3, 4):  # lamp posts along the path
        _cylinder(scene, f"post_{i}", 2.5, i * 6.0, 0.06, 4.0, metal)
        _box(scene, f"lamp_{i}", (2.3, i * 6.0 - 0.2, 4.0), (2.7, i * 6.0 + 0.2, 4.3), metal)
    for i in range(24):  # a railing: bars and a top rail
        _box(scene, f"bar_{i}", (-2.02, -12 + i, 0.0), (-1.98, -11.96 + i, 1.0), metal)
    _box(scene, "rail", (-2.05, -12.0, 1.0), (-1.95, 12.0, 1.06), metal)
    for x, y in ((6, 6), (14, 6), (6, 14), (14, 14)):  # a pavilion with overhanging eaves
        _box(scene, f"column_{x}_{y}", (x - 0.2, y - 0.2, 0.0), (x + 0.2, y + 0.2, 3.0), plaster)
    _box(scene, "roof", (4.5, 4.5, 3.0), (15.5, 15.5, 3.3), wood)
    _box(scene, "wall", (-12, 4, 0.0), (-11.6, 20, 1.5), plaster)
    _box(scene, "bench", (-6, -2, 0.4), (-4, -1.5, 0.45), wood)
    for x in (-5.9, -4.1):
        _box(scene, f"bench_leg_{x}", (x - 0.03, -1.8, 0.0), (x + 0.03, -1.7, 0.4), wood)
    _sun(scene, 4.0, elevation=35.0, azimuth=40.0)
    _world(scene, (0.35, 0.5, 0.8), 0.8)
    _camera(scene, (-5.0, -11.0, 1.7), (6.0, 8.0, 1.2), lens=20.0)


def contact():
    scene = _reset()
    floor = _material("floor", (0.7, 0.7, 0.68))
    wall = _material("wall", (0.75, 0.72, 0.65))
    red = _material("red", (0.7, 0.12, 0.1))
    wood = _material("wood", (0.5, 0.3, 0.15))
    blue = _material("blue", (0.1, 0.2, 0.6))
    _box(scene, "floor", (-3, -3, -0.05), (3, 3, 0.0), floor)
    _box(scene, "wall_back", (-3, 3.0, 0.0), (3, 3.1, 2.5), wall)
    _box(scene, "wall_left", (-3.1, -3, 0.0), (-3.0, 3.1, 2.5), wall)
    _box(scene, "table_top", (-1.0, 0.5, 0.72), (0.6, 1.5, 0.76), wood)
    for x in (-0.95, 0.55):
        for y in (0.55, 1.45):
            _box(scene, f"table_leg_{x}_{y}", (x - 0.025, y - 0.025, 0.0), (x + 0.025, y + 0.025, 0.72), wood)
    _box(scene, "seat", (0.8, 0.2, 0.44), (1.25, 0.65, 0.47), blue)
    _box(scene, "back", (1.22, 0.2, 0.47), (1.25, 0.65, 0.95), blue)
    for x in (0.82, 1.23):
        for y in (0.22, 0.63):
            _box(scene, f"chair_leg_{x}_{y}", (x - 0.015, y - 0.015, 0.0), (x + 0.015, y + 0.015, 0.44), blue)
    _box(scene, "crate", (-2.4, -0.6, 0.0), (-1.7, 0.1, 0.5), red)
    _sphere(scene, "ball", (-0.3, -0.8, 0.25), 0.25, red)
    _area(scene, "lamp", (0.5, -0.5, 2.4), 1.0, 300.0)
    _world(scene, (0.3, 0.32, 0.35), 0.5)
    _camera(scene, (2.6, -3.4, 1.6), (-0.6, 0.8, 0.4), lens=26.0)


def trusses():
    scene = _reset()
    wood = _material("wood", (0.55, 0.35, 0.2))
    floor = _material("boards", (0.5, 0.4, 0.3))
    roof = _material("roof", (0.6, 0.55, 0.5))
    _box(scene, "floor", (-3, -6, -0.1), (3, 6, 0.0), floor)
    _box(scene, "gable_back", (-3.1, 6.0, 0.0), (3.1, 6.1, 3.1), roof)
    _box(scene, "gable_front", (-3.1, -6.1, 0.0), (3.1, -6.0, 3.1), roof)
    for side in (-1, 1):  # knee walls under the eaves
        _box(scene, f"knee_{side}", (side * 3.0 - 0.05, -6.0, 0.0), (side * 3.0 + 0.05, 6.0, 1.05), roof)
    slope = math.atan2(2.0, 3.0)
    length = math.hypot(3.0, 2.0)
    for side in (-1, 1):  # two roof slabs, one with an opening for the sun
        for y0, y1 in ((-6.0, -0.8), (0.8, 6.0)) if side > 0 else ((-6.0, 6.0),):
            obj = _box(scene, f"roof_{side}_{y0}", (-length / 2, y0, -0.05), (length / 2, y1, 0.05), roof)
            obj.rotation_euler = (0.0, side * slope, 0.0)
            obj.location = (-side * 1.5, (y0 + y1) / 2, 2.0)
    for i in range(9):  # trusses: tie beam, two rafters, a king post
        y = -5.0 + i * 1.25
        _box(scene, f"tie_{i}", (-2.9, y - 0.04, 0.9), (2.9, y + 0.04, 1.0), wood)
        _box(scene, f"king_{i}", (-0.04, y - 0.04, 1.0), (0.04, y + 0.04, 2.9), wood)
        for side in (-1, 1):
            obj = _box(scene, f"rafter_{i}_{side}", (-length / 2, y - 0.04, -0.05), (length / 2, y + 0.04, 0.05), wood)
            obj.rotation_euler = (0.0, side * slope, 0.0)
            obj.location = (-side * 1.5, y, 1.9)
    _sun(scene, 5.0, elevation=55.0, azimuth=100.0)
    _area(scene, "lamp", (0.0, -4.0, 0.8), 0.5, 60.0, color=(1.0, 0.8, 0.6))
    _world(scene, (0.4, 0.5, 0.7), 0.3)
    _camera(scene, (2.2, -5.7, 0.7), (-0.8, 3.0, 0.9), lens=18.0)


def scatter(count=81, spacing=0.33, radius=0.15, seed=12):
    """Issue #12's dense scatter: count^2 rocks (icospheres of 80 faces, radius 0.15 m scaled
    0.8-1.2 and squashed in z, 0.33 m apart, their centres on the ground: half buried) on a jittered grid,
    joined into one mesh (6,561 objects would make the sync the measurement). Deterministic:
    its own seeded generator."""
    import random  # noqa: PLC0415

    scene = _reset()
    ground = _material("ground", (0.6, 0.58, 0.55))
    rock = _material("rock", (0.78, 0.76, 0.72))
    _box(scene, "ground", (-40, -40, -0.2), (40, 40, 0.0), ground)
    rng = random.Random(seed)
    half = (count - 1) * spacing / 2

    bm = bmesh.new()
    bmesh.ops.create_icosphere(bm, subdivisions=2, radius=radius)
    unit = [tuple(v.co) for v in bm.verts]
    faces = [tuple(v.index for v in f.verts) for f in bm.faces]
    bm.free()
    verts, polys = [], []
    for i in range(count):
        for j in range(count):
            x = i * spacing - half + rng.uniform(-0.25, 0.25) * spacing
            y = j * spacing - half + rng.uniform(-0.25, 0.25) * spacing
            s = rng.uniform(0.8, 1.2)
            sz = rng.uniform(0.7, 1.0)
            turn = rng.uniform(0.0, 2.0 * math.pi)
            c, si = math.cos(turn), math.sin(turn)
            base = len(verts)
            verts.extend((x + s * (c * vx - si * vy), y + s * (si * vx + c * vy), s * sz * vz) for vx, vy, vz in unit)
            polys.extend(tuple(base + k for k in f) for f in faces)
    mesh = bpy.data.meshes.new("rocks")
    mesh.from_pydata(verts, [], polys)
    mesh.materials.append(rock)
    obj = bpy.data.objects.new("rocks", mesh)
    scene.collection.objects.link(obj)
    _sun(scene, 4.0, elevation=40.0, azimuth=30.0)
    _world(scene, (0.5, 0.6, 0.8), 1.0)
    _camera(scene, (0.0, -11.0, 2.2), (0.0, -3.0, 0.0), lens=30.0)


def _studio_hdri(scene, name="sunrise.exr", rotation_z=1.2, strength=1.0):
    """The world of Blender's bundled CC0 studio HDRI `name`, turned about Z by a Mapping node."""
    path = Path(bpy.utils.system_resource("DATAFILES")) / "studiolights" / "world" / name
    world = bpy.data.worlds.new("hdri")
    world.use_nodes = True
    nodes, links = world.node_tree.nodes, world.node_tree.links
    coord = nodes.new("ShaderNodeTexCoord")
    mapping = nodes.new("ShaderNodeMapping")
    mapping.inputs["Rotation"].default_value = (0.0, 0.0, rotation_z)
    env = nodes.new("ShaderNodeTexEnvironment")
    env.image = bpy.data.images.load(str(path))
    links.new(coord.outputs["Generated"], mapping.inputs["Vector"])
    links.new(mapping.outputs["Vector"], env.inputs["Vector"])
    bg = nodes["Background"]
    bg.inputs["Strength"].default_value = strength
    links.new(env.outputs["Color"], bg.inputs["Color"])
    scene.world = world


def hdri_yard():
    """The yard lit only by the bundled sunrise HDRI (its sun casts the shadows)."""
    yard()
    scene = bpy.context.scene
    bpy.data.objects.remove(bpy.data.objects["sun"])
    _studio_hdri(scene)


def sky_yard():
    """The yard under Blender's Sky Texture (its default type) plus the sun lamp."""
    yard()
    scene = bpy.context.scene
    world = scene.world
    sky = world.node_tree.nodes.new("ShaderNodeTexSky")
    world.node_tree.links.new(sky.outputs["Color"], world.node_tree.nodes["Background"].inputs["Color"])
    world.node_tree.nodes["Background"].inputs["Strength"].default_value = 0.3


def hdri_room():
    """The contact room opened to the sunrise HDRI: no lamps, the sky through the missing walls."""
    contact()
    bpy.data.objects.remove(bpy.data.objects["lamp"])
    _studio_hdri(bpy.context.scene, rotation_z=2.4)


SCENES = {f.__name__: f for f in (yard, contact, trusses, hdri_yard, sky_yard, hdri_room, scatter)}


def build(out_dir: Path, names=None) -> dict[str, Path]:
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name in names or SCENES:
        SCENES[name]()
        path = out_dir / f"{name}.blend"
        bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=False)
        paths[name] = path
    return paths


if __name__ == "__main__":
    built = build(Path(sys.argv[1]), sys.argv[2:] or None)
    print("\n".join(str(p) for p in built.values()))
    sys.stdout.flush()
    import os

    os._exit(0)  # bpy 4.2 can crash at interpreter exit (BLENDER_FACTS)
