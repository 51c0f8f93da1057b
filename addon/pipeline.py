"""Final renders of the HYBRIDGI engine: depsgraph -> snapshot -> the seed's nine steps -> passes.

Main thread only (it reads `bpy`); the cache work inside runs on numpy snapshots. Two animation
modes (`scene.hybridgi.animation_mode`):

- INDEPENDENT (default, farm-safe): every frame starts from a fresh cache converged with
  deterministic warm-up rays, so frame N renders the same whether or not other frames were
  rendered before it (render farms may split an animation).
- INCREMENTAL: a run of successive frames of one scene is one job that keeps a `GISession`. Each
  frame syncs its snapshot: moved objects go through the per-frame dynamic Embree scene, deformed
  meshes are re-traced, and the cells within the indirect range of what changed get urgency
  (quadratic fall-off: lower hysteresis) and extra rays; then one update of the visible cells
  replaces the warm-up, with the same probe rays every frame, so the cache changes where the
  scene does and its noise does not flicker. The job's first frame warms up as INDEPENDENT does,
  and so does a frame whose light jumps (LIGHT_JUMP).

Both seed the lamps' shadow rays with the scene's seed alone, not the frame (Cycles' default, a
non-animated seed): static parts of an animation keep one noise pattern instead of crawling.
"""

import logging
import math
import time
from dataclasses import dataclass

import numpy as np

from hybridgi_core import catcher, errors, visible
from hybridgi_core.raster import gbuffer, world_background
from hybridgi_core.raster.frame import FramePipeline
from hybridgi_core.raster.gather import max_texture_size
from hybridgi_core.raster.lens import Lens
from hybridgi_core.session import GISession
from hybridgi_core.settings import CacheSettings
from hybridgi_core.system import GISystem

from . import animation, compat, properties, sync, updates

log = logging.getLogger(__name__)

#: Stats of the last rendered frame (seconds, per-step ms, rays): read by the CLI's JSON line.
LAST_STATS = {}

#: Frame number that seeds the direct light's shadow rays in every frame (see the docstring).
DIRECT_SEED_FRAME = 0
#: The probe rays of every update after a job's warm-up are those of this frame number (the extra
#: update near a change: of the next one), whatever frame renders: a cell then changes only where
#: the scene does, not with each frame's random ray rotation, which made the EMA's noise flicker.
#: Below the warm-up's numbers (system.WARMUP_FRAME_BASE + i), so it repeats none of its rays.
JOB_RAYS_FRAME = -(2**21)
#: A lamp, the sky or an emitter whose light changes by more than this share between two frames
#: of a job re-converges the kept cache with the warm-up. One update re-lights the first bounce,
#: but bounces read at probe hits lag: a doubled lamp's indirect light came out 1.77x after one
#: frame and 1.86x after seven (Cornell box). Animated lamps that change by less per frame take
#: the cheap update.
LIGHT_JUMP = 0.25


class RenderCancelled(errors.HybridGIError):
    """The user stopped the render (Esc)."""


def render_size(render):
    scale = render.resolution_percentage / 100.0
    return max(int(render.resolution_x * scale), 1), max(int(render.resolution_y * scale), 1)


def result_rect(render, width, height):
    """(x, y, w, h) pixels of the frame the render result holds, bottom-up like Blender's: the
    whole frame, or the render border (Cycles renders the border only; Blender crops the saved
    image to it or pads it back to the full frame, by `use_crop_to_border`)."""
    if not render.use_border:
        return 0, 0, width, height
    x0 = min(max(int(render.border_min_x * width), 0), width - 1)
    y0 = min(max(int(render.border_min_y * height), 0), height - 1)
    x1 = min(max(int(render.border_max_x * width), x0 + 1), width)
    y1 = min(max(int(render.border_max_y * height), y0 + 1), height)
    return x0, y0, x1 - x0, y1 - y0


