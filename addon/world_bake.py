"""Any world node tree as an equirectangular radiance map, evaluated by Blender itself.

Sky Texture, gradients, mixes of environment maps: rather than re-implement Blender's nodes, the
world is rendered by Cycles through a panoramic camera, in a separate process (a render cannot
start inside another one, and the user's file must not change). The map then goes through the
same split as an environment image (`hybridgi_core.environment`: a shadowed sun plus an SH sky).

Baked maps are cached under a key of everything the world's output depends on (`world_key`), in
memory and on disk, so a world that did not change costs nothing on the next sync. Final renders
wait for a bake; the viewport does not (`bake_world(world, wait=False)`): the bake runs on a
thread that only waits for the process, the view keeps its last world meanwhile, and `STORE.completed`
counts finished bakes so that it can read the world again. Everything that touches `bpy` runs on
the main thread; the bake process itself runs headless with the factory settings.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import time

import bpy
import numpy as np

from .bake_store import BakeStore

log = logging.getLogger(__name__)

#: Size of the finest render, and the factor the map is coarser by. A Sky Texture's sun disc
#: (0.5 degrees) needs fine pixels: its energy came out 1.8x / 1.3x / 1.05x of what Cycles lights
#: a surface with at 512 / 1024 / 2048 pixels across; the map the core reads stays 512 wide (the
#: bake script renders only the sun's texels at the finest size).
BAKE_WIDTH, BAKE_HEIGHT = 2048, 1024
BAKE_REDUCE = 4
#: Cycles samples per pixel of the finest render (only camera rays into the world: no noise but
#: AA); the map's own texels take BAKE_REDUCE times as many.
BAKE_SAMPLES = 4
#: Version of the bake (its script and settings), part of every map's key: maps baked by an older
#: one are baked again. 2: the sun's texels with SUN_OVERSAMPLE x the samples.
BAKE_VERSION = 2
#: Seconds the bake process may take before the world falls back to its mean colour.
BAKE_TIMEOUT_S = 120
#: Maps kept in memory (worlds are few, maps 1.5 MiB).
KEPT = 8

#: The Light Path node's outputs as a ray leaving a diffuse surface sees the world (Cycles' first
#: bounce: depth 1 of the diffuse kind, a reflection; the rest 0; the ray is unbounded). A world
#: that mixes with Light Path ("Is Camera Ray": a backdrop the camera sees, an HDRI that lights)
#: is baked once as the camera sees it (the background) and once as this ray does (the light).
DIFFUSE_RAY = {"Is Camera Ray": 0.0, "Is Shadow Ray": 0.0, "Is Diffuse Ray": 1.0, "Is Glossy Ray": 0.0,
               "Is Singular Ray": 0.0, "Is Reflection Ray": 1.0, "Is Transmission Ray": 0.0,
               "Is Volume Scatter Ray": 0.0, "Ray Length": 1.0e10, "Ray Depth": 1.0, "Diffuse Depth": 1.0,
               "Glossy Depth": 0.0, "Transparent Depth": 0.0, "Transmission Depth": 0.0}
#: Light Path outputs whose value differs between Cycles' two ways of finding the world from a
#: diffuse surface (lamp sampling evaluates the world with none of the ray flags set, a bounce
#: ray with its own): `DIFFUSE_RAY` is the second; a warning names them.
AMBIGUOUS_OUTPUTS = frozenset({"Is Diffuse Ray", "Is Reflection Ray", "Ray Depth", "Diffuse Depth", "Ray Length"})

#: Finished maps (memory and ~/.cache/hybridgi/worlds) and the background bakes.
STORE = BakeStore("worlds", KEPT)

#: Runs in the bake process: argv = the .blend holding the world, its name, the output .npy.
_BAKE_SCRIPT = r"""
import json
import sys
import time; T0 = time.perf_counter()
import bpy
import numpy as np
blend, name, out, width, height, samples, reduce, rays = sys.argv[-8:]
with bpy.data.libraries.load(blend) as (data_from, data_to):
    data_to.worlds = [name]
