"""The bad-input corpus (issue 13): unusual scenes, settings and output paths through the real
`hybridgi` command, each with its exact outcome.

Every case runs the command as a subprocess on a .blend file that tests/corpus_scenes.py builds in
this session, then checks, besides the case's own assertions:
- the exit status; on failure exactly one `hybridgi: error:` line holding the expected words and
  no traceback, on success none;
- stdout: one JSON line per frame written, none on failure;
- the output folder: exactly the expected files (no temporary or half-written ones).
Image cases compare with a Cycles render of the same file (32 spp, the CLI's reference settings)
within the errors stated in `similar_to_cycles`. Set HYBRIDGI_CORPUS_REPORT=FILE to append one
JSON line per case (name, outcome, seconds) for the issue's table.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from hybridgi_cli import exr

REPO = Path(__file__).resolve().parents[1]
#: HybridGI settings that keep a case to about a second on 2 cores.
FAST = ("--set", "resolution=16", "--set", "warmup_iterations=4", "--set", "rays_per_cell=32")
CYCLES_SAMPLES = "32"
TRACEBACK = "Traceback (most recent call last)"


def command() -> list[str]:
    script = Path(sys.executable).with_name("hybridgi")
    return [str(script)] if script.exists() else [sys.executable, "-m", "hybridgi_cli.main"]


def cli_env() -> dict:
    env = dict(os.environ)
    env.pop("BLENDER_USER_RESOURCES", None)  # the command makes (and removes) its own
    env.pop("HYBRIDGI_DEBUG", None)
    return env


def run_cli(*args, cwd=REPO, timeout=180) -> tuple[subprocess.CompletedProcess, float]:
    start = time.perf_counter()
    run = subprocess.run([*command(), *map(str, args)], capture_output=True, text=True, timeout=timeout,
                         env=cli_env(), cwd=cwd)
    return run, time.perf_counter() - start


# --- the session's scenes and Cycles references ------------------------------------------------


@pytest.fixture(scope="session")
def corpus(tmp_path_factory) -> Path:
    """Folder with every corpus scene as NAME.blend (built in a subprocess: its own bpy)."""
    folder = tmp_path_factory.mktemp("corpus_scenes")
    env = dict(os.environ)
    env.setdefault("BLENDER_USER_RESOURCES", str(tmp_path_factory.mktemp("corpus_blender")))
    subprocess.run([sys.executable, str(REPO / "tests" / "corpus_scenes.py"), str(folder)], check=True,
                   capture_output=True, timeout=300, env=env, cwd=REPO)
    return folder


_CYCLES: dict[str, dict] = {}


def cycles_reference(corpus: Path, name: str) -> dict[str, np.ndarray]:
    """The EXR channels of a Cycles render of corpus scene `name` (rendered once per session)."""
    if name not in _CYCLES:
        out = corpus / "cycles" / name
        run, _s = run_cli("render", corpus / f"{name}.blend", "--out", out, "--engine", "CYCLES",
                          "--samples", CYCLES_SAMPLES)
        assert run.returncode == 0, run.stderr[-2000:]
        _CYCLES[name] = exr.read_channels(f"{out}_0001.exr")
    return _CYCLES[name]


# --- image measures ------------------------------------------------------------------------------


def rgb(channels, layer: str) -> np.ndarray:
    return np.stack([channels[f"ViewLayer.{layer}.{c}"] for c in "RGB"], axis=-1)


def object_mask(channels, color, tol=0.15) -> np.ndarray:
    """Pixels whose Diffuse Color is within `tol` of `color` (an object's albedo)."""
    return np.abs(rgb(channels, "Diffuse Color") - np.asarray(color)).max(axis=-1) < tol


def iou(a: np.ndarray, b: np.ndarray) -> float:
    return float((a & b).sum() / max((a | b).sum(), 1))


def block_error(a: np.ndarray, b: np.ndarray, block: int = 4) -> float:
    """Relative L1 of block-mean images (Cycles' noise at 32 spp averages out over a block)."""
    h, w = (a.shape[0] // block) * block, (a.shape[1] // block) * block

    def blocks(x):
        return x[:h, :w].reshape(h // block, block, w // block, block, -1).mean(axis=(1, 3))

    ba, bb = blocks(a), blocks(b)
    return float(np.abs(ba - bb).sum() / max(np.abs(bb).sum(), 1e-9))


# --- cases ---------------------------------------------------------------------------------------


@dataclass
class Case:
    """One corpus entry. `args` may use {out} (the output folder) and {blend} (the scene file);
    `files`: names expected in {out} afterwards (exactly these); `check(ctx)`: further asserts."""

    name: str
    scene: str | None
    args: tuple
    rc: int = 0
    error: tuple = ()  # words the one error line must contain
    files: tuple = ()
    frames: int | None = None  # JSON lines expected (default: png files written)
    check: object = None
    prepare: object = None  # prepare(ctx) before the run (create files, first renders)
    max_seconds: float | None = None
    xfail: str | None = None
    notes: dict = field(default_factory=dict)


def _frame_files(prefix: str, frames=(1,)) -> tuple:
    return tuple(f"{prefix}_{f:04d}.{ext}" for f in frames for ext in ("png", "exr"))


BASIC = _frame_files("basic")


def _refused(name, setting_args, words, engine=()):
    return Case(name, "basic", ("--out", "{out}/basic", *engine, *setting_args), rc=1, error=words)


def _hybridgi(name, scene, check=None, extra=(), **kw):
    return Case(name, scene, ("--out", f"{{out}}/{scene}", *FAST, *extra), files=_frame_files(scene), check=check, **kw)


@dataclass
class Ctx:
    case: Case
    out: Path
    blend: Path
    corpus: Path
    run: subprocess.CompletedProcess
    seconds: float

    def channels(self, name: str | None = None, frame: int = 1):
        return exr.read_channels(self.out / f"{name or self.case.scene}_{frame:04d}.exr")

    def cycles(self, name: str | None = None):
        return cycles_reference(self.corpus, name or self.case.scene)


def similar_to_cycles(color, mask_iou=0.8, error=0.2):
    """HybridGI's image against Cycles': the object of albedo `color` covers the same pixels
    (IoU of the Diffuse Color masks >= mask_iou; edges are anti-aliased differently) and the
    Combined pass agrees within `error` relative L1 over 4x4 blocks."""

    def check(ctx: Ctx):
        mine, ref = ctx.channels(), ctx.cycles()
        combined = rgb(mine, "Combined")
        assert np.isfinite(combined).all()
        overlap = iou(object_mask(mine, color), object_mask(ref, color))
        assert overlap >= mask_iou, f"object mask IoU {overlap:.3f} < {mask_iou}"
        err = block_error(combined, rgb(ref, "Combined"))
        assert err <= error, f"Combined relative L1 {err:.3f} > {error}"
        ctx.case.notes.update(iou=round(overlap, 3), error=round(err, 3))

    return check


ORANGE, BLUE, GREY, WHITE = (0.8, 0.35, 0.1), (0.1, 0.3, 0.8), (0.8, 0.8, 0.8), (0.7, 0.7, 0.7)


def finite_image(ctx: Ctx):
    for key, values in ctx.channels().items():
        assert np.isfinite(values).all(), f"{key} has non-finite pixels"


def same_as_basic(tol=1e-3):
    """Renders like the basic scene, which it extends only by something that must not count."""

    def check(ctx: Ctx):
        finite_image(ctx)
        basic_out = ctx.out / "reference"
        run, _s = run_cli("render", ctx.corpus / "basic.blend", "--out", basic_out / "basic", *FAST)
        assert run.returncode == 0, run.stderr[-1500:]
        ref = exr.read_channels(basic_out / "basic_0001.exr")
        diff = np.abs(rgb(ctx.channels(), "Combined") - rgb(ref, "Combined")).max()
        assert diff <= tol, f"differs from the basic scene by {diff}"

    return check


def world_only(color):
    def check(ctx: Ctx):
        combined = rgb(ctx.channels(), "Combined")
        assert np.allclose(combined, color, atol=2e-3), combined.reshape(-1, 3)[:3]
        assert np.allclose(combined.mean(axis=(0, 1)), rgb(ctx.cycles(), "Combined").mean(axis=(0, 1)), atol=5e-3)

    return check


def wide_texture_halves(ctx: Ctx):
    """The left half of the plane is red, the right half green, as in Cycles."""
    mine, ref = rgb(ctx.channels(), "Diffuse Color"), rgb(ctx.cycles(), "Diffuse Color")
    w = mine.shape[1]
    for image in (mine, ref):
        left, right = image[:, 4: w // 2 - 4].mean(axis=(0, 1)), image[:, w // 2 + 4: -4].mean(axis=(0, 1))
        assert left[0] > 0.8 and left[1] < 0.1 and right[1] > 0.8 and right[0] < 0.1, (left, right)
    assert np.abs(mine.mean(axis=(0, 1)) - ref.mean(axis=(0, 1))).max() < 0.06


def tiny_image(ctx: Ctx):
    channels = ctx.channels()
    assert channels["ViewLayer.Combined.R"].shape == (3, 4)
    finite_image(ctx)


def transparent_film(ctx: Ctx):
    """Alpha as Cycles', and premultiplied colour: no world colour where alpha is 0."""
    mine, ref = ctx.channels(), ctx.cycles()
    alpha = mine["ViewLayer.Combined.A"]
    assert np.abs(alpha.mean() - ref["ViewLayer.Combined.A"].mean()) < 0.05
    assert np.abs(rgb(mine, "Combined")[alpha == 0.0]).max() == 0.0


def not_in_image(color):
    """An object hidden from the camera: its albedo appears nowhere, as in Cycles."""

    def check(ctx: Ctx):
        assert not object_mask(ctx.cycles(), color).any()
        assert not object_mask(ctx.channels(), color).any()

    return check


def previous_files_kept(ctx: Ctx):
    before = ctx.case.notes.pop("before")
    assert {p: (ctx.out / p).read_bytes() for p in before} == before


def _render_first(ctx_args):
    def prepare(ctx):
        run, _s = run_cli("render", ctx.blend, "--out", ctx.out / "basic", *FAST)
        assert run.returncode == 0, run.stderr[-1500:]
        ctx.case.notes["before"] = {p: (ctx.out / p).read_bytes() for p in BASIC}

    return prepare


def _make_file(relative):
    def prepare(ctx):
        (ctx.out / relative).write_text("not a folder")

    return prepare


def _make_dir(relative):
    def prepare(ctx):
        (ctx.out / relative).mkdir()

    return prepare


def folder_holds(sub: str, names) -> object:
    def check(ctx: Ctx):
        found = sorted(p.name for p in (ctx.out / sub).iterdir())
        assert found == sorted(names), f"{sub}/ holds {found}"

    return check


def _fast_exit(ctx: Ctx):
    # Refused before bpy is even imported.
    assert ctx.seconds < 3.0, ctx.seconds


CASES = [
    # --set values Blender would clamp silently, or that are not numbers at all: refused, by name and range.
    _refused("set_resolution_0", ("--set", "resolution=0"), ("resolution=0", "1 to 512")),
    _refused("set_rays_per_cell_negative", ("--set", "rays_per_cell=-1"), ("rays_per_cell=-1", "1 to 65536")),
    _refused("set_hysteresis_2", ("--set", "hysteresis=2"), ("hysteresis=2", "0 to 0.99")),
    _refused("set_ray_length_negative", ("--set", "ray_length=-5"), ("ray_length=-5", ">= 0")),
    _refused("set_ray_length_nan", ("--set", "ray_length=nan"), ("ray_length=nan", "not a finite number")),
    _refused("set_hysteresis_nan", ("--set", "hysteresis=NaN"), ("hysteresis=NaN", "not a finite number")),
    _refused("set_ssao_strength_inf", ("--set", "ssao_strength=inf"), ("ssao_strength=inf", "not a finite number")),
    _refused("set_ssao_radius_negative", ("--set", "ssao_radius=-1"), ("ssao_radius=-1", ">= 0")),
    _refused("set_lod_ratio_0", ("--set", "lod_ratio=0"), ("lod_ratio=0", "0.01 to 1")),
    _refused("set_downsample_0", ("--set", "downsample=0"), ("downsample=0", "1 to 16")),
    _refused("set_light_samples_0", ("--set", "light_samples=0"), ("light_samples=0", "1 to 256")),
    _refused("set_seed_negative", ("--set", "seed=-3"), ("seed=-3", ">= 0")),
    _refused("set_warmup_negative", ("--set", "warmup_iterations=-1"), ("warmup_iterations=-1", "0 to 1024")),
    _refused("set_resolution_not_a_number", ("--set", "resolution=abc"), ("resolution=abc", "invalid literal")),
    _refused("set_enum_unknown", ("--set", "sh_order=L9"), ("sh_order=L9", "L1", "L2")),
    _refused("set_bool_unknown", ("--set", "use_gi_overlay=maybe"), ("use_gi_overlay=maybe", "true or false")),
    _refused("set_unknown_setting", ("--set", "resolutionn=4"), ("resolutionn", "no writable setting")),
    _refused("set_world_color_nan", ("--set", "world.color=nan,0,0"), ("world.color", "not a finite number")),
    _refused("set_render_resolution_x_0", ("--set", "render.resolution_x=0"), ("render.resolution_x=0", "4 to")),
    _refused("set_cycles_samples_0", ("--set", "cycles.samples=0"), ("cycles.samples=0", "1 to"), ("--engine", "CYCLES")),
    # Limits: refused before the allocation, naming the limit and what to change.
    Case("cache_resolution_512_over_memory_limit", "basic", ("--out", "{out}/basic", "--set", "resolution=512"), rc=1,
         error=("cells at resolution 512", "cache memory limit of 4.0 GiB", "lower the HybridGI Resolution to"),
         max_seconds=15.0),
    # Resolution 128 on a 128x128x66 grid: its depth texture overflowed 16384 rows before.
    Case("cache_resolution_128_fits_the_gpu", "tall",
         ("--out", "{out}/tall", "--res", "32x24", "--set", "resolution=128", "--set", "warmup_iterations=1",
          "--set", "rays_per_cell=4"),
         files=_frame_files("tall"), check=lambda ctx: finite_image(ctx)),
    # Output paths.
    Case("out_cannot_be_created", "basic", ("--out", "/proc/hybridgi_corpus/x", *FAST), rc=1,
         error=("cannot create output folder /proc/hybridgi_corpus",), check=_fast_exit),
    Case("out_parent_is_a_file", "basic", ("--out", "{out}/afile/x"), rc=1,
         error=("cannot create output folder", "afile"), files=("afile",), prepare=_make_file("afile"),
         check=_fast_exit),
    Case("out_existing_folder_gets_blend_named_frames", "basic", ("--out", "{out}/frames", *FAST),
         files=("frames",), prepare=_make_dir("frames"), check=folder_holds("frames", BASIC), frames=1),
    Case("out_trailing_slash_is_a_folder", "basic", ("--out", "{out}/new/", *FAST), files=("new",), frames=1,
         check=folder_holds("new", BASIC)),
    Case("out_double_slash_is_the_blend_folder", "basic", ("--out", "//render/x", *FAST),
         files=("basic.blend", "render"), frames=1, check=folder_holds("render", _frame_files("x"))),
    Case("out_hashes_mark_the_frame_number", "basic", ("--out", "{out}/shot_##", *FAST),
         files=("shot_01.exr", "shot_01.png")),
    Case("out_frame_range", "basic", ("--out", "{out}/basic", "--frames", "1-3", *FAST), files=_frame_files("basic", (1, 2, 3))),
    Case("out_failed_render_keeps_the_previous_files", "basic", ("--out", "{out}/basic", "--set", "resolution=512"),
         rc=1, error=("cache memory limit",), files=BASIC, prepare=_render_first(()), check=previous_files_kept),
    # Command-line and scene failures.
    Case("scene_without_camera", "no_camera", ("--out", "{out}/x", *FAST), rc=1, error=("has no camera",)),
    Case("scene_file_is_corrupt", "corrupt", ("--out", "{out}/x"), rc=1, error=("cannot open",)),
    Case("scene_file_missing", None, ("--out", "{out}/x"), rc=2, error=("scene not found",)),
    Case("frames_reversed", "basic", ("--out", "{out}/x", "--frames", "3-1"), rc=2, error=("ends before it starts",)),
    Case("res_too_small", "basic", ("--out", "{out}/x", "--res", "2x2"), rc=2, error=("W, H >= 4",)),
    # Interrupts: stop within a second, exit 128 + signal, nothing written.
    Case("sigint_during_cycles", "basic", ("--out", "{out}/x", "--engine", "CYCLES", "--samples", "100000"),
         rc=130, error=("interrupted by SIGINT",), notes={"signal": signal.SIGINT}),
    Case("sigint_during_hybridgi", "basic",
         ("--out", "{out}/x", "--set", "warmup_iterations=1024", "--set", "rays_per_cell=4096"),
         rc=130, error=("interrupted by SIGINT",), notes={"signal": signal.SIGINT}),
    Case("sigterm_during_hybridgi", "basic",
         ("--out", "{out}/x", "--set", "warmup_iterations=1024", "--set", "rays_per_cell=4096"),
         rc=143, error=("interrupted by SIGTERM",), notes={"signal": signal.SIGTERM}),
    # Scenes: the image as Cycles renders it, or finite and explained.
    _hybridgi("basic_like_cycles", "basic", similar_to_cycles(ORANGE)),
    _hybridgi("sphere_100km_from_origin", "far_sphere", similar_to_cycles(BLUE)),
    _hybridgi("micrometre_cube", "micro_cube", similar_to_cycles(ORANGE)),
    _hybridgi("nan_vertices", "nan_vertices", similar_to_cycles(ORANGE)),
    _hybridgi("instances_2500", "instances", similar_to_cycles(WHITE), max_seconds=30.0),
    _hybridgi("texture_over_the_size_cap", "wide_texture", wide_texture_halves),
    _hybridgi("nan_light_emits_nothing", "nan_light", same_as_basic()),
    _hybridgi("nan_base_colour", "nan_material", finite_image),
    _hybridgi("nan_world_colour", "nan_world", finite_image),
    _hybridgi("only_zero_area_triangles", "only_degenerate", world_only((0.3, 0.4, 0.5))),
    _hybridgi("camera_only", "camera_only", world_only((0.3, 0.4, 0.5))),
    _hybridgi("resolution_percentage_10", "percent_small", tiny_image),
    # Render settings and object flags as Cycles honours them (addon/pipeline.py, sync.py).
    # The flattened cube is a 7-pixel-tall square seen edge-on: Cycles' anti-aliased rim, a fifth
    # of it, falls outside the colour mask (every pixel of Cycles' mask is inside ours).
    _hybridgi("zero_scale_object_like_cycles", "zero_scale", similar_to_cycles(ORANGE, mask_iou=0.7)),
    _hybridgi("render_border", "render_border", finite_image),
    _hybridgi("render_border_crop", "render_border_crop", finite_image),
    _hybridgi("film_transparent", "film_transparent", transparent_film),
    _hybridgi("camera_invisible_object", "camera_invisible", not_in_image(ORANGE)),
    Case("panoramic_camera_refused", "panoramic_camera", ("--out", "{out}/x", *FAST), rc=1, error=("panoramic",)),
]


def _report(case: Case, outcome: str, seconds: float) -> None:
    path = os.environ.get("HYBRIDGI_CORPUS_REPORT")
    if path:
        with open(path, "a") as f:
            f.write(json.dumps({"case": case.name, "outcome": outcome, "seconds": round(seconds, 2), **{
                k: v for k, v in case.notes.items() if k in ("iou", "error")}}) + "\n")


def _run_interrupted(args, sig, temp: Path) -> tuple[subprocess.CompletedProcess, float]:
    """Start the render, send `sig` once it renders; seconds = from the signal to the exit.
    The command's temporary folders go to `temp` (TMPDIR), which it must leave empty."""
    temp.mkdir()
    env = {**cli_env(), "TMPDIR": str(temp)}
    proc = subprocess.Popen([*command(), *map(str, args)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, cwd=REPO)
    seen = ""
    while "rendering with" not in seen:
        line = proc.stderr.readline()
        assert line, "the command ended before it rendered"
        seen += line
    time.sleep(1.0)  # well inside the frame
    start = time.perf_counter()
    proc.send_signal(sig)
    stdout, stderr = proc.communicate(timeout=30)
    seconds = time.perf_counter() - start
    assert list(temp.iterdir()) == [], "the Blender user or session folder was left behind"
    return subprocess.CompletedProcess(proc.args, proc.returncode, stdout, seen + stderr), seconds


@pytest.mark.parametrize("case", [pytest.param(c, id=c.name, marks=[pytest.mark.xfail(reason=c.xfail, strict=True)]
                                               if c.xfail else []) for c in CASES])
def test_corpus(case: Case, corpus: Path, tmp_path: Path, tmp_path_factory):
    out = tmp_path
    if case.scene == "corrupt":
        blend = out / "corrupt.blend"
        blend.write_bytes(b"BLENDER-v500" + os.urandom(2000))
        case.files = (*case.files, "corrupt.blend")
    elif case.scene is None:
        blend = out / "missing.blend"
    elif "//" in " ".join(case.args):
        blend = out / f"{case.scene}.blend"
        blend.write_bytes((corpus / f"{case.scene}.blend").read_bytes())
    else:
        blend = corpus / f"{case.scene}.blend"
    args = ["render", str(blend), *(a.format(out=out, blend=blend) for a in case.args)]
    ctx = Ctx(case, out, blend, corpus, None, 0.0)
    if case.prepare:
        case.prepare(ctx)
    start = time.perf_counter()
    outcome = "fail"
    try:
        if "signal" in case.notes:
            run, seconds = _run_interrupted(args, case.notes["signal"], tmp_path_factory.mktemp("tmpdir") / "t")
            # The render asked for runs for minutes: stopping within a few seconds is the signal
            # taken (0.1 s on a quiet host; over 1 s seen with both cores busy), not a time budget.
            assert seconds < 5.0, f"stopped {seconds:.2f} s after the signal"
        else:
            run, seconds = run_cli(*args)
        ctx.run, ctx.seconds = run, seconds
        # Usage errors (exit 2) keep argparse's form, "hybridgi render: error: ...".
        errors = [line for line in run.stderr.splitlines() if line.startswith(("hybridgi: error:", "hybridgi render: error:"))]
        assert run.returncode == case.rc, f"exit {run.returncode}, expected {case.rc}: {run.stderr[-1500:]}"
        assert TRACEBACK not in run.stderr, run.stderr[-3000:]
        if case.rc:
            assert len(errors) == 1, errors or run.stderr[-1500:]
            for word in case.error:
                assert word in errors[0], f"{word!r} not in {errors[0]!r}"
        else:
            assert errors == [], errors
        written = sorted(p.name for p in out.iterdir())
        expected = sorted(case.files)
        assert written == expected, f"files {written}, expected {expected}"
        frames = case.frames if case.frames is not None else 0 if case.rc else sum(n.endswith(".png") for n in case.files)
        lines = run.stdout.splitlines()
        assert len(lines) == frames, run.stdout
        for line in lines:
            record = json.loads(line)
            assert Path(record["png"]).is_file() and Path(record["exr"]).is_file()
        if case.max_seconds is not None:
            assert seconds <= case.max_seconds, f"{seconds:.1f} s > {case.max_seconds} s"
        if case.check:
            case.check(ctx)
        outcome = "refused" if case.rc else "ok"
    finally:
        label = outcome if not case.xfail else f"xfail ({outcome})"
        if case.rc and outcome == "refused":
            label = f"exit {case.rc}: {errors[0].split('error: ', 1)[1]}"
        _report(case, label, time.perf_counter() - start)