def pixel_filter(scene):
    """(type, width in pixels) of the pixel filter final renders integrate: Cycles' own
    (`scene.cycles`), so a scene renders with the filter Cycles would use; without the Cycles
    add-on, Blender's Filter Size (`render.filter_size`) as a Blackman-Harris filter."""
    cycles = getattr(scene, "cycles", None)
    if cycles is not None and hasattr(cycles, "filter_width"):
        return str(cycles.pixel_filter_type), float(cycles.filter_width)
    return "BLACKMAN_HARRIS", float(scene.render.filter_size)


def camera_lens(depsgraph, scene) -> Lens | None:
    """The scene camera's thin lens as Cycles sets it up (`blender/camera.cpp`): radius = focal
    length / (2 f-stop), the focus distance along the view axis (to the focus object when one is
    set), blades, rotation, ratio; None without depth of field or for a non-perspective camera."""
    cam = scene.camera
    data = getattr(cam, "data", None)
    dof = getattr(data, "dof", None)
    if dof is None or not dof.use_dof or data.type != "PERSP" or scene.hybridgi.pixel_samples <= 1:
        return None
    fstop = max(float(dof.aperture_fstop), 1e-5)
    radius = float(data.lens) * 1e-3 / (2.0 * fstop)
    focus = float(dof.focus_distance)
    target = dof.focus_object
    if target is not None:
        eye = cam.evaluated_get(depsgraph).matrix_world.normalized()
        at = target.evaluated_get(depsgraph).matrix_world.translation
        bone = getattr(dof, "focus_subtarget", "")
        if bone and target.type == "ARMATURE" and target.pose is not None and bone in target.pose.bones:
            at = target.evaluated_get(depsgraph).matrix_world @ target.pose.bones[bone].head
        axis = eye.col[2].xyz.normalized()
        focus = abs(axis.dot(eye.translation - at))
    if not (math.isfinite(radius) and math.isfinite(focus)) or radius <= 0.0:
        return None
    return Lens(radius=radius, focus=max(focus, 1e-6), blades=int(dof.aperture_blades),
                rotation=float(dof.aperture_rotation), ratio=max(float(dof.aperture_ratio), 1e-3))


def camera_matrices(depsgraph, scene, width, height):
    """(view, proj) numpy 4x4 of the scene camera, as Blender's own engines build them."""
    cam = scene.camera
    if cam is None:
        raise errors.HybridGIError("the scene has no active camera")
    if cam.type != "CAMERA":
        raise errors.HybridGIError(f"the active camera {cam.name!r} is not a camera object")
    if cam.data.type == "PANO":
        # The G-buffer is a raster of a pinhole projection: there is no panoramic raster pass.
        raise errors.HybridGIError(
            f"camera {cam.name!r} is panoramic, which HybridGI cannot render; use a perspective or "
            "orthographic camera, or render it with Cycles")
    cam_eval = cam.evaluated_get(depsgraph)
    render = scene.render
    proj = cam_eval.calc_matrix_camera(depsgraph, x=width, y=height,
                                       scale_x=render.pixel_aspect_x, scale_y=render.pixel_aspect_y)
    # Blender's engines ignore the camera's scale (its own or a scaled parent's: a model imported in
    # centimetres under an empty at 0.01): the view keeps the camera's axes and position only, as
    # Cycles' and EEVEE's do. The scaled matrix's inverse blew distances up 100x past the far clip.
    view = cam_eval.matrix_world.normalized().inverted()
    return np.array(view, np.float32), np.array(proj, np.float32)


