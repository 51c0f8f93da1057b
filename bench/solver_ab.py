"""Warm-up A/B: the retraced EMA warm-up against the stored-hit solver, per bundled scene.

    python bench/solver_ab.py [--scenes cornell,atrium] [--updates 16] [--reference-batches 6]

Per scene (procedural snapshot, camera G-buffer traced on the CPU at 160x90, as bench_core):
wall seconds and probe rays of each warm-up, and the relative L1 of the gathered Diffuse
Indirect irradiance at the G-buffer points against a reference cache (the solver with many
batches and iterations, no extrapolation), so noise and missing bounces show without Cycles.
Not a test; the last line is JSON.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_core import camera_gbuffer  # noqa: E402

from blend_scenes import procedural  # noqa: E402
from hybridgi_core.settings import CacheSettings  # noqa: E402
from hybridgi_core.system import GISystem  # noqa: E402
from hybridgi_core.visible import pixels_to_points  # noqa: E402


def indirect(system, points, normals):
    return system.gather(points, normals).indirect


def rel_l1(a, b):
    return float(np.abs(a - b).sum() / max(np.abs(b).sum(), 1e-30))


def run_scene(name, updates, ref_batches, settings):
    scene = getattr(procedural, name)()
    cam = procedural.camera(name)
    out = {"scene": name}
    with GISystem(scene, settings) as gi:
        pos, nrm = camera_gbuffer(gi, cam, 160, 90)
        points, normals, _ = pixels_to_points(pos, nrm)
        cells = np.union1d(gi.surface_cells(), gi.visible_cells(points, normals))
        out["cells"] = int(cells.size)
        # reference: many batches, many plain iterations
        t0 = time.perf_counter()
        gi.solve(cells, batches=ref_batches, max_iterations=60)
        out["reference_s"] = round(time.perf_counter() - t0, 2)
        ref = indirect(gi, points, normals)

        gi.cache.reset()
        t0 = time.perf_counter()
        runs = gi.warm_up_retraced(updates, cells)
        out["retraced_s"] = round(time.perf_counter() - t0, 3)
        out["retraced_rays"] = sum(r.rays for r in runs)
        out["retraced_err"] = round(rel_l1(indirect(gi, points, normals), ref), 4)

        for batches in (1, 2, 4):
            gi.cache.reset()
            t0 = time.perf_counter()
            runs = gi.warm_up(batches * 8, cells)
            dt = time.perf_counter() - t0
            steps = {}
            for r in runs:
                for k, v in r.steps_ms.items():
                    steps[k] = steps.get(k, 0.0) + v
            out[f"solver{batches}_s"] = round(dt, 3)
            out[f"solver{batches}_rays"] = sum(r.rays for r in runs)
            out[f"solver{batches}_iters"] = sum(r.iterations for r in runs)
            out[f"solver{batches}_err"] = round(rel_l1(indirect(gi, points, normals), ref), 4)
            out[f"solver{batches}_steps_ms"] = {k: round(v) for k, v in steps.items()}
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", default="cornell,atrium,spheres,car")
    ap.add_argument("--updates", type=int, default=16)
    ap.add_argument("--reference-batches", type=int, default=6)
    args = ap.parse_args()
    results = []
    for name in args.scenes.split(","):
        r = run_scene(name, args.updates, args.reference_batches, CacheSettings())
        print(r, flush=True)
        results.append(r)
    print(json.dumps(results))


if __name__ == "__main__":
    main()
