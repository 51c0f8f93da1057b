"""Real-time GI in the 3D viewport: the HYBRIDGI engine's `view_update` / `view_draw`, and the
session the Solid-mode GI overlay (`overlay.py`) shares.

Threads. The main thread (this module) turns the depsgraph updates `updates.py` classifies into
scene edits for the worker (`worker.py`; `sync.py` reads the snapshots, `viewport_mirror.py`
keeps the main thread's copy of the scene), rasterizes the G-buffer with the viewport's camera, reads back the
downsampled G-buffer when the camera or the geometry changed, uploads what the worker published,
runs the GPU passes and draws. The worker does every CPU step of a frame (visible cells, corner
visibility rays, direct light with shadow rays, cache updates) a frame or more behind, on numpy.

No black or flickering frames while navigating: the cache lives in world space, so a new camera
gathers it at once; the direct light the worker traced for an older camera is reprojected through
that camera and joint-bilateral upsampled (`DirectResolvePass`) until the new view's light
arrives; the exact corner-visibility mask is used only when it belongs to this very view (the
Chebyshev test of the depth moments stands in meanwhile).

Redraws: `view_draw` asks Blender for another redraw (`engine.tag_redraw()`) while the worker is
busy or has published something not drawn yet; an unchanged view with nothing new redraws the
last image without running the pipeline, or, until its anti-aliasing sum is complete, adds one
jittered subframe to it (`viewport_aa.py`: the final render's pixel filter over redraws).

Glossy light: the worker's (`ViewResult.glossy`, the lamps' GGX lobes and the cache's split sum
at the GI pixels, `hybridgi_core/glossy_image.py` as final renders compute it) is resolved onto
the frame's pixels like the direct light and added to Combined by the deferred pass.
"""

import logging
import os
import time
import weakref

import numpy as np

from hybridgi_core import cache as _cache
from hybridgi_core import errors
from hybridgi_core import glossy as _glossy_core
from hybridgi_core import grid as _grid
from hybridgi_core import pixel_gather as _pixel_gather
from hybridgi_core import settings as _settings
from hybridgi_core.raster import downsample as _downsample
from hybridgi_core.raster import frame as _frame
from hybridgi_core.raster import gather as _gather
from hybridgi_core.raster import passes as _passes
from hybridgi_core.raster import readback as _readback
from hybridgi_core.raster import settings as _raster_settings
from hybridgi_core.raster import subpixel as _subpixel

from . import material_bake, pipeline, sync, updates, viewport_aa, viewport_stats, worker, world_bake
from .pipeline import film_exposure
from .viewport_mirror import SceneMirror
from .viewport_passes import (
    PRESENT_CELLS,
    PRESENT_COLOR,
    DirectResolvePass,
    DirectSource,
    PackedGatherPass,
    PresentPass,
    draw_texture_fullscreen,
    software_renderer,
)
from .viewport_stats import GPU_STEPS, DrawStats, LiveStats, ViewCamera  # noqa: F401  (GPU_STEPS: the benchmark's)

log = logging.getLogger(__name__)


#: Full-res pixels per pixel of the direct light the worker refines while the view holds still
#: (the GI itself runs at the `downsample` setting; a moving view's first pass too). 1, as final
#: renders trace it: at 2, the upsampled shadow edges held most of the settled atrium's error vs
#: Cycles (Combined 0.034 at 2, 0.028 at 1; the final render's is 0.025).
DIRECT_FACTOR = 1
#: A moving view's coarse direct pass traces the rays of one pass at half the full resolution
#: (as when the direct light was refined there): 1 sample per GI pixel at the default downsample
#: 2, not the 4 a full-resolution pass's rays would give (~3x the first light's cost of a view).
COARSE_SHARE = 1.0 / (DIRECT_FACTOR * 2) ** 2
#: Full-resolution direct-light passes averaged while the view holds still (each as final
#: renders trace theirs: `WorkerOptions.fine_samples`).
DIRECT_PASSES = 2
#: props.debug_view of the cells view (drawn here, not by the deferred pass).
DEBUG_CELLS = "CELLS"

#: Scene name -> the latest `LiveStats` of a view of it, read by the sidebar panel.
LIVE_STATS: dict = {}
#: Every open session (engine viewports and overlays), for the redraw timer.
_OPEN = weakref.WeakSet()


def any_busy() -> bool:
    """Whether some open session still has something to show (the redraw timer asks)."""
    return any(session.needs_redraw() for session in list(_OPEN))