#: View-layer passes Cycles writes and HybridGI does not (the flag, its name in the warning).
UNWRITTEN_PASSES = (
    ("use_pass_transmission_direct", "Transmission Direct"),
    ("use_pass_transmission_indirect", "Transmission Indirect"), ("use_pass_transmission_color", "Transmission Color"),
    ("use_pass_emit", "Emission"), ("use_pass_environment", "Environment"), ("use_pass_shadow", "Shadow"),
    ("use_pass_mist", "Mist"), ("use_pass_position", "Position"), ("use_pass_vector", "Vector"),
    ("use_pass_uv", "UV"), ("use_pass_object_index", "Object Index"), ("use_pass_material_index", "Material Index"),
    ("use_pass_cryptomatte_object", "Cryptomatte Object"), ("use_pass_cryptomatte_material", "Cryptomatte Material"),
    ("use_pass_cryptomatte_asset", "Cryptomatte Asset"),
)
#: Cycles' own view-layer passes (`view_layer.cycles`) HybridGI does not write.
UNWRITTEN_CYCLES_PASSES = (
    ("denoising_store_passes", "Denoising Data"), ("use_pass_shadow_catcher", "Shadow Catcher"),
    ("use_pass_volume_direct", "Volume Direct"), ("use_pass_volume_indirect", "Volume Indirect"),
)


def unsupported_settings(scene, view_layer) -> list[str]:
    """What this scene asks for that Cycles honours and HybridGI does not render (warned once)."""
    notes = []
    if getattr(scene.render, "use_motion_blur", False):
        notes.append("motion blur is not rendered")
    bounces = properties.cycles_diffuse_bounces(scene)
    if bounces == 0:
        notes.append("Cycles' bounce limit (0 diffuse bounces) is followed: no light reflected by surfaces "
                     "(no Diffuse Indirect); the sky, emitters and lamps light directly")
    elif bounces == 1 and scene.hybridgi.indirect_quality == "MULTI_BOUNCE":
        notes.append("Cycles' bounce limit (1 diffuse bounce) is followed: rendered as Indirect Quality One Bounce")
    if getattr(scene.render, "use_multiview", False):
        notes.append("stereoscopy is not rendered: HybridGI renders the scene camera's view only")
    camera = scene.camera
    dof = getattr(getattr(camera, "data", None), "dof", None)
    if dof is not None and getattr(dof, "use_dof", False):
        if camera.data.type != "PERSP":
            notes.append(f"depth of field of {camera.data.type.lower()} camera {camera.name!r} is not rendered "
                         "(everything is in focus)")
        elif scene.hybridgi.pixel_samples <= 1:
            notes.append(f"depth of field of camera {camera.name!r} needs Pixel Samples above 1 (its lens points "
                         "are the subframes): everything is in focus")
    passes = [label for flag, label in UNWRITTEN_PASSES if getattr(view_layer, flag, False)]
    own = getattr(view_layer, "cycles", None)
    passes += [label for flag, label in UNWRITTEN_CYCLES_PASSES if getattr(own, flag, False)]
    # Shader AOVs and light groups add passes of their own to Cycles' render (a compositor tree
    # may read them): name them, or the file silently lacks what the user set up.
    passes += [f"AOV {aov.name!r}" for aov in getattr(view_layer, "aovs", ())]
    passes += [f"light group {group.name!r} (Combined_{group.name})" for group in getattr(view_layer, "lightgroups", ())]
    if passes:
        notes.append(f"passes not written: {', '.join(passes)}")
    return notes


