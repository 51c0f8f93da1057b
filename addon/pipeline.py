"""Final renders of the HYBRIDGI engine: depsgraph -> snapshot -> the seed's nine steps -> passes.

Main thread only (it reads `bpy`); the cache work inside runs on numpy snapshots. Every frame
starts from a fresh cache converged with deterministic warm-up rays, so frame N renders the same
whether or not other frames were rendered before it (render farms may split an animation).
"""

import logging
import time

import numpy as np

from . import properties, sync
from ._core import errors, submodule

log = logging.getLogger(__name__)

#: Stats of the last rendered frame (seconds, per-step ms, rays): read by the CLI's JSON line.
LAST_STATS = {}

class RenderCancelled(errors.HybridGIError):
    """The user stopped the render (Esc)."""


def render_size(render):
    scale = render.resolution_percentage / 100.0
    return max(int(render.resolution_x * scale), 1), max(int(render.resolution_y * scale), 1)


def camera_matrices(depsgraph, scene, width, height):
    """(view, proj) numpy 4x4 of the scene camera, as Blender's own engines build them."""
    cam = scene.camera
    if cam is None:
        raise errors.HybridGIError("the scene has no active camera")
    cam_eval = cam.evaluated_get(depsgraph)
    render = scene.render
    proj = cam_eval.calc_matrix_camera(depsgraph, x=width, y=height,
                                       scale_x=render.pixel_aspect_x, scale_y=render.pixel_aspect_y)
    view = cam_eval.matrix_world.inverted()
    return np.array(view, np.float32), np.array(proj, np.float32)


def render_frame(engine, depsgraph):
    """Render the current frame into the engine's result (the HYBRIDGI engine's `render`)."""
    t0 = time.perf_counter()
    scene = depsgraph.scene
    props = scene.hybridgi
    width, height = render_size(scene.render)
    settings = props.cache_settings(scene)
    steps = {}

    engine.update_stats("HybridGI", "Syncing scene")
    ts = time.perf_counter()
    snapshot = sync.snapshot_from_depsgraph(depsgraph)
    steps["sync"] = (time.perf_counter() - ts) * 1e3
    view, proj = camera_matrices(depsgraph, scene, width, height)
    world = snapshot.world.color

    if snapshot.geometry.triangle_count == 0:
        engine.report({"WARNING"}, "HybridGI: the scene has no geometry to render; only the world is shown")
        _write_background(engine, depsgraph, width, height, world)
        _record(scene, t0, steps, width, height, rays=0, cells=0)
        return

    core_system = submodule("system")
    frame_mod = submodule("raster.frame")
    engine.update_stats("HybridGI", f"Building ray scene ({snapshot.geometry.triangle_count:,} triangles)")
    ts = time.perf_counter()
    system = core_system.GISystem(snapshot, settings)
    steps["build"] = (time.perf_counter() - ts) * 1e3
    pipeline = frame_mod.FramePipeline(props.raster_settings(cell_size=system.cache.grid.cell_size))
    try:
        pipeline.resize(width, height)
        ts = time.perf_counter()
        pipeline.upload(snapshot)
        steps["upload"] = (time.perf_counter() - ts) * 1e3

        def progress(i, n):
            engine.update_stats("HybridGI", f"Converging cache {i + 1}/{n}")
            engine.update_progress(0.9 * (i + 1) / max(n, 1))
            if engine.test_break():
                raise RenderCancelled("render cancelled")

        shaded, stats = pipeline.render(
            system, view, proj, frame=scene.frame_current, warmup=props.warmup_iterations, update=False,
            debug_view=min(properties.DEBUG_VIEW[props.debug_view], 3), world_color=world, progress=progress,
        )
        steps.update(stats.steps_ms)
        engine.update_stats("HybridGI", "Writing passes")
        ts = time.perf_counter()
        _write_result(engine, depsgraph, pipeline, width, height, world)
        steps["write"] = (time.perf_counter() - ts) * 1e3
        _record(scene, t0, steps, width, height, rays=stats.rays, cells=stats.visible_cells,
                grid=list(system.cache.grid.dims), triangles=snapshot.geometry.triangle_count)
    except RenderCancelled:
        log.info("HybridGI render cancelled")
    finally:
        pipeline.free()
        system.close()
    engine.update_progress(1.0)


def _record(scene, t0, steps, width, height, **extra):
    LAST_STATS.clear()
    LAST_STATS.update(
        seconds=round(time.perf_counter() - t0, 3),
        width=width, height=height,
        steps_ms={k: round(v, 2) for k, v in steps.items()},
        **extra,
    )
    log.info("HybridGI frame %d: %.2f s", scene.frame_current, LAST_STATS["seconds"])


def _set_pass(layer, name, pixels):
    """Write (h, w, c) float32 bottom-up pixels into a result pass, if the pass exists."""
    rp = layer.passes.get(name)
    if rp is None:
        return
    channels = rp.channels
    data = np.ascontiguousarray(pixels[..., :channels], np.float32)
    if data.shape[-1] < channels:
        pad = np.repeat(data[..., -1:], channels - data.shape[-1], axis=-1)
        data = np.concatenate([data, pad], axis=-1)
    rp.rect.foreach_set(data.ravel())


def _write_result(engine, depsgraph, pipeline, width, height, world):
    film_transparent = depsgraph.scene.render.film_transparent
    result = engine.begin_result(0, 0, width, height)
    layer = result.layers[0]
    combined = pipeline.deferred.read("combined").copy()
    if not film_transparent:
        combined[..., 3] = 1.0  # Cycles' alpha is 1 on the background unless the film is transparent
    _set_pass(layer, "Combined", combined)
    _set_pass(layer, "Diffuse Direct", pipeline.deferred.read("diffuse_direct"))
    _set_pass(layer, "Diffuse Indirect", pipeline.deferred.read("diffuse_indirect"))
    _set_pass(layer, "Diffuse Color", pipeline.deferred.read("diffuse_color"))
    ao = pipeline.deferred.read("ao")
    _set_pass(layer, "Ambient Occlusion", np.repeat(ao, 3, axis=-1))
    depth = pipeline.gbuffer.read("depth")
    _set_pass(layer, "Depth", depth)
    normal = pipeline.gbuffer.read("normal")
    _set_pass(layer, "Normal", normal[..., :3] * (depth < 1e9))
    engine.end_result(result)


def _write_background(engine, depsgraph, width, height, world):
    result = engine.begin_result(0, 0, width, height)
    layer = result.layers[0]
    alpha = 0.0 if depsgraph.scene.render.film_transparent else 1.0
    bg = np.empty((height, width, 4), np.float32)
    bg[...] = (*np.asarray(world, np.float32).tolist(), alpha)
    _set_pass(layer, "Combined", bg)
    for name in ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color", "Ambient Occlusion", "Normal"):
        _set_pass(layer, name, np.zeros((height, width, 3), np.float32))
    _set_pass(layer, "Depth", np.full((height, width, 1), 1e10, np.float32))
    engine.end_result(result)
