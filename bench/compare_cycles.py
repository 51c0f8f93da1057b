"""HybridGI against Cycles ground truth, pass by pass, through the `hybridgi` CLI.

    python bench/compare_cycles.py [--scenes cornell,atrium] [--samples 1024] [--res WxH]
                                   [--spp-sweep 16,64,256] [--set NAME=VALUE ...] [--out out]

Per scene: a Cycles reference (--samples spp, the CLI's ground-truth settings: 32 bounces, no
clamping, no denoising or adaptive sampling; cached under OUT/cycles_ref/ by scene, resolution,
spp and frame, reused when present), a HYBRIDGI render at the same resolution, and for Diffuse
Indirect, Diffuse Direct, Ambient Occlusion and Combined (RGB) the relative L1 error over the
reference's geometry pixels, raw and after a masked box blur (noise-robust: it measures bias, not the
reference's noise), and the energy bias. Strips (HybridGI | Cycles | error heatmap) go to
OUT/compare/<scene>_<pass>.png, a markdown report to OUT/compare/report.md and stdout, and the last
stdout line is one JSON object with every number.

--spp-sweep renders Cycles at those sample counts too (cached), measures each one's Diffuse Indirect
error against the reference and its seconds, and reports the Cycles sample count and time that
reach HybridGI's Diffuse Indirect error (equal quality), and Cycles' error at HybridGI's time
(equal time). All errors are against a finite-spp reference, whose own noise (the GI_FACTS noise
floor, ~0.03 at 1024 spp) is in every number; with a sweep the report estimates it.

If HYBRIDGI cannot render (engine missing, frame failed) the report says why and still gives the
Cycles side. Renders run one at a time under `nice` (shared machines); a lock file keeps two runs
of this tool from rendering the same reference at once. Sweep renders use Cycles seed SWEEP_SEED so
their noise is independent of the reference's.

Exit status 0 when every scene has its Cycles side (a HYBRIDGI failure is reported, not fatal), 1
when a scene's reference could not be rendered.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import imagediff  # noqa: E402

from hybridgi_cli import blender_compat, exr  # noqa: E402

DEFAULT_SCENES = ("cornell", "atrium", "spheres", "car")
DEFAULT_RES = (320, 180)
#: The Cornell box is square-ish; GI_FACTS' numbers are at 320x240.
SCENE_RES = {"cornell": (320, 240)}

#: (report name, file-name slug, names the pass may carry in the EXR). The CLI writes Cycles'
#: "Ambient Occlusion"; "AO" is accepted in case an engine registers the short name.
PASSES = (
    ("Diffuse Indirect", "diffuse_indirect", ("Diffuse Indirect",)),
    ("Diffuse Direct", "diffuse_direct", ("Diffuse Direct",)),
    ("AO", "ao", ("Ambient Occlusion", "AO")),
    ("Combined", "combined", ("Combined",)),
)
HEADLINE = "Diffuse Indirect"
#: The step of the pipeline's LAST_STATS that fills the cache before the first frame.
WARMUP_STEP = "warmup"

#: Cycles seed of the sweep's renders. The reference keeps the scene's (0); with the same seed a
#: low-spp render is the first samples of the reference (Tabulated Sobol), which hides up to ~20%
#: of its error at 256 of 1024 spp and breaks reference_noise's independence assumption.
SWEEP_SEED = 1

#: Seconds to wait for another process's render of the same reference before giving up.
LOCK_WAIT_S = 3 * 3600


class RenderFailed(Exception):
    """A CLI render returned non-zero or wrote no EXR; the message is the CLI's own error line."""


# --- rendering through the CLI -----------------------------------------------------------------


def cli_command() -> list[str]:
    """The `hybridgi` console script beside this interpreter, else the module (same code)."""
    script = Path(sys.executable).parent / "hybridgi"
    return [str(script)] if script.is_file() else [sys.executable, "-m", "hybridgi_cli.main"]


