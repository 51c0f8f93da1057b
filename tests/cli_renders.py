"""Renders through the real `hybridgi render` command, shared by the tests that compare with Cycles
rendered in the same test (one subprocess per render: what a user runs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from hybridgi_cli import exr

HYBRIDGI = Path(sys.executable).parent / "hybridgi"
#: `hybridgi render` settings of the quick renders these tests compare: a coarse, short warm-up.
QUICK = ("--set", "warmup_iterations=2", "--set", "resolution=12", "--set", "rays_per_cell=16")
#: The Cycles these tests compare with: 64 spp and its denoiser.
CYCLES = ("--engine", "CYCLES", "--samples", "64", "--set", "cycles.use_denoising=true")


def run_bpy(script: str, *argv: str, **replace: str) -> None:
    """Run bpy code in a subprocess of this environment's Python (its own bpy: the test process's
    scene stays as it is), its `sys.argv` ending in argv; each KEY=value of `replace` substitutes
    repr(value) for KEY in the code (a path the script saves to). Fails the test if it fails."""
    for key, value in replace.items():
        script = script.replace(key, repr(value))
    subprocess.run([sys.executable, "-c", script, *argv], check=True, capture_output=True, timeout=300)


def cornell_variants(out: Path, script: str) -> Path:
    """Build the Cornell box into `out`, then run `script` (bpy code; `src` names the box's file,
    `out` the folder) in a bpy subprocess that saves its variants there: the user's files and the
    bundled scenes stay untouched. Returns `out`."""
    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, str(root / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(out)],
                   check=True, capture_output=True)
    prelude = f"import bpy\nsrc = {str(out / 'cornell.blend')!r}\nout = {str(out)!r}\n"
    subprocess.run([sys.executable, "-c", prelude + script], check=True, capture_output=True)
    return out


def run_render(blend, prefix, res, *extra, env=None) -> subprocess.CompletedProcess:
    """`hybridgi render BLEND --out PREFIX --res RES EXTRA...`, its output captured."""
    return subprocess.run([str(HYBRIDGI), "render", str(blend), "--out", str(prefix), "--res", res, *extra],
                          capture_output=True, text=True, timeout=600, env=env)


def rendered(blend, prefix, res, *extra, env=None) -> dict:
    """The channels of the multilayer EXR of a render that must succeed."""
    run = run_render(blend, prefix, res, *extra, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    return exr.read_channels(json.loads(run.stdout.strip().splitlines()[-1])["exr"])


def against_cycles(blend, folder: Path, res: str, samples: int = 256) -> tuple[dict, dict, np.ndarray]:
    """(ours, cycles, geometry): the channels of BLEND rendered by HybridGI at its defaults and by
    Cycles at `samples` spp (prefixes folder/hg and folder/cy), and the Cycles render's geometry
    pixels (h, w) bool, over which `pass_error` compares them."""
    ours = rendered(blend, folder / "hg", res)
    cycles = rendered(blend, folder / "cy", res, "--engine", "CYCLES", "--samples", str(samples))
    return ours, cycles, layer(cycles, "Depth", "Z")[..., 0] < 1e9


def layer(channels, name, components="RGB") -> np.ndarray:
    """(h, w, len(components)) float32 of a pass (rows top-down, as the EXR stores them)."""
    return np.stack([channels[f"ViewLayer.{name}.{c}"] for c in components], axis=-1)


def pass_error(ours: dict, reference: dict, name: str, mask: np.ndarray) -> float:
    """Relative L1 of pass `name` (RGB) of two renders' channels over the pixels `mask`."""
    a, b = layer(ours, name)[mask], layer(reference, name)[mask]
    return float(np.abs(a - b).sum() / np.abs(b).sum())


#: bpy code (after `import bpy` and `from mathutils import Vector`) of the helpers the scene
#: scripts share: a Principled material of a colour, a camera looking at a point (the scene's),
#: a sun shining along a direction.
STAGE_HELPERS = """
def material(name, rgb, roughness=0.5):
    m = bpy.data.materials.new(name)
    m.use_nodes = True
    bsdf = m.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*rgb, 1.0)
    bsdf.inputs["Roughness"].default_value = roughness
    return m
def camera_at(location, target, lens=None):
    cam = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    cam.location = location
    cam.rotation_euler = (Vector(target) - cam.location).to_track_quat("-Z", "Y").to_euler()
    if lens is not None:
        cam.data.lens = lens
    bpy.context.scene.collection.objects.link(cam)
    bpy.context.scene.camera = cam
    return cam
def sun_towards(direction, energy):
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = energy
    sun.rotation_euler = Vector(direction).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(sun)
    return sun
def area_lamp_at(location, target, energy, size, name="lamp"):
    lamp = bpy.data.objects.new(name, bpy.data.lights.new(name, "AREA"))
    lamp.data.energy = energy
    lamp.data.size = size
    lamp.location = location
    lamp.rotation_euler = (Vector(target) - lamp.location).to_track_quat("-Z", "Y").to_euler()
    bpy.context.scene.collection.objects.link(lamp)
    return lamp
"""


#: bpy code (for `run_bpy` scripts, after `import math, bpy`) of a stage for one object: an empty
#: scene, a camera 3.2 m in front of the origin looking slightly down, a 3-degree sun, a grey-blue
#: world and a 20 m floor 1 m below; then a smooth unit UV sphere at the origin, the active object.
LIT_SPHERE_STAGE = """
bpy.ops.wm.read_homefile(use_empty=True)
scene = bpy.context.scene
cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
cam.location, cam.rotation_euler = (0, -3.2, 1.2), (math.radians(80), 0, 0)
scene.collection.objects.link(cam)
scene.camera = cam
sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
sun.data.energy, sun.data.angle = 3.0, math.radians(3)
sun.rotation_euler = (math.radians(-40), math.radians(25), 0)
scene.collection.objects.link(sun)
scene.world = bpy.data.worlds.new("grey")
if scene.world.node_tree is None:
    scene.world.use_nodes = True
scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.3, 0.35, 0.4, 1)
bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, -1))
bpy.ops.mesh.primitive_uv_sphere_add(radius=1.0, segments=64, ring_count=32)
bpy.ops.object.shade_smooth()
"""


def principled_sphere_scene(name: str, inputs: dict) -> str:
    """bpy code (for `run_bpy`, with OUT the folder) of `LIT_SPHERE_STAGE` whose sphere wears a
    Principled BSDF material `name` with these input values (name -> float or RGBA tuple), saved
    as OUT/`name`.blend."""
    return "import math, bpy\n" + LIT_SPHERE_STAGE + f"""
m = bpy.data.materials.new({name!r})
if m.node_tree is None:
    m.use_nodes = True
bsdf = m.node_tree.nodes["Principled BSDF"]
for key, value in {inputs!r}.items():
    bsdf.inputs[key].default_value = value
bpy.context.object.data.materials.append(m)
bpy.ops.wm.save_as_mainfile(filepath=f"{{OUT}}/{name}.blend")
"""