def render_frame(engine, depsgraph):
    """Render the current frame into the engine's result (the HYBRIDGI engine's `render`)."""
    t0 = time.perf_counter()
    scene = depsgraph.scene
    props = scene.hybridgi
    width, height = render_size(scene.render)
    limit = max_texture_size()
    if max(width, height) > limit:
        # The G-buffer and film are GPU textures of the image's size: refused before any is made.
        raise errors.LimitError(f"the image is {width}x{height} pixels; this GPU's textures take at most {limit} "
                                "per side: lower the resolution (or its %)")
    settings = props.cache_settings(scene)
    for note in unsupported_settings(scene, depsgraph.view_layer):
        engine.report({"WARNING"}, f"HybridGI: {note}")
        log.warning("%s", note)
    incremental = props.animation_mode == "INCREMENTAL"
    key = animation.render_job_key(scene.name_full, depsgraph.view_layer.name)
    if not incremental:
        animation.unregister_session(key)  # a job kept by an earlier incremental render: free it
    steps = {}

    engine.update_stats("HybridGI", "Syncing scene")
    ts = time.perf_counter()
    # Animated objects start in the per-frame dynamic ray scene of an incremental job; a fresh
    # system per frame has no use for that split (and keeps the LOD of every object).
    dynamic = updates.animated_object_names(depsgraph.objects) if incremental else frozenset()
    snapshot = sync.snapshot_from_depsgraph(depsgraph, dynamic)
    steps["sync"] = (time.perf_counter() - ts) * 1e3
    view, proj = camera_matrices(depsgraph, scene, width, height)
    world = snapshot.world.background_color

    if snapshot.geometry.triangle_count == 0:
        animation.unregister_session(key)  # nothing to keep a cache of
        engine.report({"WARNING"}, "HybridGI: the scene has no geometry to render; only the world is shown")
        _write_background(engine, depsgraph, width, height, world, snapshot.world.background_map, view, proj)
        _record(scene, t0, steps, width, height, rays=0, cells=0, animation_mode=props.animation_mode)
        return

    engine.update_stats("HybridGI", f"Building ray scene ({snapshot.geometry.triangle_count:,} triangles)")
    ts = time.perf_counter()
    job = None
    extra = {"animation_mode": props.animation_mode}
    if incremental:
        job = _job_for(scene, settings, dynamic, key)
        try:
            system, fresh, job_stats = job.advance(snapshot)
        except BaseException:
            animation.unregister_session(key)  # never continue a job from a frame that failed
            raise
        extra.update(job_stats)
    else:
        system, fresh = GISystem(snapshot, settings), True
    steps["build"] = (time.perf_counter() - ts) * 1e3
    # A new cache (every independent frame, a job's first frame, a scene that outgrew the grid)
    # converges with the warm-up; later frames of a job update, through _IncrementalUpdate.
    warmup = props.warmup_iterations if fresh else 0
    # A job without warm-up updates from its first frame on (else its cache would stay empty).
    update = job is not None and warmup == 0
    refresh = None
    if update:
        # A cache solved from stored hits refreshes by re-solving: only the rays the frame's
        # changes reached are traced again, the rest re-shade (localized by construction).
        refresh = (_SolvedRefresh(system) if system.solver.has_hits
                   else _IncrementalUpdate(system, job.near, job.inner, extra["lights_changed"]))
    cells_view = props.debug_view == "CELLS"
    # The pixel filter's subframes (one when Cache Cells colours each pixel by its centre's cell).
    filter_type, filter_size = pixel_filter(scene)
    pipeline = FramePipeline(props.raster_settings(cell_size=system.cache.grid.cell_size),
                             subframes=1 if cells_view else props.pixel_samples,
                             filter_size=filter_size, filter_type=filter_type,
                             direct_samples=props.shadow_samples, glossy_samples=props.glossy_samples,
                             lens=None if cells_view else camera_lens(depsgraph, scene))
    try:
        # GPU render targets (~40 at 640x360): llvmpipe allocates them in ~0.35 s of CPU, a GPU in
        # milliseconds, so they are a step of their own (a GPU pass in bench/time_to_quality.py).
        ts = time.perf_counter()
        pipeline.resize(width, height)
        steps["targets"] = (time.perf_counter() - ts) * 1e3
        ts = time.perf_counter()
        pipeline.upload(snapshot)
        pipeline.set_world(snapshot.world)
        steps["upload"] = (time.perf_counter() - ts) * 1e3

        warmup_start = time.perf_counter()

        def progress(i, n):
            # In the status bar, and logged (the CLI prints the add-on's INFO records on stderr);
            # the updates cost about the same each, so the rest takes as long per update.
            eta = (time.perf_counter() - warmup_start) / (i + 1) * (n - i - 1)
            engine.update_stats("HybridGI", f"Converging cache {i + 1}/{n}, {eta:.1f} s left")
            log.info("frame %d: converging cache %d/%d, %.1f s left", depsgraph.scene.frame_current, i + 1, n, eta)
            engine.update_progress(0.9 * (i + 1) / max(n, 1))
            if engine.test_break():
                raise RenderCancelled("render cancelled")

        shaded, stats = pipeline.render(
            system, view, proj, frame=DIRECT_SEED_FRAME, warmup=warmup, update=update,
            debug_view=0 if props.debug_view == "CELLS" else properties.DEBUG_VIEW[props.debug_view], world_color=world, progress=progress,
            update_hook=refresh,
        )
        steps.update(stats.steps_ms)
        extra.update(subframes=stats.subframes, extra_pixels=stats.extra_pixels)
        if update:
            extra.update(updated_cells=refresh.updated_cells, extra_cells=refresh.extra_cells,
                         refresh="resolve" if isinstance(refresh, _SolvedRefresh) else "update")
        engine.update_stats("HybridGI", "Writing passes")
        ts = time.perf_counter()
        _write_result(engine, depsgraph, pipeline, width, height, world,
                      cache=system.cache if cells_view else None, levels=system.levels,
                      catchers=None if cells_view else _ShadowCatchers(system, snapshot.world, view, proj))
        steps["write"] = (time.perf_counter() - ts) * 1e3
        if job is not None:
            job.finish(scene.frame_current)
            extra["job_frames"] = job.frames
        _record(scene, t0, steps, width, height, rays=stats.rays, cells=stats.visible_cells,
                grid=list(system.cache.grid.dims), triangles=snapshot.geometry.triangle_count, **extra)
    except RenderCancelled:
        log.info("HybridGI render cancelled")
        animation.unregister_session(key)  # its cache stopped half-converged
    except BaseException:
        animation.unregister_session(key)  # never continue a job from a frame that failed
        raise
    finally:
        pipeline.free()
        if job is None:
            system.close()
    engine.update_progress(1.0)