def render(
    blend: Path, prefix: Path, engine: str, res, *, samples=None, frame=None, settings=(), nice=10, timeout=None
) -> dict:
    """Run one CLI render; returns its JSON record plus wall_seconds (bpy start-up included)."""
    cmd = cli_command() + [
        "render",
        str(blend),
        "--out",
        str(prefix),
        "--engine",
        engine,
        "--res",
        f"{res[0]}x{res[1]}",
    ]
    if samples:
        cmd += ["--samples", str(samples)]
    if frame is not None:
        cmd += ["--frames", str(frame)]
    for item in settings:
        cmd += ["--set", item]
    if nice > 0:
        cmd = ["nice", "-n", str(nice)] + cmd
    prefix.parent.mkdir(parents=True, exist_ok=True)
    log_path = prefix.with_name(prefix.name + ".log")
    start = time.perf_counter()
    try:
        with open(log_path, "w") as log:
            proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=log, text=True, timeout=timeout)
    except subprocess.TimeoutExpired:
        raise RenderFailed(f"{engine} render timed out after {timeout} s (log: {log_path})") from None
    wall = time.perf_counter() - start
    records = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    if proc.returncode != 0 or not records:
        raise RenderFailed(f"{engine}: {_cli_error(log_path) or f'exit status {proc.returncode}'} (log: {log_path})")
    record = records[-1]
    record["wall_seconds"] = round(wall, 3)
    return record


def _cli_error(log_path: Path) -> str | None:
    """The CLI's 'hybridgi: error: ...' line, else the last line that looks like an error."""
    lines = log_path.read_text(errors="replace").splitlines()
    for line in reversed(lines):
        if line.startswith("hybridgi: error:"):
            return line.removeprefix("hybridgi: error:").strip()
    for line in reversed(lines):
        if "Error" in line or "error" in line:
            return line.strip()
    return None


def file_digest(path: Path) -> str:
    return hashlib.sha1(path.read_bytes()).hexdigest()[:12]


def cycles_reference(
    blend: Path, cache: Path, scene: str, res, spp: int, frame, nice: int, refresh: bool, seed: int | None = None
) -> dict:
    """The cached Cycles render of (scene, res, spp, frame[, seed]), rendering it first when missing.

    Cached as PREFIX.json (the CLI's record, with wall_seconds and the .blend's digest) beside
    PREFIX_####.exr. A reference of another build of the .blend is still used, with a warning in
    the record: re-rendering minutes of Cycles for an unchanged scene rebuilt is the worse default.
    """
    name = f"{scene}_{res[0]}x{res[1]}_{spp}spp" + (f"_f{frame}" if frame is not None else "")
    name += f"_seed{seed}" if seed is not None else ""
    prefix = cache / name
    meta = prefix.with_name(name + ".json")
    digest = file_digest(blend)
    with _lock(prefix.with_name(name + ".lock")):
        record = None if refresh else _cached(meta)
        if record is None:
            progress(f"{scene}: Cycles {spp} spp at {res[0]}x{res[1]} (not cached; rendering)")
            settings = [f"seed={seed}"] if seed is not None else []
            record = render(blend, prefix, "CYCLES", res, samples=spp, frame=frame, settings=settings, nice=nice)
            record.update(samples=spp, seed=seed, blend_sha1=digest)
            meta.write_text(json.dumps(record) + "\n")
        else:
            progress(f"{scene}: Cycles {spp} spp at {res[0]}x{res[1]} cached ({record['seconds']:.1f} s)")
    record = dict(record, samples=spp, cached_as=str(meta))
    if record.get("blend_sha1") not in (None, digest):
        record["warning"] = f"rendered from another build of {blend.name}; --refresh-refs re-renders it"
    return record


def _cached(meta: Path) -> dict | None:
    if not meta.is_file():
        return None
    try:
        record = json.loads(meta.read_text().strip().splitlines()[-1])
    except (json.JSONDecodeError, IndexError):
        return None
    exr_path = Path(record.get("exr", ""))
    if not exr_path.is_absolute():
        exr_path = ROOT / exr_path
    return record if exr_path.is_file() else None


