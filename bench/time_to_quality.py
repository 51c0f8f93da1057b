"""Time to quality: how soon HybridGI, Cycles + OpenImageDenoise and EEVEE reach an image close to
converged path tracing, on the same CPU, measured in one run (issue #10, part 1).

    python bench/time_to_quality.py [--scenes cornell,atrium,path/to/my.blend,...] [--res 640x360]
        [--quick] [--hd | --no-hd] [--ref-spp 1024] [--ref-cache DIR] [--out out/ttq] [--docs docs]
        [--repeat 3] [--no-viewport] [--no-eevee] [--references-only] [--report-only]

`make compare` runs the full benchmark and writes docs/time_to_quality.{md,png}.

Per scene (every bundled scene in blend_scenes/, then ../shared/scenes/*.blend when present, at
640x360; with --hd also the atrium at 1280x720):

- a Cycles reference: CPU, --ref-spp samples (1024; --quick 64), 32 bounces, no clamping, no
  denoising or adaptive sampling (hybridgi_core.cycles_reference). Cached under --ref-cache
  (default out/ttq_refs/, gitignored) by `quality_ladder.reference_key`: the scene's content (the
  procedural sources of a bundled scene, whose .blend bytes change with every build; the bytes of
  any other .blend, not of the files it names: a changed texture on disk keeps the key), the
  Blender version, the resolution, the samples and the settings. A later run with the same key
  renders nothing.
- peers in the same run: Cycles + OpenImageDenoise at 1, 4, 16, 64 spp (the reference's settings,
  all CPU threads, denoising on, seed 1 so their noise is independent of the reference's), and
  EEVEE at its defaults (it renders headless on llvmpipe here: its seconds are llvmpipe's, a real
  GPU's would be far lower; it has no Diffuse Indirect pass).
- HybridGI final renders along LADDER (cache resolution r, rays per cell x, warm-up updates w, pixel
  rays p per GI pixel, anti-aliasing subframes s).
- the renders each time to the target reads (`quality_ladder.crossing_rungs`) again, --repeat - 1
  more times in rounds alternating the peers; each keeps its fastest run (`retime`).
- the HybridGI viewport, driven headless with the scene camera by bench/ttq_viewport.py (see its
  docstring): the displayed image at 0.1, 0.25, 0.5, 0.75, 1, 1.5, 2, 4 s after the first draw,
  and again after a light move, in two timelines:
    * wall: the main thread redraws continuously, as Blender does while the engine tags redraws,
      so llvmpipe's raster passes take CPU from the worker (what a user of this machine sees);
    * worker: the main thread draws once (posting the view) and then sleeps; the worker's
      publications are captured at the checkpoints and drawn afterwards. A real GPU rasterizes in
      milliseconds and asynchronously, so this is the timeline a machine with a GPU would show
      (the GI itself runs on the CPU either way). The worker builds the scene before that draw,
      timed alone and counted on the clock, which starts at the draw's end; after a light move
      it starts at the edit (the worker re-lights the view it has; no draw first);
  plus the viewport's "settled" image (after a further settle), its own converged error.

Errors, against the reference over its geometry pixels (Depth pass): relative L1 of Combined and of
Diffuse Indirect (`imagediff.relative_l1`; Cycles' denoiser only denoises Combined, so the OIDN
peers' Diffuse Indirect is their noisy pass), and mean FLIP (NVIDIA's flip-evaluator, LDR) of
Combined after `quality_ladder.tone_map` with the reference's exposure.

Seconds: the CLI's render seconds (the render operator: scene sync, BVH or cache build, render,
denoise; not the process start or the .blend load), the same for every engine. HybridGI's are also
given without its GPU passes (GPU_PASS_STEPS of its per-step timings): llvmpipe rasterizes on the
same two CPU cores, a GPU does those passes in milliseconds. The CPU time its worker threads spend
beside a GPU pass (the glossy light beside the pixel rays' filter; `gpu_overlap_cpu`) is added
back whole: a GPU machine would still spend it, at worst on the critical path.

Output: OUT/results.json, OUT/time_to_quality.{md,png} (and the same in --docs), the Markdown on
stdout, and a last stdout line of JSON: per scene the target error (Cycles 16 spp + OIDN's
Combined), the seconds HybridGI (wall and without GPU passes) and Cycles + OIDN need for it
(`quality_ladder.time_to_error`, log-log along each ladder) and their ratios ("inf" with a reason
where HybridGI never gets there, null where Cycles does not). --references-only pre-renders the
references; --report-only rebuilds table, plot and JSON from OUT/results.json (a run cut short
keeps every finished scene there). Renders run one at a time; timings
on a shared machine are noisy, which is why every peer is measured in the same run.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import math
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import compare_cycles  # noqa: E402
import error_breakdown  # noqa: E402
import imagediff  # noqa: E402
import quality_ladder as ql  # noqa: E402

from hybridgi_core.cycles_reference import CYCLES_REFERENCE  # noqa: E402
from hybridgi_core.raster.frame import GPU_PASS_STEPS  # noqa: E402
from hybridgi_core.raster.thread_cpu import GPU_OVERLAP_STEP  # noqa: E402

BUNDLED = ("cornell", "atrium", "spheres", "car", "animated")
SHARED_DIR = ROOT.parent / "shared" / "scenes"
PROCEDURAL_SOURCES = (ROOT / "blend_scenes" / "procedural.py", ROOT / "blend_scenes" / "build.py")
DEFAULT_RES = (640, 360)
HD_SCENE, HD_RES = "atrium", (1280, 720)

OIDN_SPP = (1, 4, 16, 64)
QUICK_OIDN_SPP = (1, 4, 16)
TARGET_SPP = 16
OIDN_SETTINGS = ("cycles.use_denoising=true", "cycles.denoiser=OPENIMAGEDENOISE", "cycles.seed=1")

#: HybridGI's quality ladder: (name, --set values). Names from addon/properties.py.
LADDER = (
    # The two cheapest rungs keep 4 reflection rays (the default's 8 cost more there than moving up
    # the ladder: dragon r16 -0.0011 for +0.2 s). 16 pixel rays, not 8, since one sample is filtered
    # over its neighbours (`subpixel.reconstruction_taps`): Combined -0.002 to -0.005 for +0.04 to
    # +0.17 s at 640x360 (bunny_npm 0.0317 -> 0.0289, dragon 0.0665 -> 0.0617, spheres 0.0130 ->
    # 0.0102), about twice the ladder's slope from this rung to the next.
    # 24 shadow samples in penumbrae, as the next rungs (640x360, medians of three alternating runs,
    # stop 61): -gpu bunny_npm 1.41 -> 1.34 s, morse 0.95 -> 0.90, dragon_npm 1.74 -> 1.70, spheres
    # 1.21 -> 1.11; Combined bunny 0.0261 -> 0.0263, the others equal to 3 digits. (One run each
    # before: atrium 2.07 -> 1.94, Cornell 1.04 -> 1.01, car 0.84 -> 0.79, equal errors.)
    ("r16 x16 w2 p16 s1 ss24", ("resolution=16", "rays_per_cell=16", "warmup_iterations=2", "pixel_rays=16",
                                "pixel_samples=1", "reflection_rays=4", "shadow_samples=24")),
    # The next two take 24 shadow samples in penumbrae too, not the default's 48, as the r40 rung does
    # (640x360, two runs: spheres r32 0.0072 at 1.48 s against 0.0072 at 1.60 s, r24 0.0086 at
    # 1.18 s against 1.26 s; Cornell r32 0.0209 / 1.14 s against 0.0208 / 1.20 s; atrium equal).
    ("r24 x32 w4 p16 s2 ss24", ("resolution=24", "rays_per_cell=32", "warmup_iterations=4", "pixel_rays=16",
                                "pixel_samples=2", "reflection_rays=4", "shadow_samples=24")),
    ("r32 x32 w8 p32 s4 ss24", ("resolution=32", "rays_per_cell=32", "warmup_iterations=8", "pixel_rays=32",
                                "pixel_samples=4", "shadow_samples=24")),
    # The default's cache resolution and subframes over its cheapest cache rays and pixel rays,
    # since the GI pixels' rays stratify with their neighbours' (`tiled_nets`): 640x360, one run,
    # against the next rung: atrium 0.0235 at 1.94 s (0.0228 at 2.19), spheres 0.0075 at 1.60 s
    # (0.0069 at 1.70), Cornell 0.0214 at 1.44 s (0.0203 at 1.60), dragon 0.0480 at 2.54 s
    # (0.0464 at 2.80). 24 shadow samples in penumbrae, as the cheaper rungs: Combined 48 -> 24
    # atrium 0.02352 -> 0.02356, Cornell 0.02138 -> 0.02145, spheres 0.00758 -> 0.00757, car
    # 0.00318 both, morse 0.04932 -> 0.04931, bunny 0.02422 -> 0.02432, dragon 0.04951 -> 0.04977;
    # the atrium's -gpu seconds, 5 alternating runs, median 1.33 -> 1.27.
    ("r48 x16 w6 p24 s8 ss24", ("resolution=48", "rays_per_cell=16", "warmup_iterations=6", "pixel_rays=24",
                                "pixel_samples=8", "shadow_samples=24")),
    # The default's cache and subframes with the r32 rung's pixel rays and a shorter warm-up (the
    # fixed-point solve converges in it): where the cache's resolution matters more than its
    # rays (640x360, one run, against the r40 rung beside it: atrium 0.0233 at 2.24 s, r40 0.0245
    # at 2.52 s; dragon_npm 0.0465 at 2.76 s against 0.0496 at 2.83 s; spheres 0.0077 at 1.60 s
    # against 0.0071 at 1.75 s; bunny_npm 0.0252 at 2.45 s against 0.0232 at 2.33 s).
    ("r48 x32 w6 p32 s8", ("resolution=48", "rays_per_cell=32", "warmup_iterations=6", "pixel_rays=32",
                           "pixel_samples=8")),
    # The default's pixel rays and subframes over a cheaper cache and fewer shadow rays in
    # penumbrae (replaced r24 x32 w8 p48 s8, slower than r32 and barely better: Cornell 0.0210 at
    # 2.08 s; this rung 0.0205 at 1.69 s, bunny_npm 0.0254 at 2.79 s against the default's 0.0250
    # at 3.30 s).
    ("r40 x32 w8 p48 s8 ss24", ("resolution=40", "rays_per_cell=32", "warmup_iterations=8", "pixel_rays=48",
                                "pixel_samples=8", "shadow_samples=24")),
    ("r48 x64 w8 p48 s8 (default)", ()),
    # The top rungs also refine the cache: resolution 64 read the car's and the spheres' Combined
    # 0.0029 -> 0.0024 and 0.0077 -> 0.0070 at p96 (the others equal), where 48 left the spheres
    # short of Cycles + OIDN's error at any ray count.
    # (Was r64 x64 w16 p96 s16: the spheres' 0.0069 at 3.41 s; this rung 0.0071 at 2.64 s, the
    # pixel rays were what mattered, not the second batch of probe rays or 16 subframes.)
    ("r64 x32 w8 p96 s8", ("resolution=64", "rays_per_cell=32", "warmup_iterations=8", "pixel_rays=96",
                           "pixel_samples=8")),
    ("r64 x128 w24 p160 s16", ("resolution=64", "rays_per_cell=128", "warmup_iterations=24", "pixel_rays=160",
                               "pixel_samples=16")),
)
QUICK_LADDER = LADDER[:3] + tuple(r for r in LADDER if r[0].endswith("(default)"))  # the three cheapest, the default

VIEWPORT_CHECKPOINTS = (0.1, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 4.0)
TIMELINES = ("wall", "worker", "wall_light", "worker_light")


def progress(message: str) -> None:
    print(f"time_to_quality: {time.strftime('%H:%M:%S')} {message}", file=sys.stderr, flush=True)


# --- scenes and references ------------------------------------------------------------------------


class Job:
    """One scene at one resolution."""

    def __init__(self, name: str, blend: Path, res, bundled: bool):
        self.name, self.res, self.bundled = name, tuple(res), bundled
        self.label = name if self.res == DEFAULT_RES else f"{name} {res[0]}x{res[1]}"
        self.slug = f"{name}_{res[0]}x{res[1]}"
        # Rendered where it lies (renders only read it): a copy elsewhere loses the textures and
        # environment maps that a .blend names relative to itself ("//textures/wood.png"), and
        # both Cycles and HybridGI then render them missing (a copied HDRI room was lit by
        # Cycles' magenta of a missing image, its sun gone).
        self.blend = blend
        self.digest = ql.scene_digest(blend, PROCEDURAL_SOURCES) if bundled else ql.scene_digest(blend)


def scene_jobs(args) -> list[Job]:
    available = {}
    for name in BUNDLED:
        path = ROOT / "blend_scenes" / f"{name}.blend"
        if path.is_file():
            available[name] = (path, True)
        else:
            progress(f"{name}: {path} missing (run `make scenes`); skipped")
    if SHARED_DIR.is_dir():
        for path in sorted(SHARED_DIR.glob("*.blend")):
            available.setdefault(path.stem, (path, False))
    wanted = [s.strip() for s in args.scenes.split(",") if s.strip()] if args.scenes else list(available)
    jobs = []
    for name in wanted:
        if name.endswith(".blend") and Path(name).is_file():  # any scene of the user's, by its path
            available.setdefault(name, (Path(name).resolve(), False))
        if name not in available:
            progress(f"{name}: no such scene (have {', '.join(available)}); skipped")
            continue
        path, bundled = available[name]
        jobs.append(Job(path.stem if name.endswith(".blend") else name, path, args.res, bundled))
    if args.hd and HD_SCENE in available and HD_RES != tuple(args.res):
        path, bundled = available[HD_SCENE]
        jobs.append(Job(HD_SCENE, path, HD_RES, bundled))
    return jobs


def blender_version() -> str:
    return importlib.metadata.version("bpy")


def reference(job: Job, args) -> dict:
    """The cached reference of `job`, rendered first when no cache entry has its key."""
    key = ql.reference_key(job.digest, blender_version(), job.res, args.ref_spp, CYCLES_REFERENCE)
    name = f"{job.slug}_{args.ref_spp}spp_{key}"
    prefix = args.ref_cache / name
    meta = args.ref_cache / f"{name}.json"
    with compare_cycles._lock(args.ref_cache / f"{name}.lock"):
        record = _cached_reference(meta, prefix)
        if record is None:
            progress(f"{job.label}: Cycles reference {args.ref_spp} spp (key {key}, not cached: rendering)")
            record = compare_cycles.render(job.blend, prefix, "CYCLES", job.res, samples=args.ref_spp,
                                           nice=args.ref_nice, timeout=args.ref_timeout)
            record.update(samples=args.ref_spp, key=key, blender=blender_version(),
                          exr_name=Path(record["exr"]).name)
            meta.write_text(json.dumps(record) + "\n")
        else:
            progress(f"{job.label}: Cycles reference {args.ref_spp} spp cached (key {key}, {record['seconds']:.0f} s)")
    record["exr"] = str(args.ref_cache / record["exr_name"])
    return record


def _cached_reference(meta: Path, prefix: Path) -> dict | None:
    if not meta.is_file():
        return None
    try:
        record = json.loads(meta.read_text())
    except json.JSONDecodeError:
        return None
    return record if (meta.parent / record.get("exr_name", "")).is_file() else None


# --- scoring ----------------------------------------------------------------------------------------


class Reference:
    def __init__(self, exr_path):
        self.passes = compare_cycles.read_passes(exr_path)
        self.mask = compare_cycles.geometry_mask(self.passes)
        self.combined = compare_cycles.rgb(self.passes["Combined"])
        self.white = ql.exposure_white(self.combined, self.mask)
        self.combined_ldr = ql.tone_map(self.combined, self.white)


def score(ref: Reference, combined: np.ndarray, indirect: np.ndarray | None = None) -> dict:
    """{combined, diffuse_indirect, flip} of a test image against the reference."""
    import flip_evaluator  # noqa: PLC0415 (a bench extra)

    combined = compare_cycles.rgb(combined)
    finite = ref.mask & np.isfinite(combined).all(axis=-1)
    out = {"combined": _num(imagediff.relative_l1(combined, ref.combined, finite))}
    r_ind = ref.passes.get("Diffuse Indirect")
    if indirect is not None and r_ind is not None:
        ind = compare_cycles.rgb(indirect)
        ok = finite & np.isfinite(ind).all(axis=-1)
        out["diffuse_indirect"] = _num(imagediff.relative_l1(ind, compare_cycles.rgb(r_ind), ok))
    else:
        out["diffuse_indirect"] = None
    test_ldr = ql.tone_map(combined, ref.white)
    flip_map, _mean, _params = flip_evaluator.evaluate(ref.combined_ldr, test_ldr, "LDR", inputsRGB=True,
                                                       applyMagma=False)
    flip_map = np.asarray(flip_map, np.float64).reshape(ref.mask.shape)
    out["flip"] = _num(float(flip_map[ref.mask].mean()) if ref.mask.any() else float("nan"))
    if not finite.all() and (ref.mask & ~finite).any():
        out["nonfinite_pixels"] = int((ref.mask & ~finite).sum())
    return out


def score_exr(ref: Reference, exr_path) -> dict:
    passes = compare_cycles.read_passes(exr_path)
    return score(ref, passes["Combined"], passes.get("Diffuse Indirect"))


def _num(x: float, digits: int = 5):
    return round(float(x), digits) if math.isfinite(x) else None


# --- the measured renders ------------------------------------------------------------------------------


def measured_render(job: Job, args, tag: str, engine: str, samples=None, settings=(), timeout=None) -> dict:
    prefix = args.out / "renders" / job.slug / tag
    try:
        record = compare_cycles.render(job.blend, prefix, engine, job.res, samples=samples, settings=settings,
                                       nice=args.nice, timeout=timeout or args.timeout)
    except compare_cycles.RenderFailed as err:
        progress(f"{job.label}: {tag} failed: {err}")
        return {"error": str(err)}
    return record


def gpu_pass_ms(steps: dict) -> float:
    """Milliseconds of a HybridGI render a GPU would not spend: its GPU passes' (GPU_PASS_STEPS)
    less the CPU time the frame's worker threads ran beside them (GPU_OVERLAP_STEP, one core's
    milliseconds), which a GPU machine would still spend: counted as if nothing else had run then."""
    gpu = float(sum(steps.get(k, 0.0) for k in GPU_PASS_STEPS))
    return max(gpu - float(steps.get(GPU_OVERLAP_STEP, 0.0)), 0.0)


def run_peers(job: Job, args, ref: Reference) -> dict:
    out = {"cycles_oidn": [], "eevee": None, "hybridgi": []}
    for spp in args.oidn_spp:
        r = measured_render(job, args, f"cycles_oidn_{spp}spp", "CYCLES", samples=spp, settings=OIDN_SETTINGS)
        entry = {"setting": f"{spp} spp", "spp": spp, **_timing(r)}
        if "error" not in r:
            entry.update(score_exr(ref, r["exr"]))
        out["cycles_oidn"].append(entry)
        progress(f"{job.label}: Cycles {spp} spp + OIDN {_brief(entry)}")
    if args.eevee:
        r = measured_render(job, args, "eevee", "BLENDER_EEVEE", timeout=args.eevee_timeout)
        entry = {"setting": "defaults", **_timing(r)}
        if "error" not in r:
            entry.update(score_exr(ref, r["exr"]))
        out["eevee"] = entry
        progress(f"{job.label}: EEVEE {_brief(entry)}")
    for name, settings in args.ladder:
        r = measured_render(job, args, "hybridgi_" + name.split(" (")[0].replace(" ", "_"), "HYBRIDGI",
                            settings=settings)
        entry = {"setting": name, "set": list(settings), **_timing(r)}
        if "error" not in r:
            gpu_ms = gpu_pass_ms(r.get("steps_ms", {}))
            entry.update(gpu_pass_s=round(gpu_ms / 1e3, 4), seconds_minus_gpu=round(r["seconds"] - gpu_ms / 1e3, 4),
                         rays=r.get("rays"), steps_ms=r.get("steps_ms"))
            entry.update(score_exr(ref, r["exr"]))
        out["hybridgi"].append(entry)
        progress(f"{job.label}: HybridGI {name} {_brief(entry)}")
    return out


def retime(job: Job, args, peers: dict) -> None:
    """Render again, args.repeat - 1 times, the rungs each peer's time to the target reads (the
    Cycles + OIDN rungs around its crossing, HybridGI's for wall and -gpu seconds:
    `quality_ladder.crossing_rungs`), in rounds that alternate the peers, and keep each rung's
    fastest run. Why: this host's speed drifts by +-30% between runs and spikes within one
    (the same code's Cornell ratio was 0.22 / 0.27 / 0.24 in three runs); the fastest of a few
    runs is the one least disturbed, for both peers alike. Errors are the first run's: both
    renderers are seeded, so a repeat changes only the seconds."""
    oidn = [e for e in peers["cycles_oidn"] if e.get("combined") is not None]
    target = next((e["combined"] for e in oidn if e["spp"] == TARGET_SPP), None)
    if target is None or args.repeat <= 1:
        return
    for round_ in range(2, args.repeat + 1):
        hyb = [e for e in peers["hybridgi"] if e.get("combined") is not None]
        chosen = [("cycles", oidn[i]) for i in ql.crossing_rungs([(e["seconds"], e["combined"]) for e in oidn], target)]
        rungs = set(ql.crossing_rungs([(e["seconds"], e["combined"]) for e in hyb], target))
        rungs |= set(ql.crossing_rungs([(e["seconds_minus_gpu"], e["combined"]) for e in hyb], target))
        chosen += [("hybridgi", hyb[i]) for i in sorted(rungs)]
        for kind, entry in chosen:
            tag = f"retime_{kind}_{entry['setting'].split(' (')[0].replace(' ', '_')}_{round_}"
            if kind == "cycles":
                r = measured_render(job, args, tag, "CYCLES", samples=entry["spp"], settings=OIDN_SETTINGS)
            else:
                r = measured_render(job, args, tag, "HYBRIDGI", settings=entry["set"])
            _drop_files(args.out / "renders" / job.slug, tag)
            if "error" in r:
                continue
            _keep_fastest(entry, r)
            progress(f"{job.label}: re-timed {kind} {entry['setting']} ({round_}/{args.repeat}): "
                     f"{r['seconds']:.2f} s, kept {entry['seconds']:.2f} s")


def _keep_fastest(entry: dict, record: dict) -> None:
    """Fold one more run of an entry's render into it: every run's seconds listed, the fastest
    kept (wall and, for HybridGI, without the GPU passes, each its own minimum)."""
    entry.setdefault("seconds_runs", [entry["seconds"]]).append(record["seconds"])
    entry["seconds"] = min(entry["seconds"], record["seconds"])
    entry["wall_seconds"] = min(entry["wall_seconds"], record["wall_seconds"])
    if "seconds_minus_gpu" in entry:
        gpu_s = gpu_pass_ms(record.get("steps_ms", {})) / 1e3
        minus = round(record["seconds"] - gpu_s, 4)
        entry.setdefault("minus_gpu_runs", [entry["seconds_minus_gpu"]]).append(minus)
        if minus < entry["seconds_minus_gpu"]:
            entry.update(seconds_minus_gpu=minus, gpu_pass_s=round(gpu_s, 4), steps_ms=record.get("steps_ms"))


def _drop_files(folder: Path, tag: str) -> None:
    """A re-timing render's images and log: only its seconds are kept."""
    for path in folder.glob(tag + "*"):
        path.unlink(missing_ok=True)


def _timing(record: dict) -> dict:
    if "error" in record:
        return {"failed": record["error"]}
    return {"seconds": record["seconds"], "wall_seconds": record["wall_seconds"], "exr": record["exr"]}


def _brief(entry: dict) -> str:
    if "failed" in entry:
        return f"FAILED ({entry['failed'][:200]})"
    return (f"{entry['seconds']:.2f} s, Combined {_fmt(entry.get('combined'))}, "
            f"Diffuse Indirect {_fmt(entry.get('diffuse_indirect'))}, FLIP {_fmt(entry.get('flip'))}")


# --- the viewport -------------------------------------------------------------------------------------


def run_viewport(job: Job, args, ref: Reference) -> dict:
    folder = args.out / "viewport" / job.slug
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    cmd = [sys.executable, str(ROOT / "bench" / "ttq_viewport.py"), str(job.blend), "--res",
           f"{job.res[0]}x{job.res[1]}", "--out", str(folder),
           "--checkpoints", ",".join(str(c) for c in args.checkpoints)]
    if args.nice > 0:
        cmd = ["nice", "-n", str(args.nice)] + cmd
    log_path = folder / "viewport.log"
    try:
        with open(log_path, "w") as log:
            proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=log, text=True,
                                  timeout=args.timeout, env=dict(os.environ, PYTHONPATH=str(ROOT)))
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {args.timeout} s (log {log_path})"}
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = log_path.read_text(errors="replace").strip().splitlines()[-3:]
        return {"error": f"exit {proc.returncode}: {' | '.join(tail)} (log {log_path})"}
    record = json.loads(lines[-1])
    record["folder"] = str(folder)
    score_viewport(record, ref)
    return record


