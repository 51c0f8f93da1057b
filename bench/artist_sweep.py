"""Render each case of `bench/artist_scenes.py` with HybridGI (default settings) and Cycles (64
spp + OIDN) through the real `hybridgi render`, one at a time under nice; print one JSON line per
case: seconds, rel L1 over Cycles' geometry pixels of Combined (C), Diffuse Direct / Indirect /
Color (DD, DI, DC) with both means, mean alpha, the background's mean, and the warnings.

    python bench/artist_sweep.py SCENES_DIR OUT_DIR [NAME ...]
"""
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from hybridgi_cli import exr  # noqa: E402

HG = Path(sys.executable).parent / "hybridgi"
CY = ("--engine", "CYCLES", "--samples", "64", "--set", "cycles.use_denoising=true")


def render(blend, prefix, *extra):
    t = time.time()
    r = subprocess.run(["nice", "-n", "10", str(HG), "render", str(blend), "--out", str(prefix), *extra],
                       capture_output=True, text=True, timeout=900)
    dt = time.time() - t
    warn = [ln for ln in r.stderr.splitlines() if "EGL" not in ln and ("warn" in ln.lower() or "error" in ln.lower() or "approx" in ln.lower())]
    if r.returncode != 0:
        return None, r.returncode, warn, dt
    info = json.loads(r.stdout.strip().splitlines()[-1])
    return exr.read_channels(info["exr"]), 0, warn, dt


def layer(ch, name, comps="RGB"):
    """A pass of the first view layer, whatever the scene calls it (morse_apartment: RenderLayer)."""
    prefix = min(key.split(".", 1)[0] for key in ch if key.endswith(f".{name}.{comps[0]}"))
    return np.stack([ch[f"{prefix}.{name}.{c}"] for c in comps], -1)


def rel(a, b):
    s = np.abs(b).sum()
    return float(np.abs(a - b).sum() / s) if s > 0 else float(np.abs(a).sum())


def main():
    scenes, out = Path(sys.argv[1]), Path(sys.argv[2])
    out.mkdir(parents=True, exist_ok=True)
    names = sys.argv[3:] or sorted(p.stem for p in scenes.glob("*.blend"))
    for n in names:
        blend = scenes / f"{n}.blend"
        hg, rc, warn, dt = render(blend, out / f"{n}_hg")
        cy, rc2, _, dt2 = render(blend, out / f"{n}_cy", *CY)
        row = {"case": n, "hg_s": round(dt, 1), "cy_s": round(dt2, 1)}
        if hg is None or cy is None:
            row.update(hg_rc=rc, cy_rc=rc2, warn=warn[-3:])
            print(json.dumps(row), flush=True)
            continue
        if layer(hg, "Combined").shape != layer(cy, "Combined").shape:
            row.update(shape=[layer(hg, "Combined").shape, layer(cy, "Combined").shape], warn=warn[-3:])
            print(json.dumps(row), flush=True)
            continue
        geo = layer(cy, "Depth", "Z")[..., 0] < 1e9
        geo_hg = layer(hg, "Depth", "Z")[..., 0] < 1e9
        row["geo_mismatch"] = round(float((geo != geo_hg).mean()), 4)
        for p, key in (("Combined", "C"), ("Diffuse Direct", "DD"), ("Diffuse Indirect", "DI"), ("Diffuse Color", "DC")):
            a, b = layer(hg, p)[geo], layer(cy, p)[geo]
            row[key] = round(rel(a, b), 3)
            row[key + "_m"] = [round(float(a.mean()), 3), round(float(b.mean()), 3)]
        ca, cb = layer(hg, "Combined", "RGBA"), layer(cy, "Combined", "RGBA")
        row["alpha"] = [round(float(ca[..., 3].mean()), 3), round(float(cb[..., 3].mean()), 3)]
        row["C_all"] = round(rel(ca[..., :3], cb[..., :3]), 3)
        if (~geo).any():
            row["bg"] = [round(float(ca[~geo][:, :3].mean()), 3), round(float(cb[~geo][:, :3].mean()), 3)]
        row["warn"] = [w[:300] for w in warn[-3:]]
        print(json.dumps(row), flush=True)


main()