@contextlib.contextmanager
def _lock(path: Path):
    """An O_EXCL lock file holding the owner's pid; a dead owner's lock is taken over."""
    path.parent.mkdir(parents=True, exist_ok=True)
    deadline = time.monotonic() + LOCK_WAIT_S
    announced = False
    while True:
        try:
            fd = os.open(path, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            break
        except FileExistsError:
            if not _owner_alive(path):
                path.unlink(missing_ok=True)
                continue
            if time.monotonic() > deadline:
                raise RenderFailed(f"gave up waiting for {path} (another render of this reference)") from None
            if not announced:
                progress(f"waiting for another process rendering {path.stem}")
                announced = True
            time.sleep(5)
    try:
        os.write(fd, str(os.getpid()).encode())
        os.close(fd)
        yield
    finally:
        path.unlink(missing_ok=True)


def _owner_alive(path: Path) -> bool:
    try:
        pid = int(path.read_text().strip() or "0")
    except (OSError, ValueError):
        return False
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


# --- reading passes ----------------------------------------------------------------------------


def read_passes(path: str | Path) -> dict[str, np.ndarray]:
    """{pass name: (h, w, c) float32} of the first view layer in a CLI multilayer EXR."""
    grouped: dict[str, dict[str, dict[str, np.ndarray]]] = {}
    for name, plane in exr.read_channels(path).items():
        layer_pass, _dot, chan = name.rpartition(".")
        layer, _dot, pass_name = layer_pass.rpartition(".")
        grouped.setdefault(layer, {}).setdefault(pass_name, {})[chan] = plane
    if not grouped:
        raise exr.ExrError(f"{path}: no channels")
    layer = next(iter(grouped))
    out = {}
    for pass_name, chans in grouped[layer].items():
        order = [c for c in "RGBAXYZ" if c in chans] or sorted(chans)
        out[pass_name] = np.stack([chans[c] for c in order], axis=-1)
    return out


def find_pass(passes: dict[str, np.ndarray], names) -> np.ndarray | None:
    for name in names:
        if name in passes:
            return passes[name]
    return None


def geometry_mask(passes: dict[str, np.ndarray]) -> np.ndarray:
    """Pixels with geometry: the Depth pass where there is one, else Combined's alpha."""
    if "Depth" in passes:
        return imagediff.masked_geometry(passes["Depth"][..., 0], "depth")
    return imagediff.masked_geometry(passes["Combined"][..., 3], "alpha")


def rgb(img: np.ndarray) -> np.ndarray:
    return img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, axis=-1)


# --- comparison --------------------------------------------------------------------------------


def compare(test_exr, ref_exr, heat_prefix: Path | None, blur: int, vmax: float) -> dict:
    """{pass: {rel_l1, rel_l1_blur, bias}} for PASSES, over the reference's geometry pixels."""
    test, ref = read_passes(test_exr), read_passes(ref_exr)
    mask = geometry_mask(ref)
    out = {"geometry_pixels": int(mask.sum())}
    if "Depth" in test or "Combined" in test:
        test_mask = geometry_mask(test)
        if test_mask.shape == mask.shape:
            union = int((mask | test_mask).sum())
            out["mask_iou"] = round(int((mask & test_mask).sum()) / union, 4) if union else 1.0
    for name, slug, names in PASSES:
        t, r = find_pass(test, names), find_pass(ref, names)
        if t is None or r is None:
            out[name] = {"missing": "test" if t is None else "reference"}
            continue
        t, r = rgb(t), rgb(r)
        if t.shape != r.shape:
            out[name] = {"missing": f"shape {t.shape} != reference {r.shape}"}
            continue
        # One NaN would make every number NaN: measure the finite pixels and count the others, so
        # the report shows both the engine bug and how good the rest is.
        bad = mask & ~np.isfinite(t).all(axis=-1)
        m = mask & ~bad
        out[name] = {
            "rel_l1": _round(imagediff.relative_l1(t, r, m)),
            "rel_l1_blur": _round(
                imagediff.relative_l1(imagediff.box_blur(t, blur, m), imagediff.box_blur(r, blur, m), m)
            ),
            "bias": _round(imagediff.relative_bias(t, r, m)),
        }
        if bad.any():
            out[name]["nonfinite_pixels"] = int(bad.sum())
        if heat_prefix is not None:
            strip = imagediff.comparison_strip(t, r, mask, vmax=vmax)
            out[name]["strip"] = str(
                imagediff.write_png(heat_prefix.with_name(f"{heat_prefix.name}_{slug}.png"), strip)
            )
    return out