# --- incremental jobs --------------------------------------------------------------------------


#: Incremental jobs by registry key; each is also registered with `animation` (handlers feed it).
_JOBS = {}


@dataclass
class IncrementalJob:
    """One scene's run of successive incremental frames: a `GISession` and where it stands.

    A render continues the job when its settings are the job's and its frame comes 1 to
    `frame_step` frames after the job's last one (Render Animation, or the CLI's --frames A-B,
    which renders one frame per job of Blender's); anything else starts a new job, so re-rendering
    a frame or jumping back converges from scratch.
    """

    key: tuple
    session: GISession
    settings: CacheSettings
    frame: int | None = None  # the last frame rendered
    frames: int = 0  # frames finished in this job
    #: Surface cells within the indirect range of what changed this frame, and those of them
    #: within half of it (fall-off urgency >= 0.75), which get an extra update: near a change the
    #: cache needs more rays per frame, not only a faster blend. int64.
    near: np.ndarray = None
    inner: np.ndarray = None

    def continues(self, settings, frame, step) -> bool:
        return (self.frame is not None and settings == self.settings
                and 0 < frame - self.frame <= max(step, 1))

    def advance(self, snapshot):
        """Sync to this frame's snapshot and mark the cells near what changed.

        Returns (system, fresh, stats): fresh when the cache is new (first frame, or the scene
        outgrew the grid) and must converge before this frame renders.
        """
        events = animation.take_events(self.key)
        report = self.session.sync(snapshot)
        system = self.session.system
        cache = system.cache
        changes = report.changes
        # The session raised the snapshot diff's events. Plus the handlers' boxes (evaluated
        # bounds, every place seen since the last frame) of what the diff confirms moved: the
        # handlers note every animated object, moving this frame or not.
        swept = [box for name, box in events.swept.items() if name in changes.displaced]
        touched = report.touched
        if swept and not report.fresh:
            touched = np.union1d(touched, system.on_geometry_changed(swept))
        boxes = [] if report.fresh else changes.boxes + swept
        self.near = np.intersect1d(touched, system.surface_cells())
        half = 0.5 * cache.influence_radius()
        close = [cache.grid.cells_near(lo, hi, half)[0] for lo, hi in boxes]
        self.inner = np.intersect1d(self.near, np.concatenate(close)) if close else np.zeros(0, np.int64)
        relit = changes.shading_changed and not report.fresh
        if relit:
            # The session raised every cell's urgency to re-converge at half weight, the viewport's
            # compromise between lag and ray noise. With the job's fixed rays the new estimate
            # carries no frame-to-frame noise, so a refreshed cell takes it whole: no lag behind
            # a moving lamp, no flicker (measured on the animated scene, frames 2-12: frame-to-
            # frame noise 1.0% vs 2.9% at half weight; difference to independent frames 4.4% vs 5.6%).
            cache.urgency.fill(1.0)
        jumped = relit and changes.light_jumped(cache.influence_radius(), LIGHT_JUMP)
        fresh = jumped or not (cache.samples > 0).any()
        stats = {
            "rebuilt": report.rebuilt, "moved": report.moved, "lights_changed": relit,
            "light_jump": bool(jumped), "touched_cells": int(touched.size), "sync_ms": round(report.ms, 2),
        }
        return system, fresh, stats

    def finish(self, frame) -> None:
        self.frame = frame
        self.frames += 1