def drawn_cache(scene_name: str):
    """The `worker.CacheFrame` the last live view of this scene drew, or None."""
    for session in list(_OPEN):
        if session.scene_name == scene_name and session.gpu is not None and session.gpu.cache_frame is not None:
            return session.gpu.cache_frame
    return None


# --- settings ----------------------------------------------------------------------------------


def viewport_cache_settings(scene):
    """The scene's cache settings with the worker's pool on every core (at most the scene's
    render threads). The main thread only waits on the GPU between redraws, so leaving it a core
    left half of a 2-core machine idle while the worker traced (embreex releases the GIL)."""
    settings = scene.hybridgi.cache_settings(scene)
    cores = os.cpu_count() or 2
    return settings.with_(threads=max(1, min(settings.threads, cores)))


def debug_view_of(props) -> tuple[int, int]:
    """(deferred debug view, present mode) of the panel's debug view."""
    name = getattr(props, "debug_view", "FINAL")
    if name == DEBUG_CELLS:
        return _raster_settings.DEBUG_FINAL, PRESENT_CELLS
    numbers = {"FINAL": 0, "INDIRECT": 1, "AO": 2, "AO_SPLIT": 3}
    return numbers.get(name, 0), PRESENT_COLOR


# --- one live view -------------------------------------------------------------------------------


class _GPUState:
    """Everything of a session that lives on the GPU (main thread only)."""

    def __init__(self, raster_settings):
        self.pipeline = _frame.FramePipeline(raster_settings, gather=PackedGatherPass())
        # (1: the G-buffer's own targets are read back, no copy pass.)
        factor = DIRECT_FACTOR if DIRECT_FACTOR not in (1, raster_settings.downsample) else None
        self.direct_down = _downsample.DownsamplePass(factor) if factor else None
        self.resolve_full = DirectResolvePass("RGBA32F")
        self.resolve_low = DirectResolvePass("RGBA16F")
        self.resolve_glossy = DirectResolvePass("RGBA32F")
        self.present = PresentPass()
        self.source = None  # DirectSource of the last ViewResult uploaded
        self.glossy_source = None  # its glossy light (DirectSource), None without glossy layers
        self.cells_source = None  # its Cache Cells colours, when drawn
        self.mask_tx = None
        self.mask_serial = None
        self.pixel_tx = None  # (indirect, direct, SSAO) textures of the worker's pixel rays
        self.pixel_serial = None
        self.pixel_shape = None  # their (h, w)
        self.cache_frame = None  # the CacheFrame on the GPU
        self.width = self.height = 0

    def resize(self, width: int, height: int) -> None:
        if (width, height) == (self.width, self.height):
            return
        self.pipeline.resize(width, height)
        low = _passes.low_res_size(width, height, self.pipeline.settings.downsample)
        if self.direct_down is not None:
            self.direct_down.resize(width, height)
        self.resolve_full.resize(width, height)
        self.resolve_low.resize(*low)
        self.resolve_glossy.resize(width, height)
        self.present.resize(width, height)
        self.width, self.height = width, height

    def free(self) -> None:
        for p in (self.pipeline, self.resolve_full, self.resolve_low, self.resolve_glossy, self.present):
            p.free()
        if self.direct_down is not None:
            self.direct_down.free()
        self.source = self.cells_source = self.mask_tx = self.cache_frame = self.pixel_tx = None
        self.glossy_source = None