def score_viewport(record: dict, ref: Reference) -> None:
    """Score every shot that still names its image file (the file name is then dropped)."""
    folder = Path(record["folder"])
    for shots in record.get("timelines", {}).values():
        for shot in shots:
            if "file" in shot and (folder / shot["file"]).is_file():
                img = np.load(folder / shot.pop("file"))[::-1].astype(np.float32)  # GL rows are bottom-up
                shot.update(score(ref, img))
            if shot.get("checkpoint") is not None and not math.isfinite(shot["checkpoint"]):
                shot["checkpoint"] = None


# --- summary ---------------------------------------------------------------------------------------------


def summarize(job: Job, res: dict) -> dict:
    peers = res["peers"]
    oidn = [e for e in peers["cycles_oidn"] if e.get("combined") is not None]
    target_entry = next((e for e in oidn if e["spp"] == TARGET_SPP), None)
    if target_entry is None:
        return {"error": f"no Cycles {TARGET_SPP} spp + OIDN result: no target"}
    target = target_entry["combined"]
    hyb = [e for e in peers["hybridgi"] if e.get("combined") is not None]
    c = ql.time_to_error([(e["seconds"], e["combined"]) for e in oidn], target)
    h_wall = ql.time_to_error([(e["seconds"], e["combined"]) for e in hyb], target)
    h_gpu = ql.time_to_error([(e["seconds_minus_gpu"], e["combined"]) for e in hyb], target)
    out = {
        "target_combined": target,
        "cycles_oidn": c.as_json(),
        "hybridgi_wall": h_wall.as_json(),
        "hybridgi_minus_gpu": h_gpu.as_json(),
        "ratio_wall": _ratio(h_wall, c),
        "ratio_minus_gpu": _ratio(h_gpu, c),
    }
    vp = res.get("viewport") or {}
    if "timelines" in vp:
        out["viewport"] = {}
        for timeline in TIMELINES:
            shots = vp["timelines"].get(timeline) or []
            if not shots:
                continue
            tte = _first_shot_at(shots, target)
            out["viewport"][timeline] = tte
    elif vp.get("error"):
        out["viewport"] = {"error": vp["error"]}
    if h_wall.how == "never" and hyb:
        best = min(hyb, key=lambda e: e["combined"])
        last = sorted(hyb, key=lambda e: e["seconds"])[-2:]
        flat = abs(last[-1]["combined"] - last[0]["combined"]) / max(last[0]["combined"], 1e-9)
        out["why_never"] = (
            f"best rung '{best['setting']}': Combined {best['combined']:.4f} > target {target:.4f} "
            f"(Diffuse Indirect {_fmt(best.get('diffuse_indirect'))}); the two most expensive rungs differ by "
            f"{flat:.1%} in Combined: "
            + ("more rays and warm-up updates barely lower it" if flat < 0.05 else
               "the ladder is still falling, a richer rung would get closer")
            + " (the reference's own noise is part of every error)"
        )
        limits = _limits(best, res.get("reference", {}).get("exr"))
        if limits:
            out["best_rung_breakdown"] = limits
            out["why_never"] += (
                f"; alone in the reference's composition, Diffuse Indirect would cost Combined "
                f"{_fmt(limits['combined_if_only'].get('Diffuse Indirect'))}, Diffuse Direct "
                f"{_fmt(limits['combined_if_only'].get('Diffuse Direct'))}, Diffuse Color "
                f"{_fmt(limits['combined_if_only'].get('Diffuse Color'))}; "
                f"{limits['edge_error_share']:.0%} of the error sits on edge pixels")
    return out