def _job_for(scene, settings, dynamic, key):
    job = _JOBS.get(key)
    if job is not None and job.continues(settings, scene.frame_current, scene.frame_step):
        return job
    animation.unregister_session(key)  # the previous job ends here (its on_drop closes it)
    job = IncrementalJob(key, GISession(settings, frozenset(dynamic)), settings)
    _JOBS[key] = job
    animation.register_session(key, job.session, scene=scene.name_full, on_drop=lambda: _close_job(key))
    animation.take_events(key)  # whatever happened before the job is no news to it
    return job


def _close_job(key):
    job = _JOBS.pop(key, None)
    if job is not None:
        job.session.close()


class _SolvedRefresh:
    """The update hook of an incremental frame whose cache the solver converged from stored
    hits: `GISystem.resolve()` traces the rays the session's events marked stale again (moved
    objects, lamps' shadow rays where lamps changed) and solves the fixed point again."""

    def __init__(self, system):
        self._system = system
        self.updated_cells = 0
        self.extra_cells = 0

    def __call__(self, cells, alpha=None):
        stats = self._system.resolve()
        self.updated_cells = int(stats.cells)
        return stats


class _IncrementalUpdate:
    """The update hook of an incremental frame (`FramePipeline.render(update_hook=...)`).

    The pipeline finds the visible cells and calls the hook once with them; it turns that call
    into the frame's localized refresh: the visible cells plus the surface cells near what
    changed (`near`), traced with the job's fixed rays (JOB_RAYS_FRAME; the pipeline's own `frame`
    seeds the direct light only), then a second update, with other rays, of the cells closest to
    the change (`inner`).
    """

    def __init__(self, system, near, inner, relit):
        self._system = system
        self._near = near
        self._inner = inner
        self._relit = relit
        self.updated_cells = 0
        self.extra_cells = 0

    def __call__(self, cells, alpha=None):
        system = self._system
        cells = np.union1d(np.asarray(cells, np.int64), self._near)
        stats = system.update(cells, JOB_RAYS_FRAME, alpha)
        self.updated_cells = int(cells.size)
        # After a light change every refreshed cell holds one set of rays' estimate; a second set
        # halves that noise (it is frozen in time, but visible as blotches on flat walls).
        extra = cells if self._relit else self._inner
        if extra.size:
            more = system.update(extra, JOB_RAYS_FRAME + 1, alpha)
            self.extra_cells = int(extra.size)
            stats.rays += more.rays
            stats.wall_ms += more.wall_ms
            for k, v in more.steps_ms.items():
                stats.steps_ms[k] = stats.steps_ms.get(k, 0.0) + v
        return stats


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
    """Write (h, w, c) float32 bottom-up pixels into a result pass (`name` as Blender 5.0 calls
    it), if the pass exists."""
    rp = layer.passes.get(compat.pass_name(name))
    if rp is None:
        return
    channels = rp.channels
    data = np.ascontiguousarray(pixels[..., :channels], np.float32)
    if data.shape[-1] < channels:
        pad = np.repeat(data[..., -1:], channels - data.shape[-1], axis=-1)
        data = np.concatenate([data, pad], axis=-1)
    rp.rect.foreach_set(data.ravel())


