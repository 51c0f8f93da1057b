"""`hybridgi`: headless renders of .blend files through the bpy module.

    hybridgi render SCENE.blend --out PREFIX [--frames A[-B]] [--res WxH]
                    [--engine HYBRIDGI|CYCLES|BLENDER_EEVEE] [--set NAME=VALUE ...] [--samples N]
    hybridgi check

stdout carries only JSON, one line per rendered frame (Blender's own messages are moved to
stderr, and the command leaves without bpy's teardown, which prints on stdout in some versions),
so a caller can parse it line by line. Exit status: 0 on success, 1 when a scene cannot
be loaded, a setting is refused, the output cannot be written or a frame fails (one
`hybridgi: error: ...` line on stderr, no traceback), 2 for bad arguments, 130 after Ctrl-C.
Frames are written atomically (`output.py`): a failed or interrupted frame leaves no file.
"""

from __future__ import annotations

import argparse
import atexit
import contextlib
import importlib
import json
import logging
import math
import os
import re
import shutil
import sys
import tempfile
import time
from pathlib import Path

from hybridgi_core.cycles_reference import CYCLES_REFERENCE
from hybridgi_core.rendering import rendering

from . import blender_compat, dev_install, interrupt, output, tracebacks

ENGINES = ("HYBRIDGI", "CYCLES", "BLENDER_EEVEE")

#: View-layer flags of the passes every engine writes (Cycles' names; see addon/engine.py PASSES).
PASS_FLAGS = (
    "use_pass_combined",
    "use_pass_z",
    "use_pass_normal",
    "use_pass_diffuse_direct",
    "use_pass_diffuse_indirect",
    "use_pass_diffuse_color",
    "use_pass_ambient_occlusion",
)

#: Where an undotted --set name lives, per engine.
SETTINGS_OWNER = {"HYBRIDGI": "hybridgi", "CYCLES": "cycles", "BLENDER_EEVEE": "eevee"}


_TRUE = {"1", "true", "yes", "on"}
_FALSE = {"0", "false", "no", "off"}


class CliError(Exception):
    """A failure to report on stderr with exit status 1."""


#: Set (to anything) to print the traceback of an internal error after its one-line message.
DEBUG_ENV = "HYBRIDGI_DEBUG"

#: Folders this process created (the throw-away Blender user folder, Blender's session temp
#: folder), removed when a signal ends the process (a normal exit removes them by itself).
_OWN_FOLDERS: list[str] = []


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command == "render" and not args.blend.is_file():
        parser.error(f"scene not found: {args.blend}")
    if argv is None:
        # The process is this command: it owns the signals and stderr (a caller of main(argv)
        # from Python keeps its own).
        interrupt.install(cleanups=(_remove_own_folders,))
        if not os.environ.get(DEBUG_ENV):
            tracebacks.hold()
    try:
        return args.run(args)
    except (CliError, output.OutputError) as err:
        return fail(str(err))
    except KeyboardInterrupt:
        output.discard_pending()
        return fail("interrupted; the unfinished frame was not written", 130)
    except Exception as err:  # noqa: BLE001  (the one place any failure becomes one error line)
        if os.environ.get(DEBUG_ENV):
            import traceback  # noqa: PLC0415

            traceback.print_exc()
        hint = "" if os.environ.get(DEBUG_ENV) else f" ({DEBUG_ENV}=1 shows the traceback)"
        return fail(f"internal error: {type(err).__name__}: {err}{hint}")


def fail(message: str, status: int = 1) -> int:
    """Print the one `hybridgi: error:` line (newlines folded) and return the exit status."""
    print(f"hybridgi: error: {one_line(message)}", file=sys.stderr, flush=True)
    return status


def one_line(text: str) -> str:
    return " | ".join(part.strip() for part in str(text).splitlines() if part.strip()) or "unknown error"


def _remove_own_folders() -> None:
    for folder in _OWN_FOLDERS:
        shutil.rmtree(folder, ignore_errors=True)


