"""What differs between the Blender versions HybridGI supports (4.2 LTS, 4.5 LTS, 5.0, 5.1+), for the
code that drives the bpy module from outside the add-on: the CLI, `blend_scenes/build.py`, the
benchmarks and the tests. The add-on's own differences live in `addon/compat.py` (an installed
extension ships without this package).

Importing this module does not import bpy: the functions that need it take it as an argument or
import it when called.
"""

from __future__ import annotations

import importlib.metadata
import os
import re
import shutil
import sys
from pathlib import Path

#: The Blender whose bpy `make setup` installs without BLENDER=... (README, CI's full suite).
DEFAULT_BLENDER = (5, 0)

#: Cycles' pass names before Blender 5.0, and the names 5.0 gave them (the other passes kept
#: theirs); the add-on's own copy is `addon/compat.py`'s (an extension ships without this package).
LEGACY_PASS_NAMES = {
    "DiffDir": "Diffuse Direct",
    "DiffInd": "Diffuse Indirect",
    "DiffCol": "Diffuse Color",
    "AO": "Ambient Occlusion",
    "GlossDir": "Glossy Direct",
    "GlossInd": "Glossy Indirect",
    "GlossCol": "Glossy Color",
}

ROOT = Path(__file__).resolve().parent.parent


def blender_version() -> tuple[int, int]:
    """(major, minor) of the bpy in this environment, without importing it; DEFAULT_BLENDER where
    bpy is not installed (bpy-free tests)."""
    bpy = sys.modules.get("bpy")
    if bpy is not None:
        return tuple(bpy.app.version[:2])
    try:
        text = importlib.metadata.version("bpy")
    except importlib.metadata.PackageNotFoundError:
        return DEFAULT_BLENDER
    major, minor, *_rest = text.split(".")
    return int(major), int(minor)


def scenes_dir(version: tuple[int, int] | None = None) -> Path:
    """Where `make scenes` puts the bundled .blend files built by this Blender: blend_scenes/ for
    the default version, blend_scenes/blender-X.Y/ for the others (Blender cannot open files
    saved by a newer version, so each builds its own from procedural.py)."""
    version = version or blender_version()
    folder = ROOT / "blend_scenes"
    return folder if version == DEFAULT_BLENDER else folder / f"blender-{version[0]}.{version[1]}"


def cycles_pass_name(name: str, version: tuple[int, int] | None = None) -> str:
    """The name that Blender version's Cycles (and HybridGI) gives the pass `name` (5.0's name)."""
    if (version or blender_version()) >= (5, 0):
        return name
    return {new: old for old, new in LEGACY_PASS_NAMES.items()}.get(name, name)


def saved_by(path: str | Path) -> tuple[int, int]:
    """(major, minor) of the Blender that saved the .blend file (plain, gzip or zstd), from its
    header: `BLENDER-v402...` up to 4.x, `BLENDER17-01v0500...` from 5.0."""
    with open(path, "rb") as fh:
        magic = fh.read(4)
        fh.seek(0)
        if magic == b"\x28\xb5\x2f\xfd":
            import zstandard  # noqa: PLC0415  (a dependency of every bpy wheel)

            header = zstandard.ZstdDecompressor().stream_reader(fh).read(17)
        elif magic[:2] == b"\x1f\x8b":
            import gzip  # noqa: PLC0415

            header = gzip.GzipFile(fileobj=fh).read(17)
        else:
            header = fh.read(17)
    match = re.match(rb"BLENDER(?:[-_][vV](\d)|\d\d-\d\d[vV](\d\d))(\d\d)", header)
    if match is None:
        raise ValueError(f"{path} is not a .blend file")
    return int(match.group(1) or match.group(2)), int(match.group(3))


def opens_here(path: str | Path) -> bool:
    """Whether this Blender can open the file: any older one's, and from 4.5 on also 5.x files
    (4.2 cannot read the file header 5.0 introduced)."""
    saved = saved_by(path)
    here = blender_version()
    return saved <= here or (here >= (4, 5) and saved[0] <= 5)


# --- data-block creation -------------------------------------------------------------------------


def new_material(bpy, name: str):
    """A material with its default node tree (Principled BSDF -> Material Output). Before 5.0,
    `materials.new` makes no node tree until `use_nodes` is set (5.0 deprecates the flag)."""
    mat = bpy.data.materials.new(name)
    if bpy.app.version < (5, 0, 0):
        mat.use_nodes = True
    return mat


def new_world(bpy, name: str):
    """A world with its default node tree (Background -> World Output); see new_material."""
    world = bpy.data.worlds.new(name)
    if bpy.app.version < (5, 0, 0):
        world.use_nodes = True
    return world


def fcurve_ensure(bpy, action, datablock, path: str, index: int):
    """The action's F-Curve for datablock.path[index], made if missing. Blender 4.4 brought slotted
    actions and `fcurve_ensure_for_datablock`; 5.0 removed the legacy `Action.fcurves`."""
    if bpy.app.version >= (4, 4, 0):
        return action.fcurve_ensure_for_datablock(datablock, path, index=index)
    return action.fcurves.find(path, index=index) or action.fcurves.new(path, index=index)


# --- image output --------------------------------------------------------------------------------


def set_file_format(bpy, settings, file_format: str) -> None:
    """settings.file_format = file_format. Blender 5.0 added `media_type`, which must name the
    kind of file (single image or multilayer) before a format of that kind can be chosen."""
    if bpy.app.version >= (5, 0, 0):
        settings.media_type = "MULTI_LAYER_IMAGE" if file_format == "OPEN_EXR_MULTILAYER" else "IMAGE"
    settings.file_format = file_format


# --- leaving the process -------------------------------------------------------------------------


def exit_now(status: int) -> None:
    """Leave without finalizing Python once bpy was imported.

    bpy's teardown is version-dependent noise or worse: 4.2 segfaults after a PropertyGroup with
    Python methods was registered (exit status 139 after a successful run), 4.5 prints
    "Not freed memory blocks" on stdout (which the CLI keeps for JSON). Everything the caller
    wrote is flushed first; Blender's session temp folder is removed as its teardown would.
    """
    bpy = sys.modules.get("bpy")
    if bpy is None:
        sys.exit(status)
    tempdir = getattr(bpy.app, "tempdir", "")
    sys.stdout.flush()
    sys.stderr.flush()
    if tempdir and os.path.basename(os.path.normpath(tempdir)).startswith("blender_"):
        shutil.rmtree(tempdir, ignore_errors=True)
    os._exit(status)


def lights_have_exposure(bpy) -> bool:
    """Whether lights have `exposure`, `normalize` and `use_temperature` (not in Blender 4.2)."""
    return "exposure" in bpy.types.Light.bl_rna.properties
