"""Build HybridGI's own scenes as .blend files from the procedural descriptions.

    python blend_scenes/build.py [--only NAME] [--out DIR]

writes DIR/NAME.blend (DIR defaults to blend_scenes/ for the default Blender, blend_scenes/blender-X.Y/
for the others: a Blender cannot open files a newer one saved). Every object, material, light, camera and
world comes from `procedural.describe(NAME)`, so the .blend and `procedural.NAME()` hold the same
triangles in the same order under the same names. The animated scene's ball, bunny and light are
keyframed on every frame from the same analytic motion (LINEAR keys, so integer frames are exact).
The animated scene's bunny is the Stanford bunny appended from ../shared/scenes/bunny_npm.blend
beside the checkout; without that file the procedural stand-in is used and a warning is logged.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # run as a script: make `blend_scenes` importable

import bpy  # noqa: E402
from mathutils import Matrix  # noqa: E402

from blend_scenes import procedural  # noqa: E402
from hybridgi_cli import blender_compat  # noqa: E402

log = logging.getLogger("blend_scenes.build")

BUNNY_BLEND = ROOT.parent / "shared" / "scenes" / "bunny_npm.blend"
CYCLES_SAMPLES = 128
LINEAR = 1  # enum value of 'LINEAR' in FCurve keyframe interpolation (foreach_set takes ints)


def _material(spec) -> bpy.types.Material:
    """Principled BSDF with no specular layer: Cycles then shades it as the core's Lambertian."""
    mat = blender_compat.new_material(bpy, spec.name)
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    rgba = (*map(float, spec.base_color), 1.0)
    bsdf.inputs["Base Color"].default_value = rgba
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    bsdf.inputs["Roughness"].default_value = 1.0
    strength = float(np.max(spec.emission))
    if strength > 0.0:
        bsdf.inputs["Emission Color"].default_value = (*map(float, spec.emission / strength), 1.0)
        bsdf.inputs["Emission Strength"].default_value = strength
    mat.diffuse_color = rgba  # Solid viewport colour
    return mat


def _mesh(name: str, geometry, smooth: bool) -> bpy.types.Mesh:
    """Blender mesh with exactly the geometry's triangles, in order.

    Flat parts are welded (geometry_from_arrays splits every corner) so they edit like normal
    meshes; smooth parts keep their vertices and get the authored normals as custom normals.
    """
    positions, tris = geometry.positions, geometry.triangles
    if not smooth:
        positions, inverse = np.unique(positions, axis=0, return_inverse=True)
        tris = inverse.reshape(-1)[tris]
    me = bpy.data.meshes.new(name)
    me.vertices.add(len(positions))
    me.vertices.foreach_set("co", np.ascontiguousarray(positions, np.float32).ravel())
    me.loops.add(tris.size)
    me.loops.foreach_set("vertex_index", np.ascontiguousarray(tris, np.int32).ravel())
    me.polygons.add(len(tris))
    me.polygons.foreach_set("loop_start", np.arange(0, tris.size, 3, dtype=np.int32))
    me.update(calc_edges=True)
    # New faces default to smooth (no sharp_face attribute): state the shading either way.
    me.polygons.foreach_set("use_smooth", np.full(len(tris), smooth, bool))
    if smooth:
        me.normals_split_custom_set_from_vertices(np.ascontiguousarray(geometry.normals, np.float32))
    return me


def _set_transform(obj, transform: procedural.Transform) -> None:
    obj.location = transform.location
    obj.rotation_euler = transform.rotation
    obj.scale = transform.scale


def _append_bunny(material) -> bpy.types.Mesh | None:
    """The Stanford bunny's mesh, normalized to the stand-in's frame (base centred on the origin,
    BUNNY_HEIGHT tall, facing -Y), or None where the shared file is missing."""
    if not BUNNY_BLEND.exists():
        log.warning("%s not found: the animated scene uses the procedural bunny stand-in", BUNNY_BLEND)
        return None
    if not blender_compat.opens_here(BUNNY_BLEND):
        log.warning("%s was saved by Blender %d.%d, which this one cannot read: the animated scene uses the "
                    "procedural bunny stand-in", BUNNY_BLEND, *blender_compat.saved_by(BUNNY_BLEND))
        return None
    with bpy.data.libraries.load(str(BUNNY_BLEND), link=False) as (src, dst):
        dst.objects = list(src.objects)
    meshes = [o for o in dst.objects if o is not None and o.type == "MESH"]
    if not meshes:
        log.warning("%s holds no mesh object: using the procedural bunny stand-in", BUNNY_BLEND)
        return None
    source = meshes[0]
    me = source.data
    # Its object's rotation stands the Y-up scan upright (matrix_world is not evaluated for an
    # object outside any scene: use the basis); its nose then points to -X, so turn it to face -Y.
    me.transform(Matrix.Rotation(math.pi / 2, 4, "Z") @ source.matrix_basis)
    co = np.empty(3 * len(me.vertices), np.float32)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3)
    lo, hi = co.min(axis=0), co.max(axis=0)
    scale = procedural.BUNNY_HEIGHT / float(hi[2] - lo[2])
    base = (0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), lo[2])
    me.transform(Matrix.Diagonal((scale, scale, scale, 1.0)) @ Matrix.Translation([-c for c in base]))
    me.materials.clear()
    me.materials.append(material)
    me.shade_smooth()
    me.name = "bunny"
    for o in dst.objects:  # the file's own camera and light stay out of our scene
        if o is not None:
            bpy.data.objects.remove(o)
    return me