def _limits(entry: dict, ref_exr) -> dict | None:
    """bench/error_breakdown.py's split of one render's Combined error (by pass, edges vs not)."""
    if not ref_exr or not entry.get("exr") or not Path(entry["exr"]).is_file():
        return None
    try:
        b = error_breakdown.breakdown(entry["exr"], ref_exr)
    except (KeyError, ValueError, OSError) as err:  # a pass missing from either file
        progress(f"error breakdown of {entry['exr']} failed: {err}")
        return None
    return {"combined_if_only": b["combined_if_only"], "edge_error_share": b["edge_error_share"],
            "combined_without_edges": b["combined_without_edges"]}


def _first_shot_at(shots, target) -> dict:
    """Seconds after the first draw of the first displayed image at or below target (the shots are
    discrete checkpoints: this is an upper bound to the checkpoint spacing)."""
    for s in shots:
        if s.get("combined") is not None and s["combined"] <= target:
            return {"seconds": s["t"], "how": "at checkpoint"}
    best = min((s["combined"] for s in shots if s.get("combined") is not None), default=None)
    return {"seconds": None, "how": "never",
            "reason": f"best displayed error {_fmt(best)} > target {target:.4f} within {shots[-1]['t']:.2f} s"}


def _ratio(test: ql.TimeToError, peer: ql.TimeToError):
    r = ql.speed_ratio(test, peer)
    if r is None:
        return {"value": None, "reason": f"Cycles + OIDN never reaches the target ({peer.reason})"}
    if math.isinf(r):
        return {"value": "inf", "reason": test.reason}
    return {"value": round(r, 4), **({"bound": "at_most"} if test.how == "at_most" else {})}