def _round(x: float, digits: int = 5) -> float | None:
    """Rounded, or None for inf/nan (which JSON cannot carry)."""
    return round(float(x), digits) if math.isfinite(x) else None


def pass_error(test_exr, ref_exr, pass_names=(HEADLINE,)) -> float:
    test, ref = read_passes(test_exr), read_passes(ref_exr)
    mask = geometry_mask(ref)
    return imagediff.relative_l1(rgb(find_pass(test, pass_names)), rgb(find_pass(ref, pass_names)), mask)


# --- the spp sweep -----------------------------------------------------------------------------


def equal_quality(sweep: list[dict], target: float, ref: dict | None = None) -> dict | None:
    """Cycles spp and seconds whose Diffuse Indirect error is `target` (see _ErrorModel)."""
    model = _ErrorModel.fit(sweep, ref)
    if model is None or not (target > 0 and math.isfinite(target)):
        return None
    n, extrapolated = model.spp_for_error(target)
    if n is None:
        return None
    return {"spp": round(n, 1), "seconds": round(model.seconds_at(n), 3), "extrapolated": extrapolated}


def equal_time(sweep: list[dict], seconds: float, ref: dict | None = None) -> dict | None:
    """Cycles' spp and Diffuse Indirect error for a render of `seconds` (see _ErrorModel)."""
    model = _ErrorModel.fit(sweep, ref)
    if model is None or not seconds > 0:
        return None
    n = model.spp_at(seconds)
    if n < 1:
        return {"spp": round(n, 2), "rel_l1": None, "extrapolated": True}
    err, extrapolated = model.error_at(n)
    return {"spp": round(n, 1), "rel_l1": round(err, 4), "extrapolated": extrapolated}


class _ErrorModel:
    """Cycles' Diffuse Indirect error and render time as functions of spp, from the sweep.

    Error: log(error) piecewise linear in log(spp) between swept counts (Monte Carlo error is a
    power law of spp); outside them, the least-squares power law through all points (flagged as
    extrapolated). Time: piecewise linear in spp through (0, 0), the sweep and the reference (time
    is close to proportional to spp), continued past the last point with the last slope.
    """

    def __init__(self, spp, err, t_spp, t_sec):
        self.log_spp, self.log_err = np.log(spp), np.log(err)
        self.slope, self.intercept = np.polyfit(self.log_spp, self.log_err, 1)
        self.t_spp, self.t_sec = t_spp, t_sec

    @classmethod
    def fit(cls, sweep: list[dict], ref: dict | None):
        pts = sorted((p["spp"], p["rel_l1"], p["seconds"]) for p in sweep if (p.get("rel_l1") or 0) > 0)
        if len(pts) < 2:
            return None
        timed = sorted({(p[0], p[2]) for p in pts} | ({(ref["samples"], ref["seconds"])} if ref else set()))
        t_spp = np.array([0.0] + [t[0] for t in timed])
        t_sec = np.maximum.accumulate(np.array([0.0] + [t[1] for t in timed]))
        model = cls(np.array([p[0] for p in pts], float), np.array([p[1] for p in pts], float), t_spp, t_sec)
        return model if model.slope < 0 else None

    def error_at(self, spp: float) -> tuple[float, bool]:
        x = math.log(max(spp, 1e-3))
        if self.log_spp[0] <= x <= self.log_spp[-1]:
            return float(math.exp(np.interp(x, self.log_spp, self.log_err))), False
        return float(math.exp(self.intercept + self.slope * x)), True

    def spp_for_error(self, err: float) -> tuple[float | None, bool]:
        y = math.log(err)
        for i in range(len(self.log_spp) - 1):
            hi, lo = self.log_err[i], self.log_err[i + 1]
            if hi >= y >= lo and hi > lo:
                t = (y - hi) / (lo - hi)
                return float(math.exp(self.log_spp[i] + t * (self.log_spp[i + 1] - self.log_spp[i]))), False
        return float(math.exp((y - self.intercept) / self.slope)), True

    def seconds_at(self, spp: float) -> float:
        if spp <= self.t_spp[-1]:
            return float(np.interp(spp, self.t_spp, self.t_sec))
        rate = (self.t_sec[-1] - self.t_sec[-2]) / (self.t_spp[-1] - self.t_spp[-2])
        return float(self.t_sec[-1] + rate * (spp - self.t_spp[-1]))

    def spp_at(self, seconds: float) -> float:
        if seconds <= self.t_sec[-1]:
            return float(np.interp(seconds, self.t_sec, self.t_spp))
        rate = (self.t_sec[-1] - self.t_sec[-2]) / (self.t_spp[-1] - self.t_spp[-2])
        return float(self.t_spp[-1] + (seconds - self.t_sec[-1]) / rate)


