"""CPU seconds of the final render's GI work with and without per-pixel rays, per bundled scene.

    python bench/pixel_rays_cost.py [--scenes cornell,car] [--res 320x180]

Per scene (procedural snapshot, camera G-buffer traced on the CPU at the GI resolution, as
bench_core): process CPU seconds (robust to other load on the machine, unlike wall time) of the
warm-up at several (resolution, warm-up updates) and of the per-pixel gather at several ray
counts, each measured once, back to back. Pairs with the Combined errors measured through the
engine against Cycles (README / the branch report) to give error per CPU second. Not a test;
the last line is JSON.
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
from hybridgi_core import pixel_gather  # noqa: E402
from hybridgi_core.settings import CacheSettings  # noqa: E402
from hybridgi_core.system import GISystem  # noqa: E402
from hybridgi_core.visible import pixels_to_points  # noqa: E402

CACHES = ((48, 16), (48, 8), (32, 8), (24, 8))
RAYS = (16, 32)


def cpu_seconds(fn):
    t0 = time.process_time()
    fn()
    return round(time.process_time() - t0, 3)


def run_scene(name, width, height):
    scene, cam = getattr(procedural, name)(), procedural.camera(name)
    out = {"scene": name}
    for res, updates in CACHES:
        with GISystem(scene, CacheSettings(resolution=res)) as gi:
            pos, nrm = camera_gbuffer(gi, cam, width, height)
            points, normals, _ = pixels_to_points(pos, nrm)
            cells = np.union1d(gi.surface_cells(), gi.visible_cells(points, normals))
            out[f"warmup_r{res}_u{updates}_s"] = cpu_seconds(lambda: gi.warm_up(updates, cells))  # noqa: B023
            if (res, updates) == CACHES[0]:
                out["gi_pixels"] = int(points.shape[0])
                vis = gi.corner_visibility(points, normals)
                for rays in RAYS:
                    out[f"pixel_{rays}_s"] = cpu_seconds(
                        lambda: pixel_gather.trace_pixels(gi, points, normals, rays, 0, vis))  # noqa: B023
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="cornell,car")
    ap.add_argument("--res", default="320x180")
    args = ap.parse_args(argv)
    w, h = (int(v) for v in args.res.split("x"))
    rows = []
    for name in args.scenes.split(","):
        row = run_scene(name, w, h)
        print(row, file=sys.stderr, flush=True)
        rows.append(row)
    print(json.dumps(rows))


if __name__ == "__main__":
    main()