def console_main() -> None:
    """The `hybridgi` command: main(), then leave without bpy's teardown (blender_compat.exit_now;
    it skips atexit, so the command's own folders are removed here)."""
    status = main()
    _remove_own_folders()
    blender_compat.exit_now(status)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hybridgi", description="Headless HybridGI renders through the bpy module.")
    commands = parser.add_subparsers(dest="command", required=True)

    render = commands.add_parser("render", help="render frames of a .blend file to PNG + multilayer EXR")
    render.add_argument("blend", type=Path, metavar="SCENE.blend")
    render.add_argument(
        "--out", required=True, metavar="PREFIX",
        help="writes PREFIX_####.png and PREFIX_####.exr; //PREFIX is relative to the .blend file's folder; "
        "a folder (trailing slash or existing) gets <blend name>_####.*; # in the name marks the frame number",
    )
    render.add_argument("--frames", type=frame_range, metavar="A[-B]", help="frames to render (default: current)")
    render.add_argument("--res", type=resolution, metavar="WxH", help="resolution at 100%% (default: the scene's)")
    render.add_argument("--engine", choices=ENGINES, default="HYBRIDGI")
    render.add_argument(
        "--set", action="append", default=[], type=assignment, metavar="NAME=VALUE", dest="settings",
        help="scene setting: NAME alone is the engine's own (scene.hybridgi/.cycles/.eevee), "
        "a dotted NAME is a path from the scene (cycles.samples=64, render.film_transparent=true)",
    )
    render.add_argument("--samples", type=positive_int, metavar="N", help="Cycles/EEVEE samples per pixel")
    render.set_defaults(run=run_render)

    check = commands.add_parser("check", help="enable the add-on from this checkout and report whether it registers")
    check.set_defaults(run=run_check)
    return parser


# --- argument types (argparse turns their ValueErrors into a usage error, exit status 2) -----