def reference_noise(sweep: list[dict], ref_spp: int) -> float | None:
    """The reference's own Diffuse Indirect error against the truth, from the sweep.

    Independent noise: err(n) against the reference = sigma * sqrt(1/n + 1/N), so the reference's
    share is sigma / sqrt(N); the median over sweep points tolerates one odd point.
    """
    sig = [p["rel_l1"] / math.sqrt(1 / p["spp"] + 1 / ref_spp) for p in sweep if (p.get("rel_l1") or 0) > 0]
    return round(float(np.median(sig)) / math.sqrt(ref_spp), 4) if sig else None


# --- driver ------------------------------------------------------------------------------------


def run_scene(scene: str, args) -> dict:
    blend = blender_compat.scenes_dir() / f"{scene}.blend"
    res = args.res or SCENE_RES.get(scene, DEFAULT_RES)
    result: dict = {"scene": scene, "res": list(res)}
    if not blend.is_file():
        progress(f"{scene}: {blend} missing; building it")
        subprocess.run(
            [sys.executable, str(ROOT / "blend_scenes" / "build.py"), "--only", scene, "--out", str(blend.parent)],
            cwd=ROOT, check=False,
        )
        if not blend.is_file():
            result["error"] = f"{blend} missing and could not be built"
            return result
    cache = args.out / "cycles_ref"
    compare_dir = args.out / "compare"
    try:
        ref = cycles_reference(blend, cache, scene, res, args.samples, args.frame, args.nice, args.refresh_refs)
    except RenderFailed as err:
        result["error"] = f"Cycles reference failed: {err}"
        return result
    result["reference"] = _timing(ref)

    if args.no_hybridgi:
        result["hybridgi"] = {"error": "skipped (--no-hybridgi)"}
    else:
        progress(f"{scene}: HYBRIDGI at {res[0]}x{res[1]}")
        prefix = compare_dir / "hybridgi" / f"{scene}_{res[0]}x{res[1]}"
        try:
            rec = render(
                blend,
                prefix,
                "HYBRIDGI",
                res,
                frame=args.frame,
                settings=args.settings,
                nice=args.nice,
                timeout=args.timeout,
            )
            steps = rec.get("steps_ms", {})
            result["hybridgi"] = dict(_timing(rec), steps_ms=steps)
            if WARMUP_STEP in steps:
                # The cache's warm-up is paid once per session, not per frame of an animation or
                # a viewport: the steady-state frame time is the other fair comparison.
                result["hybridgi"]["seconds_after_warmup"] = round(rec["seconds"] - steps[WARMUP_STEP] / 1000, 4)
            result["errors"] = compare(rec["exr"], ref["exr"], compare_dir / scene, args.blur, args.vmax)
        except (RenderFailed, exr.ExrError, OSError) as err:
            result["hybridgi"] = {"error": str(err)}
            progress(f"{scene}: HYBRIDGI unavailable: {err}")

    if args.spp_sweep:
        sweep = []
        for spp in args.spp_sweep:
            try:
                rec = cycles_reference(
                    blend, cache, scene, res, spp, args.frame, args.nice, args.refresh_refs, seed=SWEEP_SEED
                )
                err = pass_error(rec["exr"], ref["exr"])
                sweep.append(
                    dict(
                        _timing(rec),
                        spp=spp,
                        rel_l1=_round(err),
                        rel_l1_blur=_round(_blurred_error(rec["exr"], ref["exr"], args.blur)),
                    )
                )
            except (RenderFailed, exr.ExrError, OSError) as err:
                sweep.append({"spp": spp, "error": str(err)})
        result["sweep"] = sweep
        good = [p for p in sweep if "rel_l1" in p]
        result["reference_noise"] = reference_noise(good, args.samples)
        hgi_err = result.get("errors", {}).get(HEADLINE, {}).get("rel_l1")
        if hgi_err is not None:
            result["equal_quality"] = equal_quality(good, hgi_err, ref)
            result["equal_time"] = equal_time(good, result["hybridgi"]["seconds"], ref)
            if "seconds_after_warmup" in result["hybridgi"]:
                after = result["hybridgi"]["seconds_after_warmup"]
                result["equal_time_after_warmup"] = equal_time(good, after, ref)
    return result


