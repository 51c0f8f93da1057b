"""Viewport benchmark: the HYBRIDGI engine's view_update / view_draw on a bundled scene (atrium by
default), driven like Blender drives a 3D View but headless (fake engine and region, offscreen).

1. Navigation, one redraw per frame. Per redraw of the main thread:
   - cpu: wall time of view_draw minus the steps that submit GPU passes or wait for them
     (`viewport.GPU_STEPS`): sync, uploads, bookkeeping, Python overhead;
   - readback: the G-buffer read-back (a GPU sync), counted separately;
   - thread: CPU time of the main thread over the draw (`time.thread_time`; on llvmpipe this
     includes vertex processing, which runs on the calling thread).
2. GI updates per second with every visible cell to refresh (after a light edit): camera still,
   then the navigation of 1 replayed to the worker at 30 frames per second while the main thread
   idles (a real GPU rasterizes asynchronously; here llvmpipe would take both cores), with the lag
   between a frame and the publication of its direct light.
3. A 5k-triangle object moved every frame, camera still: main-thread cost per frame (view_update
   of the transform edit + the G-buffer's position upload + anything else) over a navigation redraw.

    .venv/bin/python bench/bench_viewport.py [--scene atrium] [--res 640x360] [--frames 60]

Ends with one JSON line. Targets (not asserted): cpu <= 5 ms per redraw, >= 30 GI updates/s,
moving object <= 3 ms per frame. Medians; a shared 2-core llvmpipe machine is noisy.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="hybridgi_bench_"))
sys.path.insert(0, str(REPO))

import bpy  # noqa: E402
import gpu  # noqa: E402
import numpy as np  # noqa: E402
from mathutils import Matrix  # noqa: E402

from hybridgi_cli import blender_compat, dev_install  # noqa: E402


class FakeEngine:
    """What view_update / view_draw use of a RenderEngine."""

    def __init__(self):
        self.viewport = None

    def tag_redraw(self):
        pass

    def get_preview_pixel_size(self, scene):
        return 1

    def bind_display_space_shader(self, scene):
        pass

    def unbind_display_space_shader(self):
        pass

    def update_stats(self, stats, info):
        pass


def scene_file(name: str) -> Path:
    path = blender_compat.scenes_dir() / f"{name}.blend"
    if path.exists():
        return path
    out = Path(tempfile.mkdtemp(prefix="hybridgi_scenes_"))
    subprocess.run([sys.executable, str(REPO / "blend_scenes" / "build.py"), "--only", name, "--out", str(out)],
                   check=True, capture_output=True)
    return out / f"{name}.blend"


def gpu_context():
    """Blender creates its GPU context in background mode on a render: a tiny Workbench one."""
    scene = bpy.context.scene
    engine, res = scene.render.engine, (scene.render.resolution_x, scene.render.resolution_y)
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = scene.render.resolution_y = 8
    bpy.ops.render.render()
    scene.render.engine = engine
    scene.render.resolution_x, scene.render.resolution_y = res


def sphere(name: str, triangles: int, radius: float, location):
    """A UV sphere of about `triangles` triangles (quads count as two), linked to the scene."""
    rings = int(math.sqrt(triangles / 4))
    segments = max(3, triangles // (2 * rings))
    verts = [(0.0, 0.0, radius)]
    for i in range(1, rings):
        t = math.pi * i / rings
        for j in range(segments):
            p = 2 * math.pi * j / segments
            verts.append((radius * math.sin(t) * math.cos(p), radius * math.sin(t) * math.sin(p), radius * math.cos(t)))
    verts.append((0.0, 0.0, -radius))
    faces = [(0, 1 + (j + 1) % segments, 1 + j) for j in range(segments)]
    for i in range(rings - 2):
        a, b = 1 + i * segments, 1 + (i + 1) * segments
        faces += [(a + j, a + (j + 1) % segments, b + (j + 1) % segments, b + j) for j in range(segments)]
    last, base = len(verts) - 1, 1 + (rings - 2) * segments
    faces += [(last, base + j, base + (j + 1) % segments) for j in range(segments)]
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    obj.location = location
    bpy.context.scene.collection.objects.link(obj)
    mesh.calc_loop_triangles()
    return obj, len(mesh.loop_triangles)


def replay(worker, requests, hz: float):
    """Post `requests` at `hz`; returns (GI updates per second, lags in ms from posting a view to
    the publication of its light for the views lit within one frame, rays per second samples,
    median worker step times)."""
    lags, rays, steps = [], [], []
    u0, t0 = worker.latest().stats.updates, time.perf_counter()
    requests = requests * max(1, int(math.ceil(2.0 * hz / max(len(requests), 1))))  # at least 2 s
    for i, request in enumerate(requests):
        posted = time.perf_counter()
        worker.post_view(request)
        if worker.wait(lambda p, key=request.key: p.view is not None and p.view.key == key, 1.0 / hz):
            lags.append((time.perf_counter() - posted) * 1e3)
        rays.append(worker.latest().stats.rays_per_s)
        steps.append(dict(worker.latest().stats.steps_ms))
        delay = t0 + (i + 1) / hz - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
    rate = (worker.latest().stats.updates - u0) / (time.perf_counter() - t0)
    step_ms = {k: round(median([s.get(k, 0.0) for s in steps]), 1) for k in steps[-1]}
    return rate, lags, rays, step_ms


def median(values):
    return statistics.median(values) if values else float("nan")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="atrium")
    parser.add_argument("--res", default="640x360")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--converge-timeout", type=float, default=120.0)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.res.lower().split("x"))

    bpy.ops.wm.open_mainfile(filepath=str(scene_file(args.scene)))
    package = dev_install.enable()
    viewport = importlib.import_module(f"{package.__name__}.viewport")
    gpu_context()
    scene = bpy.context.scene
    scene.render.engine = "HYBRIDGI"

    depsgraph = bpy.context.evaluated_depsgraph_get()
    cam = scene.camera.evaluated_get(depsgraph)
    region_data = SimpleNamespace(view_matrix=cam.matrix_world.normalized().inverted(),
                                  window_matrix=cam.calc_matrix_camera(depsgraph, x=width, y=height),
                                  is_perspective=True, view_perspective="PERSP")
    context = SimpleNamespace(region=SimpleNamespace(width=width, height=height), region_data=region_data,
                              scene=scene, evaluated_depsgraph_get=bpy.context.evaluated_depsgraph_get)
    engine = FakeEngine()
    offscreen = gpu.types.GPUOffScreen(width, height, format="RGBA16F")

    def draw():
        with offscreen.bind():
            t0, c0 = time.perf_counter(), time.thread_time()
            viewport.view_draw(engine, context, bpy.context.evaluated_depsgraph_get())
            wall, thread = (time.perf_counter() - t0) * 1e3, (time.thread_time() - c0) * 1e3
        stats = engine.viewport.last_stats
        return SimpleNamespace(wall=wall, thread=thread, cpu=stats.cpu_ms, gpu=stats.gpu_ms,
                               readback=stats.steps_ms.get("readback", 0.0), steps=dict(stats.steps_ms))

    # Start and converge the first view.
    t0 = time.perf_counter()
    viewport.view_update(engine, context, depsgraph)
    draw()
    session = engine.viewport
    published = session.worker.latest()
    converged = session.worker.wait(lambda p: p.stats.converged >= 0.99, args.converge_timeout)
    converge_s = time.perf_counter() - t0
    published = session.worker.latest()
    print(f"{args.scene}: {width}x{height}, {published.stats.visible_cells} visible cells, view converged "
          f"{'in' if converged else 'NOT within'} {converge_s:.1f} s ({published.stats.updates} updates)")
    session.worker.wait_idle(args.converge_timeout)
    draw()

    # Navigate: orbit around the view's target, one redraw per frame. The view requests posted are
    # kept for the replay below.
    requests = []
    post_view = session.worker.post_view

    def recording_post(request):
        requests.append(request)
        post_view(request)

    session.worker.post_view = recording_post
    frames = []
    updates0, t_nav = session.worker.latest().stats.updates, time.perf_counter()
    rays = []
    for i in range(args.frames):
        region_data.view_matrix = Matrix.Rotation(0.004 * math.sin(i / 9), 4, "Y") @ \
            Matrix.Translation((0.02, 0.0, 0.0)) @ region_data.view_matrix
        frames.append(draw())
        rays.append(session.worker.latest().stats.rays_per_s)
    nav_s = time.perf_counter() - t_nav
    updates_nav = session.worker.latest().stats.updates - updates0
    skip = min(3, len(frames) - 1)  # the first frames compile shader variants
    f = frames[skip:]
    print(f"navigation, {len(f)} redraws: cpu {median([x.cpu for x in f]):.2f} ms, readback "
          f"{median([x.readback for x in f]):.2f} ms, gpu passes {median([x.gpu for x in f]):.1f} ms, "
          f"wall {median([x.wall for x in f]):.1f} ms, main-thread CPU time {median([x.thread for x in f]):.1f} ms")
    steps = {k: round(median([x.steps.get(k, 0.0) for x in f]), 3) for k in f[-1].steps}
    print("  median per step (ms):", steps)
    print(f"  worker meanwhile: {updates_nav / nav_s:.1f} GI updates/s, {median(rays) / 1e6:.2f} Mrays/s "
          f"(few cells need work in a converged cache; llvmpipe's rasterization takes the same two cores)")
    session.worker.post_view = post_view
    session.worker.wait_idle(args.converge_timeout)

    # GI updates per second with every cell to refresh (a light edit), first with the camera still,
    # then with the navigation above replayed to the worker at 30 frames per second while the main
    # thread idles, as with a GPU that rasterizes asynchronously (here llvmpipe would take the cores).
    handler = lambda scn, dg: viewport.view_update(engine, context, dg)  # noqa: E731
    bpy.app.handlers.depsgraph_update_post.append(handler)
    light = next(o for o in bpy.data.objects if o.type == "LIGHT")
    light.data.energy *= 1.01
    bpy.context.view_layer.update()
    u0, t1 = session.worker.latest().stats.updates, time.perf_counter()
    # Solver steps (a re-shaded batch, an iteration): a relight may finish in fewer than 30.
    gen = session.last_edit_gen
    session.worker.wait(lambda p: p.stats.updates >= u0 + 30 or (p.stats.idle and p.stats.scene_gen >= gen), 60.0)
    still_rate = (session.worker.latest().stats.updates - u0) / (time.perf_counter() - t1)
    still_rays = session.worker.latest().stats.rays_per_s
    print(f"light edit, camera still: {still_rate:.1f} GI updates/s, {still_rays / 1e6:.2f} Mrays/s")
    session.worker.wait_idle(args.converge_timeout)
    light.data.energy /= 1.01
    bpy.context.view_layer.update()
    replay_rate, lags, replay_rays, worker_steps = replay(session.worker, requests, hz=30.0)
    view_ms = worker_steps.get("visible", 0.0) + worker_steps.get("direct", 0.0)
    print(f"light edit, navigation replayed at 30 Hz: {replay_rate:.1f} GI updates/s, "
          f"{median(replay_rays) / 1e6:.2f} Mrays/s; lighting a new view takes the worker {view_ms:.1f} ms "
          f"(lit within its frame: {len(lags)} of the views)")
    print("  worker step medians (ms):", worker_steps)
    session.worker.wait_idle(args.converge_timeout)

    # A 5k-triangle object moving every frame, camera still.
    target = np.array(region_data.view_matrix.inverted().translation) + \
        3.0 * -np.array(region_data.view_matrix.inverted().col[2][:3])
    ball, tris = sphere("bench_ball", 5000, 0.4, target.tolist())
    bpy.context.view_layer.update()
    draw()
    session.worker.wait_idle(args.converge_timeout)
    draw()
    moving = []
    updates0, t_move = session.worker.latest().stats.updates, time.perf_counter()
    for i in range(args.frames):
        ball.location.x = target[0] + 0.5 * math.sin(i / 6)
        t0 = time.perf_counter()
        bpy.context.view_layer.update()  # -> depsgraph_update_post -> view_update (timed inside)
        update_ms = (time.perf_counter() - t0) * 1e3
        frame = draw()
        frame.update = update_ms
        moving.append(frame)
    move_s = time.perf_counter() - t_move
    updates_move = session.worker.latest().stats.updates - updates0
    m = moving[skip:]
    nav_cpu = median([x.cpu for x in f])
    move_cpu = median([x.cpu for x in m])
    move_update = median([x.update for x in m])
    object_cost = move_cpu - nav_cpu + move_update
    print(f"moving {tris}-triangle object: view_update + depsgraph {move_update:.2f} ms, draw cpu {move_cpu:.2f} ms "
          f"(geometry upload {median([x.steps.get('upload_geometry', 0.0) for x in m]):.2f} ms) -> "
          f"{object_cost:.2f} ms more than a navigation redraw; worker {updates_move / move_s:.1f} GI updates/s")
    move_steps = {k: round(median([x.steps.get(k, 0.0) for x in m]), 3) for k in m[-1].steps}
    print("  median per step (ms):", move_steps)
    bpy.app.handlers.depsgraph_update_post.remove(handler)
    viewport.free(engine)
    offscreen.free()

    record = {
        "scene": args.scene, "width": width, "height": height, "frames": len(f),
        "visible_cells": published.stats.visible_cells, "converge_s": round(converge_s, 2),
        "main_cpu_ms_per_redraw": round(nav_cpu, 3),
        "readback_ms": round(median([x.readback for x in f]), 3),
        "gpu_pass_ms": round(median([x.gpu for x in f]), 2),
        "main_thread_time_ms": round(median([x.thread for x in f]), 2),
        "gi_updates_per_s_light_edit_still": round(still_rate, 1),
        "gi_updates_per_s_light_edit_navigating_30hz": round(replay_rate, 1),
        "worker_new_view_ms": round(view_ms, 1),
        "worker_steps_ms": worker_steps,
        "rays_per_s": round(still_rays),
        "gi_updates_per_s_during_llvmpipe_draws": round(updates_nav / nav_s, 1),
        "moving_object_triangles": tris,
        "moving_object_ms_per_frame": round(object_cost, 3),
        "gi_updates_per_s_moving_object": round(updates_move / move_s, 1),
        "steps_ms": steps,
    }
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    # The bpy module frees its GPU context before Python frees cached `gpu` objects: finalizing
    # would segfault after the results are printed (tests/conftest.py does the same).
    os._exit(code)