def _light(spec) -> bpy.types.Object:
    data = bpy.data.lights.new(spec.name, spec.kind)
    data.color = tuple(map(float, spec.color))
    data.energy = float(spec.power)
    if spec.kind in ("POINT", "SPOT"):
        data.shadow_soft_size = float(spec.radius)
    if spec.kind == "SPOT":
        data.spot_size, data.spot_blend = float(spec.spot_size), float(spec.spot_blend)
    if spec.kind == "SUN":
        data.angle = float(spec.angle)
    if spec.kind == "AREA":
        data.shape, data.size, data.size_y = spec.shape, float(spec.size), float(spec.size_y)
    obj = bpy.data.objects.new(spec.name, data)
    obj.matrix_world = Matrix(spec.matrix.tolist())
    return obj


def _camera(spec: procedural.Camera, name: str) -> bpy.types.Object:
    data = bpy.data.cameras.new(name)
    data.lens = spec.lens_mm
    data.sensor_width = spec.sensor_width_mm
    data.sensor_fit = "HORIZONTAL"
    data.clip_start, data.clip_end = spec.clip_start, spec.clip_end
    obj = bpy.data.objects.new(name, data)
    obj.matrix_world = Matrix(spec.matrix().tolist())
    return obj


def _world(spec, name: str) -> bpy.types.World:
    world = blender_compat.new_world(bpy, name)
    background = world.node_tree.nodes["Background"]
    background.inputs["Color"].default_value = (*map(float, spec.color), 1.0)
    background.inputs["Strength"].default_value = 1.0
    world.color = tuple(map(float, spec.color))
    world.light_settings.distance = float(spec.ao_distance)
    return world


def _keyframe(obj, path: str, frames: np.ndarray, values: np.ndarray) -> None:
    """LINEAR keys of values[:, i] on obj's `path`[i] at every frame."""
    if obj.animation_data is None:
        obj.animation_data_create()
    if obj.animation_data.action is None:
        obj.animation_data.action = bpy.data.actions.new(f"{obj.name}_motion")
    action = obj.animation_data.action
    for i in range(values.shape[1]):
        fc = blender_compat.fcurve_ensure(bpy, action, obj, path, i)
        fc.keyframe_points.add(len(frames))
        fc.keyframe_points.foreach_set("co", np.stack([frames, values[:, i]], 1).astype(np.float32).ravel())
        fc.keyframe_points.foreach_set("interpolation", np.full(len(frames), LINEAR, np.int32))
        fc.update()


def _animate(name: str, desc: procedural.SceneDescription, objects: dict, lights: dict) -> None:
    frames = np.arange(desc.frame_start, desc.frame_end + 1)
    per_frame = [procedural.describe(name, int(f)) for f in frames]
    for k, part in enumerate(desc.parts):
        if not part.dynamic:
            continue
        ts = [d.parts[k].transform for d in per_frame]
        obj = objects[part.name]
        _keyframe(obj, "location", frames, np.array([t.location for t in ts]))
        _keyframe(obj, "rotation_euler", frames, np.array([t.rotation for t in ts]))
        _keyframe(obj, "scale", frames, np.array([t.scale for t in ts]))
    for k, spec in enumerate(desc.lights):
        where = np.array([d.lights[k].matrix[:3, 3] for d in per_frame])
        if np.ptp(where, axis=0).max() > 0.0:
            _keyframe(lights[spec.name], "location", frames, where)


def _render_settings(scene, desc: procedural.SceneDescription) -> None:
    """Cycles defaults: resolution, frame range, Standard view transform (linear comparisons)."""
    r = scene.render
    r.engine = "CYCLES"
    r.resolution_x, r.resolution_y = desc.camera.resolution
    r.resolution_percentage = 100
    r.fps = desc.fps
    scene.frame_start, scene.frame_end = desc.frame_start, desc.frame_end
    scene.view_settings.view_transform = "Standard"
    scene.cycles.samples = CYCLES_SAMPLES
    # No indirect clamping: the files double as ground truth for HybridGI (see BLENDER_FACTS.md).
    scene.cycles.sample_clamp_indirect = 0.0


def build(name: str, out_dir: Path) -> Path:
    """Build one scene into out_dir/name.blend; returns the path."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    desc = procedural.describe(name)
    scene = bpy.context.scene
    materials = {m.name: _material(m) for m in desc.materials}
    objects = {}
    for part in desc.parts:
        mesh = None
        if name == "animated" and part.name == "bunny":
            mesh = _append_bunny(materials[part.material])
        if mesh is None:
            mesh = _mesh(part.name, part.geometry, part.smooth)
            mesh.materials.append(materials[part.material])
        obj = bpy.data.objects.new(part.name, mesh)
        _set_transform(obj, part.transform)
        scene.collection.objects.link(obj)
        objects[part.name] = obj
    lights = {}
    for spec in desc.lights:
        lights[spec.name] = _light(spec)
        scene.collection.objects.link(lights[spec.name])
    cam = _camera(desc.camera, "camera")
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.world = _world(desc.world, f"{name}_world")
    _render_settings(scene, desc)
    if desc.frame_end > desc.frame_start:
        _animate(name, desc, objects, lights)
    scene.frame_set(desc.frame_start)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}.blend"
    bpy.ops.wm.save_as_mainfile(filepath=str(path), compress=True)
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", choices=procedural.SCENE_NAMES, help="build just this scene")
    parser.add_argument("--out", type=Path, default=blender_compat.scenes_dir(), help="output folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name in [args.only] if args.only else procedural.SCENE_NAMES:
        t0 = time.perf_counter()
        path = build(name, args.out)
        tris = procedural.describe(name).triangle_count
        print(f"{name}: {path} ({tris:,} triangles, {time.perf_counter() - t0:.2f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