class ViewportSession:
    """One live view of a scene: the main-thread half here, the CPU half in a `ViewportWorker`.

    `sync(depsgraph, scene)` after depsgraph updates (view_update, or a depsgraph handler for the
    overlay); `draw(scene, camera, width, height)` on every redraw; `close()` at the end.
    """

    def __init__(self, options: worker.WorkerOptions | None = None, antialias: bool = True):
        """antialias : accumulate jittered subframes while the view holds still (`viewport_aa`);
        the Solid-mode overlay does not (it multiplies the last redraw's passes over Blender's
        own, unjittered image)."""
        self.antialias = antialias
        self.options = options or worker.WorkerOptions(direct_passes=DIRECT_PASSES, coarse_share=COARSE_SHARE)
        self.mirror = SceneMirror()
        self.worker: worker.ViewportWorker | None = None
        self.gpu: _GPUState | None = None
        self.last_stats = DrawStats()
        self.last_edit_gen = 0
        self._raster = None
        self._glossy_samples = 0  # the scene's Glossy Samples: the still view's final glossy light
        self._posted_key = None
        self._drawn_key = None
        self._drawn_serials = None
        self.scene_name = None
        self.settings_error: str | None = None  # the scene's settings are invalid: this message
        self._world_bakes_seen = world_bake.STORE.completed
        self._material_bakes_seen = material_bake.STORE.completed
        self.aa = viewport_aa.Accumulation()
        self._aa_source = None  # (pixel samples, filter size, filter type, lens) of self.aa
        #: Add anti-aliasing subframes while the worker is still busy (hardware GPUs); a software
        #: renderer waits for it to be idle (`viewport_aa`). None: decided on the first draw.
        self.aa_while_busy: bool | None = None
        _OPEN.add(self)

    # --- scene ----------------------------------------------------------------------------------

    def sync(self, depsgraph, scene) -> None:
        """Bring the worker's scene up to `depsgraph`: the first call snapshots everything, later
        calls read `depsgraph.updates` and send only what changed."""
        self.scene_name = scene.name
        settings = self._read_settings(scene)
        if settings is None and (self.worker is None or not self.worker.alive):
            return
        if self.worker is None or not self.worker.alive:
            # A first sync, or a fresh start after the worker failed: it knows no scene, no view.
            self.worker = worker.ViewportWorker(settings, self.options)
            self.mirror = SceneMirror()
            self._posted_key = self._drawn_key = None
        elif settings is not None:
            self.worker.set_settings(settings)
        if self.mirror.snapshot is None:
            self._post(self.mirror.full_sync(depsgraph))
            return
        changes = updates.classify_updates(depsgraph, self.mirror.structure)
        self.apply_changes(depsgraph, changes)

    def _read_settings(self, scene):
        """The scene's cache settings, or None while one is invalid: a setting out of range (a NaN
        typed in a field) is said on every redraw (`settings_error`), and the worker keeps in step
        with the scene under the settings it has until it is fixed."""
        try:
            settings = viewport_cache_settings(scene)
        except errors.HybridGIError as err:
            if self.settings_error != str(err):
                log.error("HybridGI viewport: %s", err)
            self.settings_error = str(err)
            return None
        self.settings_error = None
        return settings

    def refresh_settings(self, scene) -> None:
        """Hand the worker the scene's cache settings if they changed since the last sync. A
        Python-defined property set from a script tags no depsgraph update, so no view_update
        follows it (nor does any edit of one in the bpy module): each redraw reads them, as
        Cycles re-reads its own settings in its draw."""
        if self.worker is None or not self.worker.alive:
            return
        settings = self._read_settings(scene)
        if settings is not None:
            self.worker.set_settings(settings)

    def apply_changes(self, depsgraph, changes: updates.DepsgraphUpdates) -> None:
        mirror = self.mirror
        edits = []
        if not changes.full:
            for name, matrix in changes.moved.items():
                edit = mirror.move(name, matrix, changes.moved_ids.get(name))
                if edit is None:
                    changes.full = True
                    break
                if edit:
                    edits.append(edit)
        if changes.full:
            self._post(mirror.full_sync(depsgraph))
            return
        for edit in edits:
            self._post(edit)
        if changes.lights or changes.world or changes.materials:
            # An environment map's sun is a lamp too: a world edit reads the lamps again.
            lights = world = None
            if changes.lights or changes.world:
                lights, world = sync.scene_shading(depsgraph, wait_for_world=False)
            self._post(mirror.set_shading(
                lights=lights,
                world=world if changes.world else None,
                materials=sync.scene_materials(mirror.snapshot, changes.material_names) if changes.materials else None,
            ))

    def _post(self, edit) -> None:
        self.last_edit_gen = self.worker.post_edit(edit)

    # --- drawing --------------------------------------------------------------------------------

    def draw(self, scene, camera: ViewCamera, width: int, height: int, opaque: bool = True):
        """Run the frame's GPU half for `camera` at width x height; returns the texture to show
        (RGBA16F, scene linear) or None before the first sync. Raises HybridGIError when the
        worker failed."""
        if self.worker is None or self.mirror.snapshot is None:
            return None
        stats = DrawStats()
        t0 = time.perf_counter()
        published = self.worker.latest()
        if published.error is not None:
            raise errors.HybridGIError(f"viewport GI stopped: {published.error}")
        self.refresh_settings(scene)
        props = scene.hybridgi
        debug_view, present_mode = debug_view_of(props)
        # Cycles' Film > Exposure scales what the viewport shows, as final renders' light passes.
        exposure = float(film_exposure(scene))
        with stats.step("settings"):
            gpu_state = self._ensure_gpu(props, published, width, height)
            aa = self._aa_pattern(scene, present_mode, camera.lens)
        serials = (
            None if published.cache is None else published.cache.serial,
            None if published.view is None else published.view.serial,
        )
        key = (camera.key, width, height, self.mirror.geometry_gen, debug_view, present_mode, opaque,
               self._raster, published.empty, aa.config, self._aa_source, exposure)
        if key == self._drawn_key and serials == self._drawn_serials and self.mirror.gpu_dirty is None:
            if self._aa_due(published):
                return self._draw_subframe(gpu_state, stats, t0)
            stats.total_ms = (time.perf_counter() - t0) * 1e3
            self.last_stats = stats
            return gpu_state.present.output
        stats.redrawn = True
        pipeline = gpu_state.pipeline
        with stats.step("upload_geometry"):
            self._upload_geometry(pipeline)
        view = camera.view.astype(np.float32)
        proj = camera.proj.astype(np.float32)
        gbuf, low = pipeline.rasterize(view, proj, stats)
        debug_cells = present_mode == PRESENT_CELLS
        # (The subframes' pattern too: the worker traces its light edges for each of them.)
        view_key = (camera.key, width, height, self.mirror.geometry_gen, self._raster.downsample, debug_cells,
                    self._raster.pixel_full_res, aa.config)
        if view_key != self._posted_key and not published.empty:
            self._post_view(gpu_state, gbuf, camera, view_key, stats, debug_cells)
        with stats.step("upload_results"):
            source, mask = self._upload_results(gpu_state, published, view_key)
        stats.view_current = published.view is not None and published.view.key == view_key
        with stats.step("resolve"):
            direct = gpu_state.resolve_full.execute(gbuf.position, gbuf.normal, source)
            lit = gpu_state.resolve_low.execute(low.position, low.normal, source)
        world = self.mirror.snapshot.world.background_color
        pipeline.set_world(self.mirror.snapshot.world)  # its map uploaded once per world edit
        with stats.step("resolve"):
            self._resolve_pending(gpu_state, published, view_key)
        with stats.step("upload_results"):
            gi = self._pixel_textures(gpu_state, published, view_key)
        gi_low, gi_bilateral = low, None
        if gi is not None and gpu_state.pixel_shape != (low.height, low.width):
            with stats.step("resolve"):  # full-res GI (`ViewRequest.full_res`): its guide, a copy of this G-buffer
                gi_low, gi_bilateral = pipeline.full_res_guide(gbuf)
        with stats.step("resolve"):
            glossy = None
            if gpu_state.glossy_source is not None:
                glossy = gpu_state.resolve_glossy.execute(gbuf.position, gbuf.normal, gpu_state.glossy_source)
        shaded = pipeline.shade(gbuf, gi_low, view, proj, direct, corner_visible=mask, irradiance=lit,
                                debug_view=debug_view, world_color=world, stats=stats, gi=gi, glossy=glossy,
                                bilateral=gi_bilateral)
        if not debug_cells and aa.offsets.shape[0]:
            # The sum starts from this centre image with the first subframe (its targets hold it
            # until then): a redraw the worker's next result replaces costs no accumulate pass.
            aa.start(dict(view=view, proj=proj, mask=mask, lit=lit, gi=gi, world=world, debug_view=debug_view,
                          present_mode=present_mode, opaque=opaque, shaded=shaded, gbuf=gbuf, exposure=exposure,
                          gi_low=gi_low if gi_bilateral is not None else None, bilateral=gi_bilateral))
        else:
            aa.reset()
        with stats.step("present"):
            cells = None
            if debug_cells:
                result = published.view
                if result is not None and result.cells is not None:
                    if gpu_state.cells_source is None or gpu_state.cells_source.serial != result.serial:
                        gpu_state.cells_source = DirectSource.cells_of(result)
                    # The direct light's resolve is done with its target: reuse it for the colours.
                    cells = gpu_state.resolve_full.execute(gbuf.position, gbuf.normal, gpu_state.cells_source,
                                                           nearest=True)
            out = gpu_state.present.execute(shaded.combined, gbuf, present_mode, opaque, cells, scale=exposure,
                                            taps=None if debug_cells else self._present_filter(1))
        self._drawn_key, self._drawn_serials = key, serials
        stats.total_ms = (time.perf_counter() - t0) * 1e3
        self.last_stats = stats
        LIVE_STATS[scene.name] = LiveStats(stats, published.stats, published.error)
        return out

    # --- anti-aliasing (`viewport_aa`) -------------------------------------------------------------

    def _aa_pattern(self, scene, present_mode: int, lens=None) -> viewport_aa.Accumulation:
        """The session's `Accumulation`, remade when the scene's pixel samples, filter or the lens
        looked through (`ViewCamera.lens`) changed; none in the Cache Cells view (a cell colour per
        pixel centre, as final renders draw it)."""
        count = int(getattr(scene.hybridgi, "pixel_samples", 1))
        if present_mode == PRESENT_CELLS or not self.antialias:
            count = 1
        filter_type, filter_size = pipeline.pixel_filter(scene)
        if (count, filter_size, filter_type, lens) != self._aa_source:
            self.aa = viewport_aa.Accumulation.pattern(count, filter_size, filter_type, lens)
            self._aa_source = (count, filter_size, filter_type, lens)
        return self.aa

    def _present_filter(self, samples: int):
        """The pixel filter the view shows an image of `samples` samples per pixel through, as final
        renders' film filters theirs (`subpixel.reconstruction_taps`)."""
        _count, filter_size, filter_type, _lens = self._aa_source
        return _subpixel.reconstruction_taps(samples, filter_size, filter_type)

    def _aa_due(self, published) -> bool:
        """A jittered subframe is to be drawn now: the sum is not complete, and the worker is idle
        unless subframes may run while it is busy. Idle now (`worker.idle`: a view or edit posted
        since is work), not only in its last record: the idle record a worker publishes before its
        first view let llvmpipe's subframes take the cores the first view's light needed."""
        if not self.aa.pending:
            return False
        if self.aa_while_busy is None:
            self.aa_while_busy = not software_renderer()
        if self.aa_while_busy:
            return True
        return bool(published.stats.idle and self.worker is not None and self.worker.idle)

    def _draw_subframe(self, gpu_state: _GPUState, stats: DrawStats, t0: float):
        """Add the next jittered subframe to the running sum and show the mean: the centre redraw's
        light, GI and glossy textures, resolved at the subframe's G-buffer."""
        aa, inputs, pipeline_ = self.aa, self.aa.inputs, gpu_state.pipeline
        stats.redrawn = True
        stats.subframe = aa.drawn
        view, proj = inputs["view"], inputs["proj"]
        if aa.drawn == 1:
            with stats.step("accumulate"):  # the centre image, still in the targets
                pipeline_.accumulate.execute(inputs["shaded"], inputs["gbuf"], first=True)
        with stats.step("gbuffer"):
            view, jittered = aa.next_camera(view, proj, gpu_state.width, gpu_state.height)
            gbuf = pipeline_.gbuffer.execute(view, jittered, texture_filter=aa.texture_filter)
        # Still the centre's (the GI's guide, as final renders keep it): the downsampled G-buffer,
        # or the full-res GI's copy of the centre's.
        low = inputs["gi_low"] if inputs.get("gi_low") is not None else pipeline_.downsample.outputs()
        with stats.step("resolve"):
            source = gpu_state.source
            direct = gpu_state.resolve_full.execute(gbuf.position, gbuf.normal, source,
                                                    subframe=source.edge_subframe(aa.drawn - 1, aa.offsets))
            glossy = None
            if gpu_state.glossy_source is not None:
                glossy = gpu_state.resolve_glossy.execute(gbuf.position, gbuf.normal, gpu_state.glossy_source)
        shaded = pipeline_.shade(gbuf, low, view, proj, direct, corner_visible=inputs["mask"],
                                 irradiance=inputs["lit"], debug_view=inputs["debug_view"],
                                 world_color=inputs["world"], stats=stats, gi=inputs["gi"], glossy=glossy,
                                 bilateral=inputs.get("bilateral"), camera_proj=jittered)
        with stats.step("accumulate"):
            pipeline_.accumulate.execute(shaded, gbuf, first=False)
        aa.drawn += 1
        with stats.step("present"):
            out = gpu_state.present.execute(pipeline_.accumulate.texture("combined"), gbuf, inputs["present_mode"],
                                            inputs["opaque"], None,
                                            scale=inputs["exposure"] / pipeline_.accumulate.count,
                                            taps=self._present_filter(pipeline_.accumulate.count))
        stats.total_ms = (time.perf_counter() - t0) * 1e3
        self.last_stats = stats
        return out

    def poll_world(self, depsgraph) -> None:
        """Read the world again once a map it waited for has baked (`world_bake` runs it in the
        background: the view showed the world's uniform colour meanwhile); the materials, once
        a colour input's texture has (`material_bake`)."""
        if self.mirror.snapshot is None or self.worker is None:
            return
        if world_bake.STORE.completed != self._world_bakes_seen:
            self._world_bakes_seen = world_bake.STORE.completed
            lights, world = sync.scene_shading(depsgraph, wait_for_world=False)
            self._post(self.mirror.set_shading(lights=lights, world=world))
        if material_bake.STORE.completed != self._material_bakes_seen:
            # Colour inputs baked in the background (`material_bake`): read the materials again.
            self._material_bakes_seen = material_bake.STORE.completed
            self._post(self.mirror.set_shading(materials=sync.scene_materials(self.mirror.snapshot)))

    def needs_redraw(self) -> bool:
        """More to show: the worker is busy or published something not drawn yet. Busy by its
        inbox too (`worker.idle`): right after an edit or a new view its last record still says
        idle, and a draw that asked for no redraw then left the old image up until the redraw
        timer's next idle check (`overlay.POLL_IDLE_S`)."""
        if self.worker is None:
            return False
        if world_bake.pending() or material_bake.pending():
            return True
        published = self.worker.latest()
        if published.error is not None:
            return False
        serials = (
            None if published.cache is None else published.cache.serial,
            None if published.view is None else published.view.serial,
        )
        return (not published.stats.idle or not self.worker.idle or serials != self._drawn_serials
                or self.mirror.gpu_dirty is not None or self._aa_due(published))

    def _ensure_gpu(self, props, published, width: int, height: int) -> _GPUState:
        cell = published.cache.grid.cell_size if published.cache is not None else None
        raster = props.raster_settings(cell_size=cell)
        self._glossy_samples = int(getattr(props, "glossy_samples", 0))
        if self.gpu is not None and raster != self._raster and not self.gpu.pipeline.set_settings(raster):
            self.gpu.free()
            self.gpu = None
        if self.gpu is None:
            self.gpu = _GPUState(raster)
            self.mirror.gpu_dirty = "full"
            self._posted_key = None
        self._raster = raster
        self.gpu.resize(width, height)
        return self.gpu

    def _upload_geometry(self, pipeline) -> None:
        dirty = self.mirror.gpu_dirty
        if dirty == "full":
            pipeline.upload(self.mirror.gpu_snapshot())
        elif dirty == "positions":
            pipeline.gbuffer.update_positions(self.mirror.gpu_positions)
        self.mirror.gpu_dirty = None

    def _post_view(self, gpu_state: _GPUState, gbuf, camera: ViewCamera, view_key, stats: DrawStats,
                   debug_cells: bool = False) -> None:
        """Read back the low-res G-buffer(s) and hand them to the worker (copies: the passes
        reuse their read-back arrays)."""
        with stats.step("readback"):
            normal, position = gpu_state.pipeline.downsample.read_normal_position()
            if gpu_state.direct_down is not None:
                gpu_state.direct_down.execute(gbuf)
                d_normal, d_position = (a.copy() for a in gpu_state.direct_down.read_normal_position())
            elif DIRECT_FACTOR == 1 and gpu_state.pipeline.settings.downsample != 1:
                # New arrays (no copies to make): the full-res targets as a factor-1 downsample
                # would copy them (one sample per block), without its fullscreen pass.
                d_normal = gpu_state.pipeline.gbuffer.read("normal")
                d_position = gpu_state.pipeline.gbuffer.read("position")
            else:
                d_normal, d_position = normal.copy(), position.copy()
            # The pixel rays' GI resolved at every full-res pixel, as final renders do (`full_res_images`).
            full_res = (d_position.shape[:2] != position.shape[:2] and d_position.shape[:2] == (gbuf.height, gbuf.width)
                        and gpu_state.pipeline.settings.pixel_full_res)
            material = full_material = full_albedo = full_tint = direct_material = None
            materials = self.mirror.snapshot.materials
            if any(getattr(m, "translucent", None) is not None for m in materials):
                # The translucent shares of the coarse and the direct light's pixels (`worker._shares`).
                material = gpu_state.pipeline.downsample.read("material")[..., 0]
                if d_position.shape[:2] == (gbuf.height, gbuf.width):
                    direct_material = gpu_state.pipeline.gbuffer.read("material")[..., 0]
                elif gpu_state.direct_down is not None:
                    direct_material = gpu_state.direct_down.read("material")[..., 0]
                else:
                    direct_material = material
            if any(getattr(m, "specular", None) is not None for m in materials):
                # At the GI pixels (the glossy light's): a new array, the worker keeps it.
                if material is None:
                    material = gpu_state.pipeline.downsample.read("material")[..., 0]
                if d_position.shape[:2] == (gbuf.height, gbuf.width) and self._glossy_samples > 0:
                    # And at every pixel, for the final render's glossy light of a still view
                    # (`worker.ViewportWorker._fine_glossy`).
                    full_material = gpu_state.pipeline.gbuffer.read("material")[..., 0]
                    full_albedo = gpu_state.pipeline.gbuffer.read("albedo")
                    if any(_glossy_core.is_textured_metal(m) for m in materials):
                        full_tint = gpu_state.pipeline.gbuffer.read("emission")[..., 3]
        with stats.step("post"):
            request = worker.ViewRequest(
                key=view_key, position=position.copy(), normal=normal.copy(),
                direct_position=d_position, direct_normal=d_normal,
                view=camera.view, proj=camera.proj, debug_cells=debug_cells, material=material,
                full_res=bool(full_res), full_material=full_material, full_albedo=full_albedo, full_tint=full_tint,
                direct_material=direct_material,
                glossy_samples=self._glossy_samples if full_material is not None else 0,
                reflection_rays=gpu_state.pipeline.settings.reflection_rays,
                aa_offsets=self.aa.offsets.copy() if self.aa.offsets.shape[0] else None,  # (none in Cache Cells)
            )
            self.worker.post_view(request)
        self._posted_key = view_key
        stats.posted_view = True

    def _pixel_textures(self, gpu_state: _GPUState, published, view_key):
        """The worker's per-pixel final gather of this very view as the (indirect, direct, SSAO)
        textures `FramePipeline.shade` takes in place of the gather and the screen-space pass
        (final renders' `_pixel_gi`), uploaded once per serial; None when it has none (a moving
        or new view, a cache still converging): the cache gather stands in."""
        result = published.view
        if result is None or result.key != view_key:
            return None
        if result.gi_indirect is None:
            # A pass the worker has not resolved yet: `_resolve_pending` uploaded the draw's own.
            pending = result.gi_pending
            if pending is None or gpu_state.pixel_serial != ("pending", pending.serial):
                return None
            return gpu_state.pixel_tx
        if gpu_state.pixel_serial != result.serial:
            _upload_pixels(gpu_state, result.serial, result.gi_indirect, result.gi_direct)
        return gpu_state.pixel_tx

    def _resolve_pending(self, gpu_state: _GPUState, published, view_key) -> None:
        """The GI textures of the view's pixel pass whose rays the worker published before
        resolving them (`worker.PendingGI`): resolved once, here, by the GPU's passes."""
        result = published.view
        if result is None or result.key != view_key or result.gi_indirect is not None or result.gi_pending is None:
            return
        pending = result.gi_pending
        if gpu_state.pixel_serial != ("pending", pending.serial):
            _upload_pixels(gpu_state, ("pending", pending.serial), *_pending_images(gpu_state.pipeline, pending))

    def _upload_results(self, gpu_state: _GPUState, published, view_key):
        """Cache textures and the view's light, each uploaded once per published serial."""
        if published.cache is not None and published.cache is not gpu_state.cache_frame:
            gpu_state.pipeline.gather.upload(published.cache)
            gpu_state.cache_frame = published.cache
        elif published.cache is None and gpu_state.cache_frame is None:
            gpu_state.pipeline.gather.upload(_empty_cache_frame())
            gpu_state.cache_frame = None
        result = published.view
        if result is None:
            if gpu_state.source is None or gpu_state.source.serial != -1:
                gpu_state.source = DirectSource.empty()
        elif gpu_state.source is None or gpu_state.source.serial != result.serial:
            gpu_state.source = DirectSource.upload(result)
        if result is None or result.glossy is None:
            gpu_state.glossy_source = None
        elif gpu_state.glossy_source is None or gpu_state.glossy_source.serial != result.serial:
            gpu_state.glossy_source = DirectSource.glossy_of(result, gpu_state.source)
        mask = None
        if result is not None and result.corner_mask is not None and result.key == view_key:
            if gpu_state.mask_serial != result.serial:
                gpu_state.mask_tx = _readback.upload_texture_2d(result.corner_mask, "R32F")
                gpu_state.mask_serial = result.serial
            mask = gpu_state.mask_tx
        return gpu_state.source, mask

    # --- lifetime -------------------------------------------------------------------------------

    def close(self) -> None:
        if self.worker is not None:
            self.worker.close()
            self.worker = None
        if self.gpu is not None:
            self.gpu.free()
            self.gpu = None