# --- report -------------------------------------------------------------------------------------------------


def _fmt(x, spec=".4f") -> str:
    if x is None:
        return "n/a"
    if isinstance(x, str):
        return x
    return format(x, spec) if math.isfinite(x) else "inf"


def _fmt_tte(t: dict) -> str:
    if t is None:
        return "n/a"
    if t.get("seconds") is None:
        return "never"
    return ("<= " if t.get("how") == "at_most" else "") + f"{t['seconds']:.2f}"


def markdown(results: list[dict], args) -> str:
    mode = "quick (development)" if args.quick else "full"
    lines = [
        f"# Time to quality ({mode} run, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())})",
        "",
        f"Cycles reference: {args.ref_spp} spp, CPU, 32 bounces, no clamping, no denoising. Errors over "
        "the reference's geometry pixels. Target: the Combined relative L1 of Cycles 16 spp + OIDN in the "
        "same run. Seconds: render operator (sync + build + render), one render at a time on a shared "
        f"2-core machine without a GPU (Mesa llvmpipe); the rungs each time to the target reads: the fastest of "
        f"{args.repeat} runs, in rounds alternating the peers (`runs` lists them); `-gpu`: minus HybridGI's GPU passes "
        f"({', '.join(GPU_PASS_STEPS)}). Ratio = HybridGI seconds / Cycles + OIDN seconds to the "
        "target (issue #10's goal: <= 0.25 on the `-gpu` seconds). Viewport: first checkpoint "
        f"({', '.join(str(c) for c in args.checkpoints)} s after the first draw) whose displayed image is "
        "within the target; `worker` = GPU-free timeline, `wall` = with llvmpipe's draws (see "
        "bench/ttq_viewport.py).",
        "",
        "| scene | target | Cycles+OIDN s | HybridGI s | HybridGI -gpu s | ratio | ratio -gpu | HybridGI best Combined (s) "
        "| viewport wall / worker s | after light move wall / worker s | viewport settled |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        s = r.get("summary") or {}
        if "target_combined" not in s:
            lines.append(f"| {r['label']} | {s.get('error') or r.get('error', 'n/a')} | | | | | | | | | |")
            continue
        vp = s.get("viewport") or {}

        def v(name, vp=vp):
            return _fmt_tte(vp.get(name)) if name in vp else "n/a"

        hyb = [e for e in r["peers"]["hybridgi"] if e.get("combined") is not None]
        best = min(hyb, key=lambda e: e["combined"]) if hyb else None
        best_cell = f"{best['combined']:.4f} ({best['seconds']:.1f})" if best else "n/a"
        settled = (((r.get("viewport") or {}).get("timelines") or {}).get("settled") or [{}])[0]
        lines.append(
            f"| {r['label']} | {s['target_combined']:.4f} | {_fmt_tte(s['cycles_oidn'])} | "
            f"{_fmt_tte(s['hybridgi_wall'])} | {_fmt_tte(s['hybridgi_minus_gpu'])} | "
            f"{_fmt(s['ratio_wall']['value'], '.2f')} | {_fmt(s['ratio_minus_gpu']['value'], '.2f')} | {best_cell} | "
            f"{v('wall')} / {v('worker')} | {v('wall_light')} / {v('worker_light')} | {_fmt(settled.get('combined'))} |"
        )
    lines += ["", "## Every render", "",
              "| scene | renderer | setting | s | -gpu s | Combined | Diffuse Indirect | FLIP | runs (s) |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        if "peers" not in r:
            continue
        p = r["peers"]
        rows = [("Cycles+OIDN", e) for e in p["cycles_oidn"]]
        if p.get("eevee"):
            rows.append(("EEVEE", p["eevee"]))
        rows += [("HybridGI", e) for e in p["hybridgi"]]
        for who, e in rows:
            if "failed" in e:
                lines.append(f"| {r['label']} | {who} | {e['setting']} | failed: {e['failed'][:120]} | | | | | |")
                continue
            lines.append(
                f"| {r['label']} | {who} | {e['setting']} | {e['seconds']:.2f} | "
                f"{_fmt(e.get('seconds_minus_gpu'), '.2f')} | {_fmt(e.get('combined'))} | "
                f"{_fmt(e.get('diffuse_indirect'))} | {_fmt(e.get('flip'))} | "
                f"{' / '.join(f'{x:.2f}' for x in e.get('seconds_runs', ()))} |"
            )
        vp = r.get("viewport") or {}
        for timeline in TIMELINES:
            shots = (vp.get("timelines") or {}).get(timeline) or []
            if shots:
                cells = ", ".join(f"{s['t']:.2f} s: {_fmt(s.get('combined'), '.3f')}" for s in shots)
                lines.append(f"| {r['label']} | HybridGI viewport | {timeline} | {cells} | | | | | |")
        settled = ((vp.get("timelines") or {}).get("settled") or [{}])[0]
        if settled.get("combined") is not None:
            lines.append(f"| {r['label']} | HybridGI viewport | settled (after light move) | {settled['t']:.1f} | | "
                         f"{_fmt(settled['combined'])} | n/a | {_fmt(settled.get('flip'))} | |")
        if vp.get("error"):
            lines.append(f"| {r['label']} | HybridGI viewport | | failed: {vp['error'][:160]} | | | | | |")
        if vp.get("notes"):
            lines.append(f"| {r['label']} | HybridGI viewport | notes | {'; '.join(vp['notes'])} | | | | | |")
    notes = [f"- {r['label']}: {r['summary']['why_never']}" for r in results if (r.get("summary") or {}).get("why_never")]
    if notes:
        lines += ["", "Where HybridGI never reaches the target:", "", *notes]
    return "\n".join(lines) + "\n"


def plot(results: list[dict], path: Path) -> Path | None:
    try:
        import matplotlib  # noqa: PLC0415

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt  # noqa: PLC0415
    except ImportError:
        progress("matplotlib missing (pip install -e '.[bench]'): no plot")
        return None
    done = [r for r in results if "peers" in r]
    if not done:
        return None
    cols = min(3, len(done))
    rows = math.ceil(len(done) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.0 * rows), squeeze=False)
    for ax, r in zip(axes.ravel(), done, strict=False):
        p = r["peers"]

        def curve(entries, key="seconds", ax=ax, **kw):
            pts = sorted((e[key], e["combined"]) for e in entries
                         if e.get("combined") and e.get(key) and e[key] > 0)
            if pts:
                ax.plot([t for t, _ in pts], [e for _, e in pts], **kw)

        curve(p["cycles_oidn"], marker="o", color="tab:blue", label="Cycles + OIDN (1-64 spp)")
        curve(p["hybridgi"], marker="s", color="tab:red", label="HybridGI final (wall)")
        curve(p["hybridgi"], key="seconds_minus_gpu", marker="s", ls="--", color="tab:red", mfc="none",
              label="HybridGI final (- GPU passes)")
        if p.get("eevee") and p["eevee"].get("combined"):
            ax.plot([p["eevee"]["seconds"]], [p["eevee"]["combined"]], marker="x", ms=9, ls="none",
                    color="tab:green", label="EEVEE (llvmpipe)")
        styles = {"wall": ("tab:purple", "-"), "worker": ("tab:orange", "-"),
                  "wall_light": ("tab:purple", ":"), "worker_light": ("tab:orange", ":")}
        for timeline, (color, ls) in styles.items():
            shots = ((r.get("viewport") or {}).get("timelines") or {}).get(timeline) or []
            pts = [(s["t"], s["combined"]) for s in shots if s.get("combined") and s["t"] > 0]
            if pts:
                ax.plot(*zip(*pts, strict=True), color=color, ls=ls, marker=".",
                        label=f"viewport {timeline.replace('_light', ' after light move')}")
        s = r.get("summary") or {}
        if s.get("target_combined"):
            ax.axhline(s["target_combined"], color="grey", lw=0.8, ls="--", label="target: Cycles 16 spp + OIDN")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(r["label"])
        ax.set_xlabel("seconds")
        ax.set_ylabel("Combined relative L1")
        ax.grid(True, which="both", alpha=0.3)
    for ax in axes.ravel()[len(done):]:
        ax.axis("off")
    handles, labels = axes.ravel()[0].get_legend_handles_labels()
    fig.tight_layout()
    # Below the panels; bbox_inches="tight" grows the picture to hold it.
    fig.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, 0.0), ncol=min(4, 2 * cols),
               fontsize=8, frameon=False)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=90, bbox_inches="tight")
    plt.close(fig)
    return path


