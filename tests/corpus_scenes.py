"""The bad-input corpus's scenes, built as small .blend files with bpy (issue 13).

    python tests/corpus_scenes.py OUT_DIR [NAME ...]

writes OUT_DIR/NAME.blend for every scene in SCENES (or the named ones). Each scene is tiny (a
few objects, 48x36 pixels) so the whole corpus renders in about a minute; tests/test_corpus.py
runs the `hybridgi` command on them and checks each outcome. Run in its own process: it resets
the bpy module's file.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

# ruff: noqa: I001  (bpy must come first: importing it makes bmesh and mathutils importable)
import bpy
import bmesh
from mathutils import Vector

WIDTH, HEIGHT = 48, 36


def _reset():
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.resolution_x, scene.render.resolution_y = WIDTH, HEIGHT
    scene.render.resolution_percentage = 100
    scene.frame_start = scene.frame_end = scene.frame_current = 1
    return scene


def _material(name, color=(0.8, 0.8, 0.8)):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True  # no-op on 5.0, needed before it
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bsdf.inputs["Roughness"].default_value = 1.0
    return mat


def _object(scene, name, mesh, location=(0, 0, 0), scale=(1, 1, 1), material=None):
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    obj.scale = scale
    if material is not None and not mesh.materials:
        mesh.materials.append(material)
    scene.collection.objects.link(obj)
    return obj


def _mesh_from(name, build):
    bm = bmesh.new()
    build(bm)
    mesh = bpy.data.meshes.new(name)
    bm.to_mesh(mesh)
    bm.free()
    return mesh


def cube_mesh(name="cube", size=1.0):
    return _mesh_from(name, lambda bm: bmesh.ops.create_cube(bm, size=size))


def sphere_mesh(name="sphere", radius=1.0, segments=24):
    return _mesh_from(name, lambda bm: bmesh.ops.create_uvsphere(bm, u_segments=segments, v_segments=segments // 2,
                                                                 radius=radius))


def plane_mesh(name="plane", size=1.0):
    mesh = bpy.data.meshes.new(name)
    h = size / 2
    mesh.from_pydata([(-h, -h, 0), (h, -h, 0), (h, h, 0), (-h, h, 0)], [], [(0, 1, 2, 3)])
    mesh.uv_layers.new(name="UVMap")
    return mesh


def _camera(scene, location, target, lens=35.0, clip=(0.1, 100.0)):
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.location = location
    direction = Vector(target) - Vector(location)
    direction /= direction.length  # to_track_quat treats micrometre-long vectors as zero
    cam.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    cam.data.lens = lens
    cam.data.clip_start, cam.data.clip_end = clip
    scene.collection.objects.link(cam)
    scene.camera = cam
    return cam


def _sun(scene, strength=3.0, direction=(0.4, -0.3, -1.0)):
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = strength
    sun.rotation_euler = Vector(direction).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(sun)
    return sun


def _world(scene, color=(0.2, 0.2, 0.2)):
    world = bpy.data.worlds.new("world")
    world.use_nodes = True
    world.node_tree.nodes["Background"].inputs["Color"].default_value = (*color, 1.0)
    world.color = color
    scene.world = world
    return world


def _basic(offset=(0.0, 0.0, 0.0), scale=1.0):
    """Floor, cube, sun, grey sky and a camera, all `scale` times Blender's unit around `offset`."""
    scene = _reset()
    o = Vector(offset)
    grey = _material("grey")
    # Scaled objects, not scaled meshes: bmesh merges vertices closer than ~1e-6.
    s3 = (scale, scale, scale)
    _object(scene, "floor", plane_mesh("floor", 4.0), location=o, scale=s3, material=grey)
    _object(scene, "cube", cube_mesh("cube", 1.0), location=o + Vector((0, 0, 0.5 * scale)), scale=s3,
            material=_material("orange", (0.8, 0.35, 0.1)))
    _camera(scene, o + Vector((3.0, -3.0, 2.4)) * scale, o + Vector((0, 0, 0.4 * scale)),
            clip=(0.01 * scale, 100.0 * scale))
    _sun(scene)
    _world(scene)
    return scene


# --- the scenes --------------------------------------------------------------------------------


def basic():
    _basic()


def far_sphere():
    """A 1 m sphere of 2,256 triangles on a floor 100 km from the origin (float32 still resolves
    ~8 mm there); a zero-area test growing with the distance from the origin dropped them all."""
    scene = _reset()
    o = Vector((1.0e5, 0.0, 0.0))
    grey = _material("grey")
    _object(scene, "floor", plane_mesh("floor", 6.0), location=o + Vector((0, 0, -1)), material=grey)
    _object(scene, "sphere", sphere_mesh("sphere", 0.5, segments=48), location=o,
            material=_material("blue", (0.1, 0.3, 0.8)))
    _camera(scene, o + Vector((2.5, -2.5, 1.2)), o)
    _sun(scene)
    _world(scene)


def micro_cube():
    """A one-micrometre cube on a 4 um floor, seen from 4 um away."""
    _basic(scale=1.0e-6)


def zero_scale():
    """A cube squashed flat (scale z = 0) lying above the floor: Cycles renders its square."""
    scene = _basic()
    cube = scene.objects["cube"]
    cube.scale.z = 0.0
    cube.location.z = 0.3