def _blurred_error(test_exr, ref_exr, radius: int) -> float:
    test, ref = read_passes(test_exr), read_passes(ref_exr)
    mask = geometry_mask(ref)
    t, r = rgb(test[HEADLINE]), rgb(ref[HEADLINE])
    return imagediff.relative_l1(imagediff.box_blur(t, radius, mask), imagediff.box_blur(r, radius, mask), mask)


def _timing(record: dict) -> dict:
    keep = ("samples", "seconds", "wall_seconds", "exr", "warning")
    return {k: record[k] for k in keep if k in record}


def markdown(results: list[dict], args) -> str:
    blur = args.blur
    lines = [f"# HybridGI vs Cycles ({args.samples} spp reference)", ""]
    lines += [
        "| scene | res | Cycles s | HybridGI s | HybridGI s after warm-up | HybridGI steps (ms) |",
        "|---|---|---|---|---|---|",
    ]
    for r in results:
        ref = r.get("reference", {})
        hgi = r.get("hybridgi", {})
        steps = ", ".join(f"{k} {v:.1f}" for k, v in hgi.get("steps_ms", {}).items()) or "-"
        hgi_s = f"{hgi['seconds']:.2f}" if "seconds" in hgi else "n/a"
        ref_s = f"{ref['seconds']:.1f}" if "seconds" in ref else "n/a"
        after = f"{hgi['seconds_after_warmup']:.2f}" if "seconds_after_warmup" in hgi else "-"
        lines.append(f"| {r['scene']} | {r['res'][0]}x{r['res'][1]} | {ref_s} | {hgi_s} | {after} | {steps} |")
    lines += ["", f"Relative L1 over geometry pixels (blur = masked box blur, radius {blur}; bias = energy +/-):", ""]
    lines += ["| scene | pass | rel L1 | rel L1 blur | bias |", "|---|---|---|---|---|"]
    for r in results:
        errors = r.get("errors")
        if not errors:
            why = r.get("error") or r.get("hybridgi", {}).get("error", "no HybridGI render")
            lines.append(f"| {r['scene']} | - | n/a | n/a | {why} |")
            continue
        for name, _slug, _names in PASSES:
            e = errors.get(name, {})
            if "rel_l1" in e:
                note = f" ({e['nonfinite_pixels']} NaN/inf pixels left out)" if "nonfinite_pixels" in e else ""
                cells = f"{_fmt(e['rel_l1'])} | {_fmt(e['rel_l1_blur'])} | {_fmt(e['bias'], '+.4f')}"
                lines.append(f"| {r['scene']} | {name} | {cells}{note} |")
            else:
                lines.append(f"| {r['scene']} | {name} | n/a | n/a | missing in {e.get('missing')} |")
    swept = [r for r in results if r.get("sweep")]
    if swept:
        lines += ["", f"Cycles spp sweep: {HEADLINE} error against the reference:", ""]
        lines += ["| scene | spp | seconds | rel L1 | rel L1 blur |", "|---|---|---|---|---|"]
        for r in swept:
            for p in r["sweep"]:
                if "rel_l1" in p:
                    lines.append(
                        f"| {r['scene']} | {p['spp']} | {p['seconds']:.2f} | {_fmt(p['rel_l1'])} | {_fmt(p['rel_l1_blur'])} |"
                    )
                else:
                    lines.append(f"| {r['scene']} | {p['spp']} | n/a | n/a | {p['error']} |")
        lines.append("")
        for r in swept:
            noise = r.get("reference_noise")
            if noise is not None:
                lines.append(
                    f"- {r['scene']}: the {args.samples} spp reference's own noise is about {noise:.3f} (rel L1)."
                )
            q = r.get("equal_quality")
            hgi_err = r.get("errors", {}).get(HEADLINE, {}).get("rel_l1")
            if q:
                extra = " (extrapolated)" if q["extrapolated"] else ""
                lines.append(
                    f"- {r['scene']}: HybridGI's {HEADLINE} error {hgi_err:.4f} = Cycles at {q['spp']:.0f} spp, "
                    f"{q['seconds']:.2f} s{extra}; HybridGI took {r['hybridgi']['seconds']:.2f} s."
                )
            for key, label in (("equal_time", "time"), ("equal_time_after_warmup", "time after warm-up")):
                t = r.get(key)
                if t:
                    extra = " (extrapolated)" if t["extrapolated"] else ""
                    lines.append(
                        f"- {r['scene']}: in HybridGI's {label} Cycles reaches {t['spp']:.1f} spp, "
                        f"error {_fmt(t['rel_l1'])}{extra}."
                    )
    warnings = [
        f"- {r['scene']}: {r['reference']['warning']}" for r in results if r.get("reference", {}).get("warning")
    ]
    if warnings:
        lines += ["", *warnings]
    return "\n".join(lines) + "\n"