def final_json(results: list[dict], args) -> dict:
    return {
        "mode": "quick" if args.quick else "full",
        "reference_spp": args.ref_spp,
        "blender": blender_version(),
        "target": f"Combined relative L1 of Cycles {TARGET_SPP} spp + OIDN",
        "scenes": {r["label"]: r.get("summary") or {"error": r.get("error")} for r in results},
    }


def write_outputs(results: list[dict], args) -> str:
    report = markdown(results, args)
    folders = [args.out] + ([args.docs] if args.docs else [])
    for folder in folders:
        folder.mkdir(parents=True, exist_ok=True)
        (folder / "time_to_quality.md").write_text(report)
        plot(results, folder / "time_to_quality.png")
    (args.out / "results.json").write_text(json.dumps({"args": _args_json(args), "results": results}, indent=1) + "\n")
    return report


def _args_json(args) -> dict:
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()}


# --- main -------------------------------------------------------------------------------------------------


def _resolution(text: str):
    w, _x, h = text.lower().partition("x")
    return int(w), int(h)


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", help="comma-separated names or .blend paths (default: every bundled and shared "
                        "scene)")
    parser.add_argument("--res", type=_resolution, default=DEFAULT_RES, help="WxH (default 640x360)")
    parser.add_argument("--hd", action=argparse.BooleanOptionalAction, default=None,
                        help=f"also {HD_SCENE} at {HD_RES[0]}x{HD_RES[1]} (default: on, off with --quick or --scenes)")
    parser.add_argument("--quick", action="store_true",
                        help="development run: 64-spp references, OIDN at 1/4/16 spp, a 4-rung ladder, no EEVEE")
    parser.add_argument("--ref-spp", type=int, help="reference samples (default 1024, --quick 64)")
    parser.add_argument("--ref-cache", type=Path, default=Path(os.environ.get("HYBRIDGI_REF_CACHE", ROOT / "out" / "ttq_refs")))
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "ttq")
    parser.add_argument("--docs", type=Path, help="also write time_to_quality.{md,png} here (make compare: docs)")
    parser.add_argument("--no-viewport", dest="viewport", action="store_false")
    parser.add_argument("--eevee", action=argparse.BooleanOptionalAction, default=None, help="default: on unless --quick")
    parser.add_argument("--references-only", action="store_true", help="render missing references, measure nothing")
    parser.add_argument("--report-only", action="store_true",
                        help="render nothing: summarize OUT/results.json again (table, plot, JSON)")
    parser.add_argument("--nice", type=int, default=0, help="niceness of the measured renders")
    parser.add_argument("--ref-nice", type=int, default=0, help="niceness of reference renders")
    parser.add_argument("--repeat", type=int, default=None,
                        help="runs of the renders each peer's time to the target reads; the fastest is kept "
                        "(default 3, --quick 1)")
    parser.add_argument("--timeout", type=int, default=1200, help="seconds per measured render")
    parser.add_argument("--eevee-timeout", type=int, default=900)
    parser.add_argument("--ref-timeout", type=int, default=4 * 3600)
    args = parser.parse_args(argv)
    args.ref_spp = args.ref_spp or (64 if args.quick else 1024)
    args.hd = (not args.quick and not args.scenes) if args.hd is None else args.hd
    args.eevee = (not args.quick) if args.eevee is None else args.eevee
    args.oidn_spp = QUICK_OIDN_SPP if args.quick else OIDN_SPP
    args.ladder = QUICK_LADDER if args.quick else LADDER
    if args.repeat is None:
        args.repeat = 1 if args.quick else 3
    if args.repeat < 1:
        raise SystemExit("--repeat must be at least 1")
    args.checkpoints = VIEWPORT_CHECKPOINTS
    args.out = args.out.resolve()
    args.ref_cache = args.ref_cache.resolve()
    args.ref_cache.mkdir(parents=True, exist_ok=True)
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.report_only:
        results = json.loads((args.out / "results.json").read_text())["results"]
        for entry in results:
            if "peers" in entry:
                vp = entry.get("viewport") or {}
                if "timelines" in vp:
                    vp.setdefault("folder", str(args.out / "viewport" / f"{entry['scene']}_{entry['res'][0]}x{entry['res'][1]}"))
                    score_viewport(vp, Reference(entry["reference"]["exr"]))
                entry["summary"] = summarize(None, entry)
        report = write_outputs(results, args)
        print(report)
        print(json.dumps(final_json(results, args)))
        return 0
    jobs = scene_jobs(args)
    if args.references_only:
        for job in jobs:
            try:
                reference(job, args)
            except compare_cycles.RenderFailed as err:
                progress(f"{job.label}: reference failed: {err}")
        return 0
    results = []
    for job in jobs:
        entry = {"label": job.label, "scene": job.name, "res": list(job.res), "blend": str(job.blend)}
        results.append(entry)
        try:
            ref_record = reference(job, args)
        except compare_cycles.RenderFailed as err:
            entry["error"] = f"reference failed: {err}"
            progress(f"{job.label}: {entry['error']}")
            write_outputs(results, args)
            continue
        entry["reference"] = {k: ref_record.get(k) for k in ("seconds", "samples", "key", "blender", "exr")}
        ref = Reference(ref_record["exr"])
        entry["peers"] = run_peers(job, args, ref)
        retime(job, args, entry["peers"])
        if args.viewport:
            progress(f"{job.label}: viewport timelines")
            entry["viewport"] = run_viewport(job, args, ref)
            if entry["viewport"].get("error"):
                progress(f"{job.label}: viewport failed: {entry['viewport']['error']}")
        write_outputs(results, args)  # the measurements are kept even if summarizing fails
        entry["summary"] = summarize(job, entry)
        progress(f"{job.label}: {json.dumps(entry['summary'])}")
        write_outputs(results, args)
    report = write_outputs(results, args)
    print(report)
    print(json.dumps(final_json(results, args)))
    return 0 if all("error" not in r for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