if rays != "camera":
    # The world as a diffuse bounce ray sees it: every linked Light Path output becomes a Value
    # node of that ray's value (the bake's own rays are camera rays).
    values = json.loads(rays)
    def ray_values(tree, seen):
        if tree is None or tree.name_full in seen:
            return
        seen.add(tree.name_full)
        for node in list(tree.nodes):
            if node.type == "LIGHT_PATH":
                for output in node.outputs:
                    targets = [link.to_socket for link in tree.links if link.from_socket == output]
                    if not targets:
                        continue
                    value = tree.nodes.new("ShaderNodeValue")
                    value.outputs[0].default_value = values.get(output.identifier, 0.0)
                    for socket in targets:  # replaces the input's link
                        tree.links.new(value.outputs[0], socket)
            ray_values(getattr(node, "node_tree", None), seen)
    ray_values(data_to.worlds[0].node_tree, set())
scene = bpy.context.scene
for obj in list(scene.objects):
    bpy.data.objects.remove(obj)
scene.world = data_to.worlds[0]
camera = bpy.data.objects.new("bake", bpy.data.cameras.new("bake"))
scene.collection.objects.link(camera)
scene.camera = camera
camera.data.type = "PANO"
if hasattr(camera.data, "panorama_type"):
    camera.data.panorama_type = "EQUIRECTANGULAR"
else:  # Blender before 4.0 keeps it in the Cycles settings
    camera.data.cycles.panorama_type = "EQUIRECTANGULAR"
# Facing +X at the horizon: rows from the nadir up, the middle column towards +X, as the core reads.
camera.rotation_euler = (1.5707963267948966, 0.0, -1.5707963267948966)
scene.render.engine = "CYCLES"
scene.cycles.device = "CPU"
scene.cycles.use_denoising = False
scene.cycles.use_adaptive_sampling = False
scene.render.resolution_percentage = 100
scene.render.film_transparent = False
scene.view_settings.view_transform = "Standard"
scene.render.image_settings.file_format = "OPEN_EXR"
scene.render.image_settings.color_depth = "32"