def _upload_pixels(gpu_state: _GPUState, serial, indirect: np.ndarray, direct: np.ndarray) -> None:
    """The (indirect, direct, SSAO) textures `FramePipeline.shade` takes of pixel-ray GI images."""
    neutral = np.zeros(indirect.shape, np.float32)
    neutral[..., 3] = 1.0  # no occlusion, no near-field bounce: the rays saw the near field
    gpu_state.pixel_tx = (_readback.upload_texture_2d(indirect, "RGBA32F"),
                          _readback.upload_texture_2d(direct, "RGBA32F"),
                          _readback.upload_texture_2d(neutral, "RGBA16F"))
    gpu_state.pixel_serial = serial
    gpu_state.pixel_shape = indirect.shape[:2]


def _pending_images(pipeline, pending: worker.PendingGI) -> tuple[np.ndarray, np.ndarray]:
    """(indirect, direct) full-res GI images of a pixel pass the worker has not resolved yet
    (`worker.PendingGI`), resolved here by the GPU's filter and interpolation passes as final
    renders resolve theirs (`pixel_gather.full_res_preview`: without the detail pixels, which the
    worker's own resolve adds)."""
    (h, w), (full_points, full_normals, full_pix) = pending.full_shape, pending.full
    return _pixel_gather.full_res_preview(
        pending.gi, pending.position_lo, pending.pix, pending.points, pending.normals, pending.view, full_points,
        full_normals, full_pix, (w, h), pending.passes, pending.plane_sigma, pending.normal_power,
        filter=pipeline.atrous, upsample=pipeline.upsample)


