"""Core benchmark: one cache update on the generated atrium, per step, against raw Embree; then
the final-render warm-up, retraced against the stored-hit solver.

Select = primary rays from the scene camera at a downsampled G-buffer resolution (the CPU stand-in
for the GPU G-buffer read-back) plus the visible-cell selection; then trace, shade, shadow, SH and
blend of one update, for several rays-per-cell and cache resolutions. Prints a table and, last,
one JSON line for the default settings. Timings are medians over repeats; not a test.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from blend_scenes import procedural  # noqa: E402
from hybridgi_core.settings import CacheSettings  # noqa: E402
from hybridgi_core.system import GISystem  # noqa: E402
from hybridgi_core.trace.embree import EmbreeTracer  # noqa: E402
from hybridgi_core.visible import pixels_to_points  # noqa: E402


def camera_rays(camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (h*w, 3) float32 through pixel centres, rows bottom-up."""
    m = camera.matrix()
    half_w = 0.5 * camera.sensor_width_mm / camera.lens_mm
    half_h = half_w * height / width
    x = ((np.arange(width) + 0.5) / width * 2 - 1) * half_w
    y = ((np.arange(height) + 0.5) / height * 2 - 1) * half_h
    xx, yy = np.meshgrid(x, y)
    local = np.stack([xx.ravel(), yy.ravel(), -np.ones(xx.size)], axis=1)
    d = local @ m[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return m[:3, 3].astype(np.float32), d.astype(np.float32)


def camera_gbuffer(system: GISystem, camera, width: int, height: int):
    """Primary-ray G-buffer (positions with w, normals) of the scene camera: (h, w, 4), (h, w, 3)."""
    origin, dirs = camera_rays(camera, width, height)
    hits = system.tracer.intersect(np.repeat(origin[None], dirs.shape[0], axis=0).astype(np.float32), dirs)
    ok = hits.prim >= 0
    surf = system.surfaces.surface(hits.prim[ok], hits.u[ok], hits.v[ok], dirs[ok])
    pos = np.zeros((dirs.shape[0], 4), np.float32)
    nrm = np.zeros((dirs.shape[0], 3), np.float32)
    pos[ok, :3] = surf.position
    pos[ok, 3] = 1.0
    nrm[ok] = surf.normal
    return pos.reshape(height, width, 4), nrm.reshape(height, width, 3)


def run_config(scene, camera, settings: CacheSettings, repeats: int, gbuffer_res=(160, 90)) -> dict:
    with GISystem(scene, settings) as system:
        system.warm_up(2)  # fill the cache so hits read real irradiance
        rows = []
        for r in range(repeats):
            t0 = time.perf_counter()
            pos, nrm = camera_gbuffer(system, camera, *gbuffer_res)
            t1 = time.perf_counter()
            points, normals, _ = pixels_to_points(pos, nrm)
            cells = system.visible_cells(points, normals)
            t2 = time.perf_counter()
            stats = system.update(cells, frame=r)
            rows.append(
                {
                    "gbuffer_ms": (t1 - t0) * 1e3,
                    "select_ms": (t2 - t1) * 1e3,
                    "update_ms": stats.wall_ms,
                    "rays": stats.rays,
                    "cells": stats.cells,
                    **{f"{k}_ms": v for k, v in stats.steps_ms.items()},
                }
            )
        # Raw Embree on the same ray mesh with as many threads as the update uses: the update runs
        # settings.threads workers over single-threaded tracer calls, so that is the fair ceiling.
        with EmbreeTracer(system.ray_geometry, threads=settings.threads) as raw_tracer:
            raw = max(raw_tracer.raw_throughput(200_000) for _ in range(2))
        med = {k: statistics.median(row[k] for row in rows) for k in rows[0]}
        med["rays_per_s"] = med["rays"] / (med["update_ms"] * 1e-3)
        med["raw_rays_per_s"] = raw
        med["efficiency"] = med["rays_per_s"] / raw
        med["grid"] = list(system.cache.grid.dims)
        med["triangles"] = scene.geometry.triangle_count
        return med


def warm_up_ab(scene, camera, settings: CacheSettings, updates: int = 16) -> dict:
    """Final-render warm-up of the camera's cells (surface cells plus visible ones), the
    retraced EMA warm-up against the stored-hit solver, in one process: wall seconds, probe rays,
    and the solver's steps (worker CPU ms)."""
    out = {}
    with GISystem(scene, settings) as system:
        pos, nrm = camera_gbuffer(system, camera, 160, 90)
        points, normals, _ = pixels_to_points(pos, nrm)
        cells = np.union1d(system.surface_cells(), system.visible_cells(points, normals))
        for name, run in (("retraced", system.warm_up_retraced), ("solver", system.warm_up)):
            system.cache.reset()
            t0 = time.perf_counter()
            stats = run(updates, cells)
            out[f"{name}_s"] = round(time.perf_counter() - t0, 3)
            out[f"{name}_rays"] = int(sum(st.rays for st in stats))
            steps = {}
            for st in stats:
                for k, v in st.steps_ms.items():
                    steps[k] = steps.get(k, 0.0) + v
            out[f"{name}_steps_ms"] = {k: round(v, 1) for k, v in steps.items()}
        out["cells"] = int(cells.size)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="default settings only")
    args = ap.parse_args()

    t0 = time.perf_counter()
    scene = procedural.atrium()
    camera = procedural.camera("atrium")
    print(f"atrium: {scene.geometry.triangle_count} triangles, generated in {time.perf_counter() - t0:.2f} s")
    default = CacheSettings()
    configs = (
        [(default.resolution, default.rays_per_cell)]
        if args.quick
        else list(dict.fromkeys(
            [(res, rays) for res in (32, 48) for rays in (4, 16, 64)] + [(default.resolution, default.rays_per_cell)]
        ))
    )
    header = f"{'res':>4} {'rays/cell':>9} {'cells':>6} {'rays':>8} {'select':>7} {'trace':>7} {'shade':>7} {'shadow':>7} {'sh':>6} {'blend':>6} {'update':>7} {'Mrays/s':>8} {'raw':>6} {'eff':>5}"
    print("per-step ms (trace..blend summed over worker threads; update = wall clock)")
    print(header)
    result = None
    for res, rays in configs:
        s = default.with_(resolution=res, rays_per_cell=rays)
        m = run_config(scene, camera, s, args.repeats)
        print(
            f"{res:>4} {rays:>9} {m['cells']:>6.0f} {m['rays']:>8.0f} {m['select_ms']:>7.1f} {m['trace_ms']:>7.1f} "
            f"{m['shade_ms']:>7.1f} {m['shadow_ms']:>7.1f} {m['sh_ms']:>6.1f} {m['blend_ms']:>6.1f} "
            f"{m['update_ms']:>7.1f} {m['rays_per_s'] / 1e6:>8.2f} {m['raw_rays_per_s'] / 1e6:>6.2f} {m['efficiency']:>5.2f}"
        )
        if (res, rays) == (default.resolution, default.rays_per_cell):
            result = m
    ab = warm_up_ab(scene, camera, default)
    print(
        f"final-render warm-up (16 updates, {ab['cells']} cells): retraced {ab['retraced_s']:.2f} s / "
        f"{ab['retraced_rays'] / 1e6:.2f} M rays, stored-hit solver {ab['solver_s']:.2f} s / {ab['solver_rays'] / 1e6:.2f} M rays"
    )
    print(f"solver steps (worker ms): {ab['solver_steps_ms']}")
    ms_per_100k = result["update_ms"] * 100_000 / result["rays"]
    print(f"default settings: {ms_per_100k:.1f} ms per 100k probe rays (shading and shadow rays included)")
    print(
        json.dumps(
            {
                "triangles": result["triangles"],
                "rays_per_frame": int(result["rays"]),
                "cells": int(result["cells"]),
                "update_ms": round(result["update_ms"], 2),
                "ms_per_100k_rays": round(ms_per_100k, 2),
                "rays_per_s": round(result["rays_per_s"]),
                "raw_rays_per_s": round(result["raw_rays_per_s"]),
                "efficiency": round(result["efficiency"], 3),
                "steps_ms": {
                    k: round(result[f"{k}_ms"], 2) for k in ("select", "trace", "shade", "shadow", "sh", "blend")
                },
                "warm_up": ab,
            }
        )
    )


if __name__ == "__main__":
    main()