def render(w, h, spp, path, border=None):
    # The world at w x h, spp box-filtered samples per pixel, as (h, w, 3); border : (x0, x1,
    # y0, y1) pixels to render alone (the rest of the array is left zero).
    scene.cycles.samples = int(spp)
    scene.cycles.pixel_filter_type = "BOX"
    scene.cycles.filter_width = 1.0
    scene.render.resolution_x, scene.render.resolution_y = w, h
    scene.render.use_border = border is not None
    scene.render.use_crop_to_border = False
    if border is not None:
        x0, x1, y0, y1 = border
        scene.render.border_min_x, scene.render.border_max_x = x0 / w, x1 / w
        scene.render.border_min_y, scene.render.border_max_y = y0 / h, y1 / h
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)
    image = bpy.data.images.load(path)
    pixels = np.empty(w * h * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(h, w, image.channels)[..., :3]


#: Texels on each side of the brightest one rendered again k times finer.
SUN_TEXELS = 4
#: How far the brightest texel must stand above the median one for that second render (a sun).
SUN_PEAK = 50.0
#: Samples per texel of that finer render, over the map's own: the disc covers ~7 of its texels,
#: and 4 box samples each misjudged the coverage of its rim: a Nishita sun (elevation 25 degrees)
#: lit the ground 3% bright, 320x180 Combined 0.0313 against Cycles 512 spp; x16 0.0111, x64
#: 0.0105 (Diffuse Direct's mean within 0.01%). The region is 9 x 9 texels: 330k samples.
SUN_OVERSAMPLE = 64
# The map at its own size, samples x k box-filtered samples a texel, then, where a sun stands
# out, the texels around the brightest one again from a k times finer render: a Sky Texture's
# sun disc (0.5 degrees) is under a texel, whose own samples misjudge its energy (1.8x at 512
# wide); the rest of the sky is smooth at the map's size. Why not all of it k times finer, as
# before: 4x the samples and a 32 MB image for the same map (a Nishita sky's mean equal to 4
# digits; the bake process 1.9 -> 1.1 s, its sun region 0.3 s of it).
k = int(reduce)
w, h = int(width) // k, int(height) // k
rgb = render(w, h, int(samples) * k, out + ".exr")
luma = rgb @ np.array([0.2126, 0.7152, 0.0722], np.float32)
y, x = np.unravel_index(int(np.argmax(luma)), (h, w))
if luma[y, x] > SUN_PEAK * max(float(np.median(luma)), 1e-12):
    x0, x1, y0, y1 = max(x - SUN_TEXELS, 0), min(x + SUN_TEXELS + 1, w), max(y - SUN_TEXELS, 0), min(y + SUN_TEXELS + 1, h)
    fine = render(w * k, h * k, int(samples) * SUN_OVERSAMPLE, out + "_sun.exr", (x0 * k, x1 * k, y0 * k, y1 * k))
    rgb[y0:y1, x0:x1] = fine[y0 * k:y1 * k, x0 * k:x1 * k].reshape(y1 - y0, k, x1 - x0, k, 3).mean(axis=(1, 3))
np.save(out, rgb)
"""


def _value_repr(value) -> str:
    if isinstance(value, bpy.types.ID):
        return f"ID:{value.name_full}:{getattr(value, 'filepath', '')}"
    if hasattr(value, "__len__") and not isinstance(value, str):
        try:
            return repr(tuple(value))
        except TypeError:
            return repr(value)
    return repr(value)


def world_key(world, rays: str = "camera") -> str:
    """Hash of what a world's output depends on: its nodes' settings, socket values and links,
    the images they read (by name, path and size), the Blender version and BAKE_VERSION; with
    rays="diffuse", of its map as diffuse bounce rays see it (`DIFFUSE_RAY`)."""
    digest = hashlib.sha256(bpy.app.version_string.encode())
    digest.update(f"bake={BAKE_VERSION}".encode())
    tree_digest(digest, world.node_tree)
    if rays != "camera":
        digest.update(f"rays={rays}:{sorted(DIFFUSE_RAY.items())}".encode())
    return digest.hexdigest()[:32]


def tree_digest(digest, tree, seen: set | None = None) -> None:
    """Feed `digest` with everything a node tree's output depends on: its nodes (settings, socket
    values, images, Color Ramp stops and curve points, which are not node properties) and links,
    node groups followed once each (`material_bake` keys material trees the same way)."""
    seen = set() if seen is None else seen
    if tree is None or tree.name_full in seen:
        return
    seen.add(tree.name_full)
    for node in sorted(tree.nodes, key=lambda n: n.name):
        digest.update(f"{node.bl_idname}|{node.name}|{node.mute}".encode())
        for prop in node.bl_rna.properties:
            if prop.identifier in {"rna_type", "location", "width", "height", "dimensions", "select", "name", "label",
                                   "parent", "color", "use_custom_color", "show_options", "show_preview", "hide",
                                   "show_texture", "location_absolute", "warning_propagation"}:
                continue
            try:
                value = getattr(node, prop.identifier)
            except (AttributeError, TypeError):
                continue
            # Sockets, ramps and other structs are read below or by the caller: their repr holds
            # a memory address, which would change the key in every process.
            if prop.type == "COLLECTION" or (prop.type == "POINTER" and not isinstance(value, bpy.types.ID)):
                continue
            digest.update(f"{prop.identifier}={_value_repr(value)}".encode())
        for socket in node.inputs:
            value = getattr(socket, "default_value", None)
            digest.update(f"in:{socket.identifier}={_value_repr(value)}".encode())
        image = getattr(node, "image", None)
        if image is not None:
            path = bpy.path.abspath(image.filepath, library=image.library) if image.filepath else ""
            mtime = os.path.getmtime(path) if path and os.path.isfile(path) else 0.0
            digest.update(f"image:{tuple(image.size)}:{image.is_dirty}:{image.packed_file is not None}:{mtime}".encode())
    for link in tree.links:
        digest.update(f"{link.from_node.name}.{link.from_socket.identifier}->{link.to_node.name}."
                      f"{link.to_socket.identifier}|{link.is_muted}".encode())
    for node in tree.nodes:
        ramp = getattr(node, "color_ramp", None)
        if ramp is not None:
            digest.update(repr((ramp.interpolation, ramp.color_mode, ramp.hue_interpolation,
                                [(e.position, tuple(e.color)) for e in ramp.elements])).encode())
        mapping = getattr(node, "mapping", None)
        if mapping is not None and hasattr(mapping, "curves"):
            digest.update(repr([[tuple(p.location) for p in c.points] for c in mapping.curves]).encode())
        group = getattr(node, "node_tree", None)
        if group is not None:
            tree_digest(digest, group, seen)


def bake_world(world, wait: bool = True, key: str | None = None, rays: str = "camera") -> np.ndarray | None:
    """(h, w, 3) float32 linear radiance of `world` in every direction (the core's equirect
    layout), or None when the bake failed (logged; the caller falls back) or, with wait=False,
    is still running in the background. key : `world_key(world, rays)` when the caller has it.
    rays : "camera" (what the camera sees) or "diffuse" (what lights a diffuse surface: its
    Light Path nodes read as `DIFFUSE_RAY`)."""
    key = key or world_key(world, rays)
    pixels = STORE.get(key)
    if pixels is not None:
        return pixels
    if not wait:
        _start(world, key, rays)
        return None
    if STORE.running(key):  # started early (`sync.start_world_bakes`): its result, failed or not
        STORE.join(key, BAKE_TIMEOUT_S)
        return STORE.get(key)
    return _finish(key, _bake(world, rays))


def pending() -> bool:
    """Whether a background bake is running."""
    return STORE.pending()


def _finish(key: str, pixels: np.ndarray | None) -> np.ndarray | None:
    """Keep a finished bake (any thread: numpy and files only); None passes through."""
    return None if pixels is None else STORE.put(key, pixels)


def _start(world, key: str, rays: str = "camera") -> None:
    """Bake on a thread (main thread: the world is written out here, the thread only waits)."""
    if STORE.running(key):
        return
    tmp = tempfile.mkdtemp(prefix="hybridgi_world_")
    cmd, out = _command(world, tmp, rays)
    name = world.name

    def work():
        try:
            _finish(key, _run(cmd, out, name))
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    log.info("world %r: baking its map in the background", name)
    STORE.start(key, work, "hybridgi-world-bake")


def _command(world, tmp: str, rays: str = "camera") -> tuple[list[str], str]:
    """The bake process's command line for `world` (written to a .blend in `tmp`), and its output."""
    blend = os.path.join(tmp, "world.blend")
    out = os.path.join(tmp, "map")
    # Only the world and what it uses; image paths made absolute so the bake finds them.
    bpy.data.libraries.write(blend, {world}, path_remap="ABSOLUTE", fake_user=True)
    args = [blend, world.name, out, str(BAKE_WIDTH), str(BAKE_HEIGHT), str(BAKE_SAMPLES), str(BAKE_REDUCE),
            "camera" if rays == "camera" else json.dumps(DIFFUSE_RAY)]
    if bpy.app.binary_path:  # inside Blender: its own binary, headless
        return [bpy.app.binary_path, "-b", "--factory-startup", "--python-expr", _BAKE_SCRIPT, "--", *args], out
    return [sys.executable, "-c", _BAKE_SCRIPT, *args], out  # the bpy module: this Python


def _run(cmd: list[str], out: str, name: str) -> np.ndarray | None:
    """Run the bake process and read its map (any thread: no bpy)."""
    t0 = time.perf_counter()
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=BAKE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as err:
        log.warning("world %r could not be baked (%s); using its mean colour", name, err)
        return None
    if run.returncode != 0 or not os.path.isfile(out + ".npy"):
        tail = (run.stderr or run.stdout).strip().splitlines()[-3:]
        log.warning("world %r could not be baked (exit %s: %s); using its mean colour", name, run.returncode,
                    " | ".join(tail))
        return None
    pixels = np.load(out + ".npy").astype(np.float32)
    log.info("world %r baked to a %dx%d map in %.1f s", name, pixels.shape[1], pixels.shape[0], time.perf_counter() - t0)
    return pixels


def _bake(world, rays: str = "camera") -> np.ndarray | None:
    with tempfile.TemporaryDirectory(prefix="hybridgi_world_") as tmp:
        cmd, out = _command(world, tmp, rays)
        return _run(cmd, out, world.name)