_EMPTY = {}


def _empty_cache_frame() -> worker.CacheFrame:
    """A one-cell cache with nothing valid: what the gather reads before the worker's first frame."""
    frame = _EMPTY.get("frame")
    if frame is None:
        settings = _settings.CacheSettings(resolution=1)
        cache = _cache.IrradianceCache(_grid.CacheGrid.from_bounds(np.zeros(3), np.ones(3), 1), settings)
        sh_tex, depth_tex = _gather.pack_cache(cache)
        frame = _EMPTY["frame"] = worker.CacheFrame(0, cache.grid, settings, sh_tex, depth_tex)
    return frame


# --- the engine's callbacks ----------------------------------------------------------------------


def view_update(engine, context, depsgraph) -> None:
    """HybridGIRenderEngine.view_update: sync what changed to the engine's viewport session."""
    session = getattr(engine, "viewport", None)
    if session is None:
        session = engine.viewport = ViewportSession()
    session.sync(depsgraph, depsgraph.scene)
    engine.tag_redraw()


def view_draw(engine, context, depsgraph) -> None:
    """HybridGIRenderEngine.view_draw: draw the live GI image with Blender's display transform."""
    import gpu  # noqa: PLC0415

    t0 = time.perf_counter()
    session = getattr(engine, "viewport", None)
    if session is None:
        # Blender calls view_update first; a draw without it (tests, a reset) syncs here.
        view_update(engine, context, depsgraph)
        session = engine.viewport
    scene = depsgraph.scene
    region = context.region
    pixel_size = max(int(engine.get_preview_pixel_size(scene)), 1)
    width, height = max(region.width // pixel_size, 1), max(region.height // pixel_size, 1)
    # Through the scene camera, its depth of field too (its lens points in the subframes).
    through = getattr(context.region_data, "view_perspective", "") == "CAMERA"
    camera = ViewCamera.from_region_data(context.region_data, pipeline.camera_lens(depsgraph, scene) if through else None)
    session.poll_world(depsgraph)
    try:
        texture = session.draw(scene, camera, width, height, opaque=not scene.render.film_transparent)
    except errors.HybridGIError as err:
        log.error("HybridGI viewport: %s", err)
        engine.update_stats("HybridGI", f"Error: {err}")
        return
    if texture is None:
        engine.update_stats("HybridGI", status_line(session))
        return
    with session.last_stats.step("display"):
        gpu.state.blend_set("ALPHA_PREMULT" if scene.render.film_transparent else "NONE")
        engine.bind_display_space_shader(scene)
        draw_texture_fullscreen(texture)
        engine.unbind_display_space_shader()
        gpu.state.blend_set("NONE")
    with session.last_stats.step("status"):
        if session.needs_redraw():
            engine.tag_redraw()
        engine.update_stats("HybridGI", status_line(session))
    session.last_stats.total_ms = (time.perf_counter() - t0) * 1e3


def status_line(session: ViewportSession) -> str:
    if session.settings_error is not None:
        return f"Error: {session.settings_error}"
    return viewport_stats.status_line(session.worker.latest() if session.worker is not None else None)


def free(engine) -> None:
    """Stop the engine's worker (RenderEngine.__del__)."""
    session = getattr(engine, "viewport", None)
    if session is not None:
        session.close()
        engine.viewport = None
