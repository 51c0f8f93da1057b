"""The HybridGI viewport's time to quality (part of bench/time_to_quality.py): the image the
HYBRIDGI engine's view_draw displays, read back at fixed seconds after the first draw, headless.

    python bench/ttq_viewport.py SCENE.blend --res 640x360 --out DIR [--checkpoints 0.1,0.25,...]

Driven like bench/bench_viewport.py and tests/test_viewport.py: a fake engine and region whose
region_data carries the scene camera's view and projection (calc_matrix_camera at the region's
size), an offscreen RGBA16F target; view_update / view_draw are called directly (timers and draw
handlers never run in the bpy module). The displayed image is the offscreen after view_draw:
scene-linear Combined (the fake engine binds no display transform), rows bottom-up.

Two timelines, both starting at the start of the first view_draw (it rasterizes the G-buffer and
posts the view to the worker; the scene sync in view_update comes before and is reported apart):

- wall: the main thread redraws continuously, as Blender does while the engine tags redraws. Each
  redraw runs the raster passes on llvmpipe, which uses the same two CPU cores as the worker: the
  worker's progress is slowed by raster work a GPU would do in milliseconds.
- worker: the main thread draws once, then only sleeps; at each checkpoint it takes the worker's
  latest publication (`worker.latest()`: read-only arrays, no GPU work). No raster runs beside
  the worker's steps on this clock: the worker builds the scene first (view_update's edit, timed
  alone and counted), then the first draw rasterizes the G-buffer and posts the view, and the
  clock runs from the draw's end plus the scene build; after a light move the worker re-lights
  the view it has, and the clock starts at the edit, with no draw. When the timeline is over,
  each captured publication is drawn (the session's `worker.latest` is pointed at it for that one
  draw) and read back. So llvmpipe's cost stays out of the worker's timeline, and what is drawn is
  exactly what a GPU would have shown at that moment. A GPU also adds the anti-aliasing subframes
  of a still view (`viewport_aa.py`) within milliseconds: each publication is drawn with all its
  subframes (the "worker" images); "worker_centre" keeps the pixel-centre image of the same
  publication (what a GPU shows before its first subframe).

Then the same after a light move: the first lamp moves (a sun turns 25 degrees about Z, any other
lamp moves 30% of the way towards the middle of the scene), the view re-converges, and the lamp
moves back to where the reference has it; the timelines start at that move (the wall one at
the first draw after it), from a cache converged for the other position. So the image is
compared with the one reference.

Last, "settled": the worker session's view once it is idle (up to CONVERGE_TIMEOUT_S), the
viewport's own converged error.

Prints one JSON line: {"*_sync_s", "timelines": {name: [{"t", "file"}]}, "notes"};
the images are DIR/<timeline>_<i>.npy (float16, (h, w, 4), rows bottom-up).
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import os
import sys
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace

REPO = Path(__file__).resolve().parents[1]
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="hybridgi_ttq_"))
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import bpy  # noqa: E402
import gpu  # noqa: E402
import numpy as np  # noqa: E402
from bench_viewport import FakeEngine, gpu_context  # noqa: E402
from mathutils import Matrix, Vector  # noqa: E402

from hybridgi_cli import dev_install  # noqa: E402

#: How long the view may take to re-converge between timelines (the worker keeps refining a
#: converged view for a long time; 99% of its cells converged is what bench_viewport.py waits for).
CONVERGE_TIMEOUT_S = 20.0
#: Sleep of the wall timeline's loop when a redraw had nothing new to draw (Blender's redraw
#: timer would not redraw either).
IDLE_POLL_S = 0.005


def log(message: str) -> None:
    print(f"ttq_viewport: {message}", file=sys.stderr, flush=True)


class Viewport:
    def __init__(self, viewport, width: int, height: int):
        self.viewport = viewport
        self.width, self.height = width, height
        scene = bpy.context.scene
        depsgraph = bpy.context.evaluated_depsgraph_get()
        cam = scene.camera.evaluated_get(depsgraph)
        self.region_data = SimpleNamespace(
            view_matrix=cam.matrix_world.normalized().inverted(), window_matrix=cam.calc_matrix_camera(depsgraph, x=width, y=height),
            is_perspective=cam.data.type != "ORTHO", view_perspective="CAMERA")
        self.context = SimpleNamespace(region=SimpleNamespace(width=width, height=height),
                                       region_data=self.region_data, scene=scene,
                                       evaluated_depsgraph_get=bpy.context.evaluated_depsgraph_get)
        self.engine = FakeEngine()
        self.offscreen = gpu.types.GPUOffScreen(width, height, format="RGBA16F")
        self.handler = lambda _scene, dg: viewport.view_update(self.engine, self.context, dg)
        bpy.app.handlers.depsgraph_update_post.append(self.handler)

    @property
    def session(self):
        return self.engine.viewport

    def update(self):
        self.viewport.view_update(self.engine, self.context, bpy.context.evaluated_depsgraph_get())

    def draw(self, read: bool = False):
        """One view_draw into the offscreen; returns (redrawn, image or None)."""
        out = np.empty((self.height, self.width, 4), np.float32) if read else None
        with self.offscreen.bind():
            self.viewport.view_draw(self.engine, self.context, bpy.context.evaluated_depsgraph_get())
            if read:
                fb = gpu.state.active_framebuffer_get()
                fb.read_color(0, 0, self.width, self.height, 4, 0, "FLOAT", data=gpu.types.Buffer("FLOAT", out.size, out))
        return self.session.last_stats.redrawn, out

    def finish_aa(self, read: bool = False, limit: int = 256):
        """Redraw while the session adds anti-aliasing subframes (Blender redraws while the engine
        tags redraws); returns the last image when read."""
        img = None
        self.aa_ms = []  # llvmpipe milliseconds of each subframe's redraw
        for _ in range(limit):
            session = self.session
            aa = getattr(session, "aa", None)
            if aa is None or not session._aa_due(session.worker.latest()):
                break
            self.draw()
            self.aa_ms.append(session.last_stats.total_ms)
        if read:
            _, img = self.draw(read=True)
        return img

    def applied(self, timeout: float) -> float:
        """Wait until the worker has applied every edit posted so far; returns the seconds since
        the call (the worker's scene build when the last edit was just posted)."""
        t0 = time.perf_counter()
        gen = self.session.last_edit_gen
        self.session.worker.wait(lambda p: p.stats.scene_gen >= gen, timeout)
        return time.perf_counter() - t0

    def settle(self, idle: bool = False):
        # Stats of a publication from before the latest edit say nothing about it: wait for one
        # that applied every edit posted so far (idle: and for the worker to have nothing left).
        gen = self.session.last_edit_gen
        ok = self.session.worker.wait(
            lambda p: p.stats.scene_gen >= gen and (p.stats.idle or (not idle and p.stats.converged >= 0.99)),
            CONVERGE_TIMEOUT_S)
        self.draw()
        return ok

    def close(self):
        bpy.app.handlers.depsgraph_update_post.remove(self.handler)
        if self.session is not None:
            self.viewport.free(self.engine)
        self.offscreen.free()


def wall_timeline(view: Viewport, checkpoints, folder: Path, name: str) -> list[dict]:
    shots, k = [], 0
    t0 = time.perf_counter()
    while k < len(checkpoints):
        redrawn, _ = view.draw()
        t = time.perf_counter() - t0
        if t >= checkpoints[k]:
            _, img = view.draw(read=True)  # a no-op redraw unless a publication just arrived
            t = time.perf_counter() - t0
            while k < len(checkpoints) and t >= checkpoints[k]:
                shots.append(_save(folder, name, len(shots), img, t, checkpoints[k]))
                k += 1
        elif not redrawn:
            time.sleep(IDLE_POLL_S)
    return shots


def worker_timeline(view: Viewport, checkpoints, folder: Path, name: str,
                    head_s: float | None = None) -> list[dict]:
    """head_s : None: the first draw posts the view (a new session), and the clock starts at its
    end with the worker's scene build (`Viewport.applied`) already counted; a number: no draw
    first (a lamp edit of a posted view, which the worker lights without one), the clock started
    head_s ago. Either way llvmpipe's raster, milliseconds on a GPU, never runs beside the
    worker's steps on the timeline: the first draw's G-buffer took 0.17-0.23 s of both cores here
    and slowed the scene build beside it ~10x (spheres 640x360: 23 ms alone, 212 ms beside it);
    the view it posts is handed to the worker once it returns."""
    session = view.session
    captured = []
    first_ms = None
    if head_s is None:
        applied = getattr(view, "applied_s", 0.0)
        # The view the draw posts reaches the worker when the draw is over: its passes after the
        # post (resolve, present: 0.05-0.1 s on llvmpipe) would run beside the worker's first steps.
        posted = []
        session.worker.post_view = posted.append
        t_draw = time.perf_counter()
        try:
            view.draw()
        finally:
            del session.worker.post_view
        first_ms = (time.perf_counter() - t_draw) * 1e3
        t0 = time.perf_counter() - applied
        for request in posted:
            session.worker.post_view(request)
    else:
        t0 = time.perf_counter() - head_s
    for c in checkpoints:
        delay = t0 + c - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        captured.append((time.perf_counter() - t0, c, session.worker.latest()))
    # Draw what the worker had published at each checkpoint (no more worker time is measured).
    worker = session.worker
    latest = worker.latest
    shots, centre = [], []
    busy = getattr(session, "aa_while_busy", None)
    try:
        session.aa_while_busy = True  # a GPU's subframes cost the worker nothing
        for i, (t, c, published) in enumerate(captured):
            worker.latest = lambda p=published: p
            session._drawn_key = None  # the centre image of this publication, even if the last one had it
            _, img = view.draw(read=True)
            centre.append(_save(folder, f"{name}_centre", i, img, t, c))
            draw_ms = session.last_stats.total_ms
            img = view.finish_aa(read=True)
            shot = _save(folder, name, i, img, t, c)
            # llvmpipe's share, apart from the worker's timeline: the centre redraw of this
            # publication and its anti-aliasing subframes' redraws.
            shot["draw_ms"] = round(draw_ms, 1)
            shot["aa_draw_ms"] = [round(v, 1) for v in view.aa_ms]
            shot["updates"] = published.stats.updates
            shot["steps_ms"] = {k: round(v, 1) for k, v in published.stats.steps_ms.items()}
            shots.append(shot)
    finally:
        worker.latest = latest
        session.aa_while_busy = busy
    if first_ms is not None:
        shots[0]["first_draw_ms"] = round(first_ms, 1)
        shots[0]["scene_build_s"] = round(getattr(view, "applied_s", 0.0), 4)
    view.centre_shots = centre
    return shots


def _save(folder: Path, name: str, i: int, img, t: float, checkpoint: float) -> dict:
    file = f"{name}_{i}.npy"
    np.save(folder / file, img.astype(np.float16))
    return {"checkpoint": checkpoint, "t": round(t, 4), "file": file}


def lamp_move(light, centre):
    """(moved, back): apply the move away, and the move back to the original transform."""
    original = light.matrix_world.copy()
    if light.data.type == "SUN":
        moved = Matrix.Rotation(math.radians(25.0), 4, "Z") @ original
    else:
        loc = original.translation
        moved = Matrix.Translation(0.3 * (Vector(centre) - loc)) @ original

    def away():
        light.matrix_world = moved
        bpy.context.view_layer.update()

    def back():
        light.matrix_world = original
        bpy.context.view_layer.update()

    return away, back


def scene_centre():
    pts = []
    for obj in bpy.context.scene.objects:
        if obj.type == "MESH":
            pts += [obj.matrix_world @ Vector(c) for c in obj.bound_box]
    if not pts:
        return (0.0, 0.0, 0.0)
    a = np.array([tuple(p) for p in pts])
    return tuple(0.5 * (a.min(0) + a.max(0)))


def run_timelines(viewport, args, width, height, folder, checkpoints, timed, timeline_fn, prefix):
    """Start a fresh viewport session, run the first-draw timeline, then the light-move one."""
    view = Viewport(viewport, width, height)
    out, notes = {}, []
    try:
        t0 = time.perf_counter()
        view.update()
        timed[f"{prefix}_sync_s"] = round(time.perf_counter() - t0, 3)
        if prefix == "worker":
            # The worker builds the scene alone (with a GPU the first draw beside it is brief).
            view.applied_s = view.applied(60.0)
        out[prefix] = timeline_fn(view, checkpoints, folder, prefix)
        if getattr(view, "centre_shots", None):
            out[f"{prefix}_centre"], view.centre_shots = view.centre_shots, None
        if not view.settle():
            notes.append(f"{prefix}: the view did not converge within {CONVERGE_TIMEOUT_S:.0f} s")
        light = next((o for o in bpy.context.scene.objects if o.type == "LIGHT"), None)
        if light is None:
            notes.append("no lamp to move: light-move timeline skipped")
            return out, notes
        away, back = lamp_move(light, scene_centre())
        away()
        view.draw()
        # The artist's view before the move is a refined one (its pixel passes, edges, glossy
        # light: what a lamp edit may carry over), not one whose cache just converged.
        view.settle(idle=True)
        t_light = time.perf_counter()
        back()
        if prefix == "worker":
            out[f"{prefix}_light"] = timeline_fn(view, checkpoints, folder, f"{prefix}_light",
                                                 head_s=time.perf_counter() - t_light)
        else:
            out[f"{prefix}_light"] = timeline_fn(view, checkpoints, folder, f"{prefix}_light")
        if getattr(view, "centre_shots", None):
            out[f"{prefix}_light_centre"], view.centre_shots = view.centre_shots, None
        timed["light"] = f"{light.name} ({light.data.type})"
        if prefix == "worker":
            # Where the view ends up: the light-move timeline's view once the worker is idle (every
            # refinement done), or after CONVERGE_TIMEOUT_S.
            view.settle(idle=True)
            img = view.finish_aa(read=True)  # the anti-aliasing subframes of the idle view
            out["settled"] = [_save(folder, "settled", 0, img, time.perf_counter() - t_light, None)]
    finally:
        view.close()
    return out, notes


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("blend", type=Path)
    parser.add_argument("--res", default="640x360")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--checkpoints", default="0.1,0.25,0.5,1,2,4")
    parser.add_argument("--timelines", default="wall,worker",
                        help="which timelines to run (wall, worker; the worker one is llvmpipe-free)")
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.res.lower().split("x"))
    checkpoints = sorted(float(c) for c in args.checkpoints.split(","))
    args.out.mkdir(parents=True, exist_ok=True)

    bpy.ops.wm.open_mainfile(filepath=str(args.blend.resolve()))
    package = dev_install.enable()
    viewport = importlib.import_module(f"{package.__name__}.viewport")
    gpu_context()
    bpy.context.scene.render.engine = "HYBRIDGI"

    record = {"width": width, "height": height, "timelines": {}, "notes": []}
    # A throw-away session first: compiles the shaders, so neither timeline pays for that.
    warm = Viewport(viewport, width, height)
    warm.update()
    warm.draw()
    warm.close()
    wanted = {t.strip() for t in args.timelines.split(",")}
    for prefix, fn in (("wall", wall_timeline), ("worker", worker_timeline)):
        if prefix not in wanted:
            continue
        log(f"{prefix} timelines")
        timelines, notes = run_timelines(viewport, args, width, height, args.out, checkpoints, record, fn, prefix)
        record["timelines"].update(timelines)
        record["notes"] += notes
    record["notes"] = sorted(set(record["notes"]))
    print(json.dumps(record))
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)  # see bench_viewport.py: finalizing the bpy module after gpu objects segfaults
