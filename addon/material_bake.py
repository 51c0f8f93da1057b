"""Colour inputs the reader cannot fold, evaluated by Blender itself into a texture per mesh.

A Base Color fed by procedural textures, Color Ramps, mixes of textures, Color Attributes,
image textures through colour nodes, a non-active UV map, box mapping... is not re-implemented:
Cycles bakes the socket's value (an Emission shader fed by the socket, bake type EMIT: exactly
the input's colour, with none of the BSDF's weights, which `sync` applies as for an image) over
a UV layout of its own, one cell per pair of triangles (`atlas_uvs`), so overlapping or missing
UV maps do not matter. The triangles of that material then carry the atlas UVs and the baked
texture, through the same plumbing as an image texture (probe hits: `shading.SurfaceTable`; the
G-buffer: `raster/gbuffer`).

An emission whose colour or strength is linked (`sync.EMISSION_BAKE`) is baked the same way as
their product: one Emission shader fed by both, so the texture is the emitted radiance, HDR
(float bake; the disk copy is float16, radiance clipped at its 65504).

The bake runs Cycles in a separate process, like `world_bake` (a bake cannot run inside a
render, and the user's data must not change): the mesh travels as arrays (the triangles of the
material's slot, object-space corners, every UV map and colour attribute, the texture space), the
material as a library file. One process bakes every job of a sync. Results are cached by a
content key (the node tree, nested groups and images included; the socket; the mesh arrays; the
bake size; the Blender version) in memory and on disk (`~/.cache/hybridgi/materials`), so an
unchanged material costs nothing on the next sync and an edit bakes again.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np

from . import world_bake
from .bake_store import BakeStore

log = logging.getLogger(__name__)

#: Texels along one atlas cell (two triangles) before the size is clamped, and the clamp: small
#: meshes get detail, the largest (200k triangles) still the average colour of each triangle.
TEXELS_PER_CELL = 24
MIN_SIZE, MAX_SIZE = 512, 2048
SIZE_STEP = 64
#: Texels kept free around each triangle of a cell, and between its two triangles: the bake's
#: margin fills them, so bilinear lookups near an edge never read the neighbouring triangle.
PAD, GAP = 1.5, 1.0
#: Bake margin in texels (Blender's extend mode fills the pads from each triangle's edge).
MARGIN = 4
#: Cycles samples per texel (emission only: no noise, just antialiasing of fine patterns).
BAKE_SAMPLES = 4
#: Seconds one bake process (all of a sync's jobs) may take.
BAKE_TIMEOUT_S = 300
#: Baked textures kept in memory.
KEPT = 64
#: Bumped when the bake script or the layout changes (part of every key).
VERSION = 1

#: Finished textures (memory and ~/.cache/hybridgi/materials, float16 on disk: albedos need no
#: more) and the background bakes.
STORE = BakeStore("materials", KEPT, disk_dtype=np.float16)


@dataclass
class BakeJob:
    """One socket of one material over the triangles of one mesh slot.

    positions, normals : (3T, 3) float32 object-space corners, three per triangle, and their
        shading normals
    uv_maps : name -> (3T, 2) float32; colors : name -> (3T, 4) float32 (corner domain)
    """

    material: object  # bpy.types.Material (main thread only)
    node: str
    socket: str
    positions: np.ndarray
    uv_maps: dict[str, np.ndarray] = field(default_factory=dict)
    render_uv: str | None = None
    normals: np.ndarray | None = None  # (3T, 3) float32 object-space shading normals
    colors: dict[str, np.ndarray] = field(default_factory=dict)
    texspace: tuple = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    key: str = ""
    source: str = ""  # the node feeding the input, for messages
    #: The mesh deforms over the animation: its positions stay out of the key, so the texture of
    #: the first frame serves every frame (UV and Generated coordinates do not move with the
    #: surface; a texture in Object coordinates would, and is not baked again).
    dynamic: bool = False
    #: The Object Info values the material reads for the object this bake is for (`sync.object_values`:
    #: random, location, color, object_index), or None: the bake process feeds them as constants.
    object_values: dict | None = None

    @property
    def what(self) -> str:
        return f"{self.socket} of {self.node!r}" + (f" (from {self.source!r})" if self.source else "")

    @property
    def triangles(self) -> int:
        return self.positions.shape[0] // 3

    @property
    def size(self) -> int:
        return bake_size(self.triangles)


def bake_size(n_triangles: int) -> int:
    """Texture side for an atlas of `n_triangles`: TEXELS_PER_CELL per cell, rounded up to a
    multiple of SIZE_STEP and clamped to [MIN_SIZE, MAX_SIZE]."""
    cells = max(1, math.ceil(math.sqrt(math.ceil(n_triangles / 2))))
    return int(min(MAX_SIZE, max(MIN_SIZE, -(-cells * TEXELS_PER_CELL // SIZE_STEP) * SIZE_STEP)))


def cell_texels(n_triangles: int) -> float:
    """Texels along one atlas cell (two triangles) of a bake of `n_triangles`."""
    return bake_size(n_triangles) / max(1, math.ceil(math.sqrt(math.ceil(n_triangles / 2))))


def atlas_uvs(n_triangles: int, size: int) -> np.ndarray:
    """(n, 3, 2) float32 UVs in [0, 1]: triangle 2k and 2k+1 share cell k (row-major), the first
    below the cell's diagonal, the second above it, each inset by PAD texels and GAP apart."""
    cells = max(1, math.ceil(math.sqrt(math.ceil(n_triangles / 2))))
    c = size / cells  # texels per cell
    p, g = min(PAD, c / 8), min(GAP, c / 8)
    lower = np.array([[p, p], [c - p - g, p], [p, c - p - g]], np.float64)
    upper = np.array([[c - p, c - p], [p + g, c - p], [c - p, p + g]], np.float64)
    i = np.arange(n_triangles)
    cell = i // 2
    origin = np.stack([cell % cells, cell // cells], axis=1).astype(np.float64) * c
    shape = np.where((i % 2 == 0)[:, None, None], lower[None], upper[None])
    return ((origin[:, None, :] + shape) / size).astype(np.float32)


def used_texels(n_triangles: int, size: int) -> np.ndarray:
    """(size, size) bool: texels of the cells the atlas uses (the rest is never looked up)."""
    cells = max(1, math.ceil(math.sqrt(math.ceil(n_triangles / 2))))
    n_cells = math.ceil(n_triangles / 2)
    c = size / cells
    idx = np.arange(size)
    col = np.minimum((idx + 0.5) // c, cells - 1).astype(np.int64)
    return (col[:, None] * cells + col[None, :]) < n_cells  # [row (v), column (u)]


# --- content keys --------------------------------------------------------------------------


def job_key(job: BakeJob) -> str:
    digest = hashlib.sha256(f"{VERSION}|{bpy.app.version_string}|{job.node}|{job.socket}|{job.size}".encode())
    world_bake.tree_digest(digest, job.material.node_tree)
    if not job.dynamic:
        digest.update(np.ascontiguousarray(job.positions).tobytes())
    digest.update(f"{job.triangles}|{job.dynamic}".encode())
    for name in sorted(job.uv_maps):
        digest.update(name.encode() + np.ascontiguousarray(job.uv_maps[name]).tobytes())
    for name in sorted(job.colors):
        digest.update(name.encode() + np.ascontiguousarray(job.colors[name]).tobytes())
    if job.normals is not None and not job.dynamic:
        digest.update(np.ascontiguousarray(job.normals).tobytes())
    digest.update(repr((job.render_uv, job.texspace)).encode())
    if job.object_values is not None:
        digest.update(repr(sorted(job.object_values.items())).encode())
    return digest.hexdigest()[:32]


# --- cache ---------------------------------------------------------------------------------


def cached(key: str) -> np.ndarray | None:
    """(size, size, 3) float32 texture of a finished bake, from memory or disk, or None."""
    return STORE.get(key)


# --- baking --------------------------------------------------------------------------------


def bake(jobs: list[BakeJob], wait: bool = True) -> dict[str, np.ndarray]:
    """key -> (size, size, 3) float32 texture for every job baked or cached. Jobs not cached are
    baked together in one process (wait=True) or in the background (wait=False: the caller keeps
    its fallback until `STORE.completed` changes). A failed bake is logged and left out."""
    out = {}
    todo = []
    for job in jobs:
        job.key = job.key or job_key(job)
        texture = cached(job.key)
        if texture is not None:
            out[job.key] = texture
        elif all(job.key != other.key for other in todo):
            todo.append(job)
    if not todo:
        return out
    tmp = tempfile.mkdtemp(prefix="hybridgi_bake_")
    try:
        cmd = _command(todo, tmp)
    except (OSError, RuntimeError) as err:
        shutil.rmtree(tmp, ignore_errors=True)
        log.warning("materials %s could not be written for baking (%s); using their constant colours",
                    ", ".join(sorted({job.material.name for job in todo})), err)
        return out
    described = [(job.key, job.material.name, job.what, job.size, job.triangles) for job in todo]
    if not wait:
        _start(cmd, tmp, described)
        return out
    try:
        out.update(_run(cmd, tmp, described))
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def pending() -> bool:
    return STORE.pending()


def _start(cmd, tmp, described) -> None:
    name = ",".join(key for key, *_ in described)
    if STORE.running(name):
        shutil.rmtree(tmp, ignore_errors=True)
        return

    def work():
        try:
            _run(cmd, tmp, described)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    STORE.start(name, work, "hybridgi-material-bake")


def _command(jobs: list[BakeJob], tmp: str) -> list[str]:
    """Write the materials (a library .blend) and each job's mesh arrays; the process's command."""
    # One library file per material: a partial write of several at once dropped all but one.
    blends = {}
    for job in jobs:
        if job.material.name not in blends:
            blends[job.material.name] = os.path.join(tmp, f"material{len(blends)}.blend")
            # The original datablock: a render's depsgraph hands out evaluated copies, which Blender
            # 4.2 and 4.5 write as an empty library (every bake failed there: "KeyError") and 5.0
            # with a "loopback" error.
            original = getattr(job.material, "original", None) or job.material
            bpy.data.libraries.write(blends[job.material.name], {original}, path_remap="ABSOLUTE", fake_user=True)
    specs = []
    for job in jobs:
        arrays = {"positions": job.positions, "atlas": atlas_uvs(job.triangles, job.size).reshape(-1, 2)}
        if job.normals is not None:
            arrays["normals"] = job.normals
        for i, name in enumerate(job.uv_maps):
            arrays[f"uv{i}"] = job.uv_maps[name]
        for i, name in enumerate(job.colors):
            arrays[f"color{i}"] = job.colors[name]
        np.savez(os.path.join(tmp, f"{job.key}.npz"), **arrays)
        specs.append({"key": job.key, "material": job.material.name, "blend": blends[job.material.name],
                      "node": job.node, "socket": job.socket,
                      "size": job.size, "uv_maps": list(job.uv_maps), "render_uv": job.render_uv,
                      "colors": list(job.colors), "texspace": [list(v) for v in job.texspace],
                      "object_values": job.object_values})
    with open(os.path.join(tmp, "jobs.json"), "w") as f:
        json.dump({"samples": BAKE_SAMPLES, "margin": MARGIN, "jobs": specs}, f)
    args = [os.path.join(tmp, "jobs.json"), tmp]
    script = Path(__file__).with_name("material_bake_process.py").read_text()
    if bpy.app.binary_path:  # inside Blender: its own binary, headless
        return [bpy.app.binary_path, "-b", "--factory-startup", "--python-expr", script, "--", *args]
    return [sys.executable, "-c", script, *args]


def _run(cmd, tmp, described) -> dict[str, np.ndarray]:
    """Run the bake process; read, fill and cache its textures (any thread: no bpy)."""
    t0 = time.perf_counter()
    names = ", ".join(sorted({name for _, name, *_ in described}))
    try:
        run = subprocess.run(cmd, capture_output=True, text=True, timeout=BAKE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired) as err:
        log.warning("materials %s could not be baked (%s); using their constant colours", names, err)
        return {}
    out = {}
    for key, material, node, size, n_tri in described:
        path = os.path.join(tmp, f"{key}.npy")
        if not os.path.isfile(path):
            reason = _reason(tmp, key, run)
            log.warning("material %r: %s could not be baked (%s); using its constant value", material, node, reason)
            continue
        texture = np.load(path).astype(np.float32)
        seconds = Path(path).with_suffix(".s")
        if seconds.is_file():
            log.info("material %r: %s baked (%dx%d, %d triangles) in %s s", material, node, size, size, n_tri,
                     seconds.read_text().strip())
        used = used_texels(n_tri, size)
        if not used.all():
            texture[~used] = texture[used].mean(axis=0)  # the texture's mean stays the surface's
        if not np.isfinite(texture).all():
            texture = np.nan_to_num(texture, nan=0.0, posinf=0.0, neginf=0.0)
        np.minimum(texture, np.float32(65504.0), out=texture)  # float16's largest, on disk and in the G-buffer
        STORE.put(key, texture)
        out[key] = texture
    log.info("baked %d material texture(s) (%s) in %.1f s, the process's start included", len(out), names,
             time.perf_counter() - t0)
    return out


def _reason(tmp, key, run) -> str:
    err = os.path.join(tmp, f"{key}.err")
    if os.path.isfile(err):
        return Path(err).read_text().strip().splitlines()[-1][:300]
    tail = (run.stderr or run.stdout or "").strip().splitlines()[-2:]
    return f"exit {run.returncode}: " + " | ".join(tail)