class _Result:
    """The engine's render result for the frame's `result_rect`: passes are given as whole-frame
    (h, w, c) bottom-up arrays and cut to the rectangle here."""

    def __init__(self, engine, render, width, height, layer: str = ""):
        self.engine = engine
        self.x, self.y, self.w, self.h = result_rect(render, width, height)
        # Blender's result is the rectangle itself: its coordinates start at the rectangle's corner.
        # Blender renders each view layer with its own depsgraph: the result holds that layer alone
        # (else layers[0], the first view layer, took every layer's image in turn).
        self.result = engine.begin_result(0, 0, self.w, self.h, layer=layer)
        self.layer = self.result.layers[0]

    def set(self, name, pixels):
        _set_pass(self.layer, name, pixels[self.y:self.y + self.h, self.x:self.x + self.w])

    def end(self):
        self.engine.end_result(self.result)


@dataclass
class _ShadowCatchers:
    """What composes a frame's shadow-catcher pixels (`catcher.py`): the system (its lamps' light
    without shadows), the world behind them, the camera."""

    system: object
    world: object
    view: np.ndarray
    proj: np.ndarray

    def apply(self, pipeline, combined, passes, transparent: bool) -> None:
        """Compose the catcher pixels of `combined` (h, w, 4) and zero their light `passes`
        (name -> (h, w, 3) arrays), in place, as Cycles does."""
        pixels = pipeline.catchers
        if pixels is None:
            return
        h, w = combined.shape[:2]
        film = pipeline.film
        light = (film.read("diffuse_direct") + film.read("diffuse_indirect"))[..., :3].reshape(-1, 3)[pixels.pix]
        ratio = catcher.light_ratio(self.system, pixels, light * np.float32(np.pi), DIRECT_SEED_FRAME)
        background = None
        if not transparent:
            rays = world_background.pixel_directions(self.view, self.proj, w, h)[pixels.pix]
            seen = getattr(self.world, "background_map", None)
            background = (seen.radiance(rays) if seen is not None
                          else np.broadcast_to(np.asarray(self.world.background_color, np.float32), (rays.shape[0], 3)))
        catcher.compose(combined, pixels.pix, ratio, background, transparent)
        for name in passes:
            passes[name].reshape(-1, passes[name].shape[-1])[pixels.pix] = 0.0