def frame_range(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(-?\d+)(?:-(-?\d+))?", text.strip())
    if not match:
        raise argparse.ArgumentTypeError(f"frames must be A or A-B, got {text!r}")
    first = int(match.group(1))
    last = int(match.group(2)) if match.group(2) is not None else first
    if last < first:
        raise argparse.ArgumentTypeError(f"frame range {text!r} ends before it starts")
    return first, last


def resolution(text: str) -> tuple[int, int]:
    match = re.fullmatch(r"(\d+)[xX](\d+)", text.strip())
    if not match or int(match.group(1)) < 4 or int(match.group(2)) < 4:
        raise argparse.ArgumentTypeError(f"resolution must be WxH with W, H >= 4, got {text!r}")
    return int(match.group(1)), int(match.group(2))


def assignment(text: str) -> tuple[str, str]:
    name, sep, value = text.partition("=")
    if not sep or not name.strip():
        raise argparse.ArgumentTypeError(f"--set needs NAME=VALUE, got {text!r}")
    return name.strip(), value.strip()


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return value


# --- commands --------------------------------------------------------------------------------


def run_render(args) -> int:
    # The output is checked before bpy loads: a path that cannot be written fails in milliseconds.
    prefix = output.resolve_prefix(args.out, args.blend)
    output.prepare_folder(prefix)
    with json_stdout() as out:
        bpy = import_bpy()
        uses_addon = args.engine == "HYBRIDGI" or any(name.startswith("hybridgi.") for name, _v in args.settings)
        addon = enable_addon() if uses_addon else None
        scene = open_scene(bpy, args.blend)
        configure(scene, args)
        if addon is not None:
            check_core_settings(scene)
        first, last = args.frames or (scene.frame_current, scene.frame_current)
        # HybridGI's frames keep its render settings between them too (`rendering`, which each
        # frame holds as well); another engine's render is left to its own allocator and interval.
        with rendering() if args.engine == "HYBRIDGI" else contextlib.nullcontext():
            for i, frame in enumerate(range(first, last + 1), 1):
                _render_one(bpy, scene, args, prefix, out, addon, frame, f"{i}/{last - first + 1}")
    return 0


def _render_one(bpy, scene, args, prefix, out, addon, frame: int, of: str) -> None:
    progress(f"frame {frame} ({of}): rendering with {args.engine}")
    png, exr = output.frame_paths(prefix, frame)
    with output.FrameFiles(png, exr) as files:
        record = render_frame(bpy, scene, frame, files, args.engine, addon)
        with output.COMMIT_LOCK:
            files.commit()
            out.write(json.dumps(record) + "\n")
            out.flush()
    progress(f"frame {frame} ({of}): {record['seconds']:.2f} s -> {record['png']}")


def run_check(args) -> int:
    with json_stdout() as out:
        bpy = import_bpy()
        addon = enable_addon()
        record = {
            "addon": addon.__name__,
            "path": str(Path(addon.__file__).resolve().parent),
            "engine_registered": dev_install.engine_registered(),
            "blender": bpy.app.version_string,
        }
        out.write(json.dumps(record) + "\n")
    return 0


# --- steps -----------------------------------------------------------------------------------


@contextlib.contextmanager
def json_stdout():
    """A file on the real stdout for JSON lines, while fd 1 points at stderr.

    Blender's C code prints render progress straight to fd 1; moving fd 1 is the only way to keep
    it out of the JSON stream.
    """
    sys.stdout.flush()
    saved = os.dup(1)
    os.dup2(2, 1)
    out = os.fdopen(os.dup(saved), "w", buffering=1)
    try:
        yield out
    finally:
        out.close()
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def import_bpy():
    """Import bpy with a throw-away Blender user folder unless the caller chose one."""
    if "bpy" not in sys.modules and "BLENDER_USER_RESOURCES" not in os.environ:
        folder = tempfile.mkdtemp(prefix="hybridgi_cli_")
        os.environ["BLENDER_USER_RESOURCES"] = folder
        _OWN_FOLDERS.append(folder)
        # Registered before bpy's own exit handler, so it runs after it (atexit is LIFO).
        atexit.register(shutil.rmtree, folder, ignore_errors=True)
    import bpy  # noqa: PLC0415

    # Blender's session temp folder: Blender removes it at a normal exit, an interrupt must.
    session_tmp = Path(bpy.app.tempdir)
    if session_tmp.name.startswith("blender_") and str(session_tmp) not in _OWN_FOLDERS:
        _OWN_FOLDERS.append(str(session_tmp))
    return bpy


def enable_addon():
    try:
        package = dev_install.enable()
    except dev_install.DevInstallError as err:
        raise CliError(str(err)) from err
    log_to_stderr(package.__name__)
    return package


def log_to_stderr(package_name: str) -> None:
    """The add-on's INFO records on stderr: warm-up progress with the time left, frame times."""
    logger = logging.getLogger(package_name)
    if not any(getattr(h, "hybridgi_cli", False) for h in logger.handlers):
        handler = logging.StreamHandler(sys.stderr)
        handler.setFormatter(logging.Formatter("hybridgi: %(message)s"))
        handler.hybridgi_cli = True
        logger.addHandler(handler)
        logger.setLevel(logging.INFO)


def open_scene(bpy, path: Path):
    try:
        bpy.ops.wm.open_mainfile(filepath=str(path.resolve()), load_ui=False)
    except RuntimeError as err:
        raise CliError(f"cannot open {path}: {err}") from err
    scene = bpy.context.scene
    if scene.camera is None:
        raise CliError(f"{path}: scene {scene.name!r} has no camera")
    return scene


def configure(scene, args) -> None:
    """Engine, resolution, reference settings, passes, then the user's --set values (they win)."""
    scene.render.engine = args.engine
    if args.res:
        scene.render.resolution_x, scene.render.resolution_y = args.res
        scene.render.resolution_percentage = 100
    if args.engine == "CYCLES":
        for name, value in CYCLES_REFERENCE.items():
            setattr(scene.cycles, name, value)
        if args.samples:
            scene.cycles.samples = args.samples
    elif args.engine == "BLENDER_EEVEE" and args.samples:
        scene.eevee.taa_render_samples = args.samples
    elif args.samples:
        progress("--samples is ignored by HYBRIDGI (see --set rays_per_cell=N)")
    for view_layer in scene.view_layers:
        for flag in PASS_FLAGS:
            setattr(view_layer, flag, True)
    for name, value in args.settings:
        assign(scene, name, value, args.engine)
    if scene.render.use_multiview:
        # Blender then writes one image per view; this command's files are one image per frame
        # (Blender refused to save them: "Image 'Render Result' could not be saved", Cycles too).
        raise CliError("Stereoscopy is on (Output Properties > Stereoscopy): hybridgi render writes one "
                       "image per frame; turn it off (--set render.use_multiview=false)")


def assign(scene, name: str, text: str, engine: str) -> None:
    """scene.<owner>.<name> = value parsed by the property's RNA type."""
    path = name if "." in name else f"{SETTINGS_OWNER[engine]}.{name}"
    owner_path, _dot, attr = path.rpartition(".")
    try:
        owner = scene.path_resolve(owner_path)
    except ValueError:
        raise CliError(f"--set {name}: scene has no {owner_path!r}") from None
    prop = owner.bl_rna.properties.get(attr)
    if prop is None or prop.is_readonly:
        raise CliError(f"--set {name}: {owner_path} has no writable setting {attr!r}")
    try:
        value = parse_value(prop, text)
        check_value(prop, value)
        setattr(owner, attr, value)
    except (TypeError, ValueError) as err:
        raise CliError(f"--set {name}={text}: {err}") from None


def check_value(prop, value) -> None:
    """Refuse what Blender would clamp silently: non-finite numbers and values outside the
    property's hard range (ValueError naming the range)."""
    if prop.type not in ("INT", "FLOAT"):
        return
    for v in value if isinstance(value, list) else [value]:
        if not math.isfinite(v):
            raise ValueError(f"{v!r} is not a finite number (valid: {_range_text(prop)})")
        if v < prop.hard_min or v > prop.hard_max:
            raise ValueError(f"{v!r} is out of range (valid: {_range_text(prop)})")


def _range_text(prop) -> str:
    low = prop.hard_min if prop.hard_min > -1e30 else None
    high = prop.hard_max if prop.hard_max < 1e30 and abs(prop.hard_max) < 2**31 - 1 else None
    fmt = "{:d}" if prop.type == "INT" else "{:g}"
    low, high = (None if v is None else fmt.format(v) for v in (low, high))
    if low is not None and high is not None:
        return f"{low} to {high}"
    if low is not None:
        return f">= {low}"
    return f"<= {high}" if high is not None else "any finite number"


def check_core_settings(scene) -> None:
    """The add-on's settings as the core will see them: refused here, before anything renders,
    with the core's message (the setting, its value and its valid range)."""
    props = scene.hybridgi
    try:
        props.cache_settings(scene)
        props.raster_settings()
    except ValueError as err:  # SettingsError is a ValueError
        raise CliError(f"--set: {err}") from None


def parse_value(prop, text: str):
    length = getattr(prop, "array_length", 0)
    if length:
        parts = [p for p in re.split(r"[,\s]+", text) if p]
        if len(parts) != length:
            raise ValueError(f"expected {length} comma-separated values")
        return [_scalar(prop.type, p) for p in parts]
    if prop.type == "ENUM":
        return text
    return _scalar(prop.type, text)


def _scalar(kind: str, text: str):
    if kind == "BOOLEAN":
        if text.lower() in _TRUE:
            return True
        if text.lower() in _FALSE:
            return False
        raise ValueError(f"expected true or false, got {text!r}")
    if kind == "INT":
        return int(text)
    if kind == "FLOAT":
        return float(text)
    if kind == "STRING":
        return text
    raise ValueError(f"settings of type {kind} cannot be set from the command line")


def render_frame(bpy, scene, frame: int, files: output.FrameFiles, engine: str, addon) -> dict:
    scene.frame_set(frame)
    start = time.perf_counter()
    try:
        bpy.ops.render.render()
        failure = None
    except RuntimeError as err:  # the operator raises for reports of type ERROR (no camera, ...)
        failure = err
    seconds = time.perf_counter() - start
    # The engine's own record comes first: an exception in render() leaves the operator FINISHED.
    error = frame_error(addon) if addon is not None and engine == "HYBRIDGI" else None
    if error or failure:
        raise CliError(f"frame {frame}: {error or failure}")
    png, exr = files.paths
    save(bpy, scene, files.temp[png], files.temp[exr])
    bad = output.non_finite_channels(files.temp[exr])
    fatal = output.fatal_non_finite(bad, engine)
    if fatal:
        raise CliError(f"frame {frame}: the render has non-finite pixels in {', '.join(fatal)}; nothing was written")
    if bad:
        progress(f"warning: frame {frame}: {engine} left non-finite pixels in {', '.join(bad)}; "
                 "written as the engine made them (Combined is finite)")
    percent = scene.render.resolution_percentage / 100
    return {
        "frame": frame,
        "engine": engine,
        "seconds": round(seconds, 4),
        "width": int(scene.render.resolution_x * percent),
        "height": int(scene.render.resolution_y * percent),
        "png": str(png),
        "exr": str(exr),
        **(pipeline_stats(addon) if engine == "HYBRIDGI" else {"steps_ms": {}}),
    }


def frame_error(addon) -> str | None:
    """The HYBRIDGI engine's record of the last frame's failure (Blender swallows the exception)."""
    return importlib.import_module(f"{addon.__name__}.engine").LAST_ERROR


def pipeline_stats(addon) -> dict:
    """The pipeline's record of the last frame (module-level LAST_STATS): steps_ms ({step: ms}),
    rays, visible cells, grid, triangles. The CLI's own wall-clock seconds stay authoritative."""
    pipeline = sys.modules.get(f"{addon.__name__}.pipeline")
    stats = dict(getattr(pipeline, "LAST_STATS", None) or {})
    stats.pop("seconds", None)
    stats.pop("width", None)
    stats.pop("height", None)
    stats["steps_ms"] = {str(k): round(float(v), 3) for k, v in stats.get("steps_ms", {}).items()}
    return stats


def save(bpy, scene, png: Path, exr: Path) -> None:
    """8-bit colour-managed PNG, then every pass as 32-bit float multilayer EXR."""
    result = bpy.data.images["Render Result"]
    settings = scene.render.image_settings
    blender_compat.set_file_format(bpy, settings, "PNG")
    settings.color_mode = "RGBA"
    settings.color_depth = "8"
    result.save_render(str(png), scene=scene)
    blender_compat.set_file_format(bpy, settings, "OPEN_EXR_MULTILAYER")
    settings.color_depth = "32"
    settings.exr_codec = "ZIP"
    render = scene.render
    aspect = (render.pixel_aspect_x, render.pixel_aspect_y)
    if aspect[0] != aspect[1]:
        # Blender's multilayer EXR writer refuses non-square pixels ("Conflicting attributes found
        # for header :: ... 'pixelAspectRatio'"), for Cycles' renders too: the passes are written
        # with square pixels, the image itself is the one rendered.
        progress(f"warning: Pixel Aspect {aspect[0]:g}:{aspect[1]:g}: the EXR is written with square pixels "
                 "(Blender's multilayer EXR writer refuses other aspects)")
        render.pixel_aspect_x = render.pixel_aspect_y = 1.0
    try:
        result.save_render(str(exr), scene=scene)
    finally:
        render.pixel_aspect_x, render.pixel_aspect_y = aspect
    for path in (png, exr):
        if not path.is_file() or path.stat().st_size == 0:
            raise CliError(f"Blender did not write {path}")


def progress(message: str) -> None:
    print(f"hybridgi: {message}", file=sys.stderr, flush=True)


if __name__ == "__main__":
    console_main()