def _fmt(x: float | None, spec: str = ".4f") -> str:
    return "n/a" if x is None else format(x, spec)


def progress(message: str) -> None:
    print(f"compare_cycles: {message}", file=sys.stderr, flush=True)


def _resolution(text: str) -> tuple[int, int]:
    w, _x, h = text.lower().partition("x")
    try:
        return int(w), int(h)
    except ValueError:
        raise argparse.ArgumentTypeError(f"resolution must be WxH, got {text!r}") from None


def _int_list(text: str) -> list[int]:
    try:
        values = sorted({int(v) for v in text.split(",") if v.strip()})
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None
    if not values or values[0] < 1:
        raise argparse.ArgumentTypeError(f"sample counts must be positive, got {text!r}")
    return values


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", default=",".join(DEFAULT_SCENES), help="comma-separated scene names")
    parser.add_argument("--samples", type=int, default=1024, help="spp of the Cycles reference")
    parser.add_argument("--res", type=_resolution, help="WxH for every scene (default 320x180, cornell 320x240)")
    parser.add_argument("--frame", type=int, help="frame to render (default: each scene's current frame)")
    parser.add_argument("--spp-sweep", type=_int_list, metavar="N,N,...", help="Cycles sample counts to compare")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        dest="settings",
        metavar="NAME=VALUE",
        help="passed to the HYBRIDGI render (see `hybridgi render --help`)",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "out", help="root of cycles_ref/ and compare/")
    parser.add_argument("--blur", type=int, default=2, help="box-blur radius of the noise-robust error")
    parser.add_argument("--vmax", type=float, default=1.0, help="heatmap top: error / mean reference value")
    parser.add_argument("--nice", type=int, default=10, help="niceness of the render processes (0: none)")
    parser.add_argument("--timeout", type=int, default=1800, help="seconds before a HYBRIDGI render is abandoned")
    parser.add_argument("--no-hybridgi", action="store_true", help="Cycles side only")
    parser.add_argument("--refresh-refs", action="store_true", help="re-render cached Cycles references")
    args = parser.parse_args(argv)
    args.out = args.out.resolve()
    scenes = [s.strip() for s in args.scenes.split(",") if s.strip()]

    results = [run_scene(scene, args) for scene in scenes]
    report = markdown(results, args)
    compare_dir = args.out / "compare"
    compare_dir.mkdir(parents=True, exist_ok=True)
    (compare_dir / "report.md").write_text(report)
    summary = {"samples": args.samples, "blur": args.blur, "scenes": results}
    (compare_dir / "report.json").write_text(json.dumps(summary, indent=1) + "\n")
    print(report)
    print(json.dumps(summary))
    ok = all("error" not in r for r in results)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