def nan_vertices():
    """Three of the sphere's vertices are NaN: the rest must still render, without NaN pixels."""
    scene = _basic()
    sphere = _object(scene, "sphere", sphere_mesh("sphere", 0.4), location=(1.2, 0.6, 0.4),
                     material=_material("green", (0.1, 0.7, 0.2)))
    for i in (5, 40, 77):
        sphere.data.vertices[i].co = (math.nan, math.nan, math.nan)


def instances():
    """2,500 objects sharing one cube mesh on a 50 x 50 grid (one pass over the triangles)."""
    scene = _reset()
    mesh = cube_mesh("small", 0.05)
    mat = _material("white", (0.7, 0.7, 0.7))
    mesh.materials.append(mat)
    for i in range(2500):
        x, y = i % 50, i // 50
        obj = bpy.data.objects.new(f"c{i}", mesh)
        obj.location = (x * 0.08 - 2.0, y * 0.08 - 2.0, 0.025 + 0.02 * ((x * 7 + y * 3) % 5))
        scene.collection.objects.link(obj)
    _object(scene, "floor", plane_mesh("floor", 5.0), material=_material("grey"))
    _camera(scene, (3.0, -3.5, 3.0), (0, 0, 0))
    _sun(scene)
    _world(scene)


def wide_texture():
    """A plane textured with a 6000 x 4 image (over the 4096 texel cap): left half red, right half
    green; the capped texture must keep the halves."""
    scene = _reset()
    image = bpy.data.images.new("wide", 6000, 4, alpha=False, float_buffer=False)
    pixels = []
    for _y in range(4):
        pixels += [1.0, 0.05, 0.05, 1.0] * 3000 + [0.05, 1.0, 0.05, 1.0] * 3000
    image.pixels.foreach_set(pixels)
    image.pack()
    mat = _material("tex")
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    tex.interpolation = "Closest"
    mat.node_tree.links.new(tex.outputs["Color"], mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"])
    _object(scene, "plane", plane_mesh("plane", 2.0), material=mat)
    _camera(scene, (0.0, 0.0, 3.0), (0.0, 0.0, 0.0), lens=50.0)
    _sun(scene, direction=(0.0, 0.0, -1.0))
    _world(scene)


def nan_light():
    """A point light with NaN power beside a normal sun."""
    scene = _basic()
    lamp = bpy.data.objects.new("lamp", bpy.data.lights.new("lamp", "POINT"))
    lamp.data.energy = math.nan
    lamp.location = (1.0, -1.0, 2.0)
    scene.collection.objects.link(lamp)


def nan_material():
    """The cube's base colour is NaN."""
    scene = _basic()
    mat = scene.objects["cube"].data.materials[0]
    mat.node_tree.nodes["Principled BSDF"].inputs["Base Color"].default_value = (math.nan, 0.5, 0.5, 1.0)


def nan_world():
    """The world colour is NaN."""
    scene = _basic()
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (math.nan, math.nan, 0.2, 1.0)
    scene.world.color = (math.nan, math.nan, 0.2)


def no_camera():
    scene = _basic()
    camera = scene.camera
    scene.camera = None
    bpy.data.objects.remove(camera)


def only_degenerate():
    """The only mesh has nothing but zero-area triangles: the world alone renders."""
    scene = _reset()
    mesh = bpy.data.meshes.new("sliver")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 0)], [], [(0, 1, 2), (0, 0, 3)])
    _object(scene, "sliver", mesh)
    _camera(scene, (0, -4, 1), (0, 0, 0))
    _world(scene, (0.3, 0.4, 0.5))


def camera_only():
    scene = _reset()
    _camera(scene, (0, -4, 1), (0, 0, 0))
    _world(scene, (0.3, 0.4, 0.5))


def render_border():
    scene = _basic()
    scene.render.use_border = True
    scene.render.border_min_x, scene.render.border_max_x = 0.25, 0.75
    scene.render.border_min_y, scene.render.border_max_y = 0.25, 0.75


def render_border_crop():
    render_border()
    bpy.context.scene.render.use_crop_to_border = True


def film_transparent():
    scene = _basic()
    scene.render.film_transparent = True


def panoramic_camera():
    scene = _basic()
    scene.camera.data.type = "PANO"


def camera_invisible():
    """The cube is hidden from camera rays (Object > Visibility > Camera) but still casts shadows."""
    scene = _basic()
    scene.objects["cube"].visible_camera = False


def tall():
    """The basic scene with a 2.05 m tall cube: at resolution 128 its grid is 128x128x66 cells,
    whose depth texture needed more than OpenGL's 16384 rows in the old 4096-wide layout."""
    scene = _basic()
    cube = scene.objects["cube"]
    cube.scale.z = 2.05  # basic's cube has scale 1
    cube.location.z = 1.025


def percent_small():
    """resolution_percentage 10 of 48x36: a 4x3 image."""
    scene = _basic()
    scene.render.resolution_percentage = 10


SCENES = {f.__name__: f for f in (
    basic, far_sphere, micro_cube, zero_scale, nan_vertices, instances, wide_texture, nan_light,
    nan_material, nan_world, no_camera, only_degenerate, camera_only, render_border, render_border_crop,
    film_transparent, panoramic_camera, camera_invisible, percent_small, tall,
)}


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