def _write_result(engine, depsgraph, pipeline, width, height, world, cache=None, levels=None, catchers=None):
    """Write the pipeline's filtered passes (`FramePipeline.film`) into the render result; with
    `cache`, Combined shows the Cache Cells debug view instead (each pixel coloured by the cell it
    reads; with `levels`, the system's finer cache levels, in each level's hue). catchers : the
    frame's `_ShadowCatchers` (their pixels are the pipeline's `catchers`), or None."""
    render = depsgraph.scene.render
    result = _Result(engine, render, width, height, depsgraph.view_layer.name)
    film = pipeline.film
    # A transparent film's background adds nothing to a pixel's colour: each subframe's colour
    # counts with its alpha (premultiplied, as Cycles writes it).
    combined = film.read("combined_premultiplied" if render.film_transparent else "combined").copy()
    light = {name: film.read(name).copy() for name in ("diffuse_direct", "diffuse_indirect", "glossy_direct",
                                                       "glossy_indirect")}
    if catchers is not None:
        catchers.apply(pipeline, combined, light, bool(render.film_transparent))
    if cache is not None:
        points, normals, pix = visible.pixels_to_points(pipeline.gbuffer.read("position"), pipeline.gbuffer.read("normal"))
        flat = combined.reshape(-1, 4)
        flat[:, :3] = 0.0
        flat[pix, :3] = visible.cell_debug_colors(cache, points, normals, levels=levels)
    if render.film_transparent:
        # Cycles' transparent film: premultiplied, the world lights the scene but is not seen.
        if cache is not None:
            combined[..., :3] *= combined[..., 3:4]
    else:
        combined[..., 3] = 1.0  # Cycles' alpha is 1 on the background unless the film is transparent
    depth = film.read("depth")
    holes = gbuffer.holdout_mask(depth[..., 0])
    if holes.any():
        # Holdouts: Cycles' Combined is 0 and its alpha the rest's coverage, transparent film or
        # not (the premultiplied colour, whose background adds nothing); their Depth the background's.
        if not render.film_transparent:
            combined[holes] = film.read("combined_premultiplied")[holes]
        depth = np.where(holes[..., None], np.float32(gbuffer.BACKGROUND_DEPTH), depth)
    exposure = film_exposure(depsgraph.scene)
    combined[..., :3] *= exposure
    result.set("Combined", combined)
    result.set("Diffuse Direct", light["diffuse_direct"] * exposure)
    result.set("Diffuse Indirect", light["diffuse_indirect"] * exposure)
    result.set("Diffuse Color", film.read("diffuse_color"))
    result.set("Ambient Occlusion", np.repeat(film.read("ao"), 3, axis=-1))
    result.set("Depth", depth)
    result.set("Normal", film.read("normal"))  # the average of the hits' normals, 0 on the background
    result.set("Glossy Direct", light["glossy_direct"] * exposure)
    result.set("Glossy Indirect", light["glossy_indirect"] * exposure)
    result.set("Glossy Color", film.read("glossy_color"))
    result.end()


def film_exposure(scene) -> np.float32:
    """Cycles' Film > Exposure (`scene.cycles.film_exposure`, a linear factor, 1 by default): Cycles
    scales its light passes (Combined, Diffuse/Glossy Direct and Indirect) by it; colour, AO,
    depth and normal passes stay (Cornell, 2: Diffuse Direct mean 0.384 -> 0.768)."""
    value = float(getattr(getattr(scene, "cycles", None), "film_exposure", 1.0))
    return np.float32(value if np.isfinite(value) and value >= 0.0 else 1.0)


def _write_background(engine, depsgraph, width, height, world, background_map=None, view=None, proj=None):
    """A frame without geometry: the world as the camera sees it (its map along each pixel
    centre's ray where it has one, else its colour), no light passes."""
    render = depsgraph.scene.render
    result = _Result(engine, render, width, height, depsgraph.view_layer.name)
    bg = np.zeros((height, width, 4), np.float32)
    if not render.film_transparent:
        exposure = film_exposure(depsgraph.scene)
        bg[...] = (*(np.asarray(world, np.float32) * exposure).tolist(), 1.0)
        if background_map is not None and view is not None:
            rays = world_background.pixel_directions(view, proj, width, height)
            bg[..., :3] = background_map.radiance(rays).reshape(height, width, 3) * exposure
    result.set("Combined", bg)
    for name in ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color", "Ambient Occlusion", "Normal", "Glossy Direct",
                 "Glossy Indirect", "Glossy Color"):
        result.set(name, np.zeros((height, width, 3), np.float32))
    result.set("Depth", np.full((height, width, 1), 1e10, np.float32))
    result.end()
