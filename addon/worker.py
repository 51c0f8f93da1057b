"""The viewport's CPU half on a background thread: cache updates, visible cells, corner visibility,
direct light and the glossy layers' light at the pixels, all on numpy snapshots.

The main thread posts scene edits (applied in order) and view requests (the latest wins) and reads
what the worker published: one immutable `Published` record, swapped under a lock, holding
version-stamped copies (the packed cache textures, the view's direct light and visibility mask).
The worker alone owns its `GISession`: it builds, syncs, updates and closes it; the main thread
never calls into it, so closing the viewport while a rebuild runs is safe.

This module imports nothing from bpy, gpu or mathutils (a test imports it with them blocked): a
Blender object deleted while the worker traces cannot be reached from here.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import threading
import time
from collections.abc import Callable
from concurrent import futures
from types import MappingProxyType

import numpy as np

from hybridgi_core import errors
from hybridgi_core import gi_carry as _gi_carry
from hybridgi_core import glossy_image as _glossy
from hybridgi_core import glossy_ltc as _glossy_ltc
from hybridgi_core import glossy_noise as _glossy_noise
from hybridgi_core import lights as _lights
from hybridgi_core import penumbra as _penumbra
from hybridgi_core import pixel_gather as _pixel_gather
from hybridgi_core import translucent as _translucent
from hybridgi_core import visible as _visible
from hybridgi_core.camera import camera_position
from hybridgi_core.raster import gather as _gather_layout
from hybridgi_core.raster import settings as _raster_settings
from hybridgi_core.raster import subpixel as _subpixel
from hybridgi_core.raster.gbuffer import camera_eye
from hybridgi_core.rendering import rendering
from hybridgi_core.rows import rows_above
from hybridgi_core.session import GISession

from . import worker_pixels as _pixels

# The records exchanged with the main thread, importable from here as the worker's own API.
from .worker_messages import (  # noqa: F401
    CacheFrame,
    EdgeLight,
    FullScene,
    MoveVertices,
    PendingGI,
    Published,
    SetShading,
    ViewRequest,
    ViewResult,
    WorkerOptions,
    WorkerStats,
    frozen,
)
from .worker_solve import SolveSchedule
from .worker_view import DirectLevel, GlossyLevel, ViewState

log = logging.getLogger(__name__)


#: The least relative step of the lamps' light between neighbours on different surfaces that
#: makes their pixels edges of a still view's subframes (`_edge_pass`; a light edge alone takes
#: `subpixel.LIGHT_EDGE_CONTRAST`).
SURFACE_EDGE_CONTRAST = 0.05
#: Seconds over which updates and rays per second are counted.
RATE_WINDOW_S = 1.0
#: Points per chunk of the corner-visibility rays (8 rays each): between chunks the worker looks
#: for a newer view and drops a mask that would be stale before it is done. Two of
#: `system.VISIBILITY_BLOCK`: each chunk is split over both threads of a 2-core pool (4096 ran
#: on the worker thread alone).
MASK_CHUNK = 16384
#: Direct-light points per pool job of a direct pass (`_direct_split`), and the most jobs.
DIRECT_BLOCK_POINTS = 16384
MAX_DIRECT_BLOCKS = 64
#: Shortest time between two published caches while updates continue: packing costs the worker
#: and uploading costs the main thread about 1 ms per 3 MB of texture data, and a display shows
#: no more than about this rate anyway.
PUBLISH_INTERVAL_S = 1.0 / 30.0
#: The same while the solver iterates towards a fixed point: each published iteration adds a
#: bounce but costs a pack (~50-100 ms for a 48^3 grid here, a third of an iteration), so the
#: intermediate ones go out at this rate; a finished solve is always published at once.
SOLVE_PUBLISH_INTERVAL_S = 0.3
#: ... and at least this many times the last pack's time (with the glossy light read from it)
#: after the previous one or the event that began the solve: a re-solve's iterates cost it at
#: most a fifth (bunny_npm 640x360 after a lamp move, 2 busy cores: two iterates at 0.16-0.5 s a
#: pack and glossy read held the converged cache back by 0.5 s of a 0.45 s solve).
SOLVE_PUBLISH_PACKS = 4.0
#: A fresh cache's first solve publishes no intermediate iteration before this long after its
#: first batch: an iterate with a bounce or two is far darker than the fixed point (Cornell box:
#: Combined error 0.49 vs 0.04), and packing it (the depth moments and SH of every cell, 50-200 ms
#: on 2 busy cores) delayed the converged image that follows within ~0.5 s. A scene whose solve
#: takes longer still shows its iterations after this hold.
FIRST_SOLVE_HOLD_S = 1.5
#: While the solver still works, the glossy light's cache part is read again with a packed cache
#: at most this often (each reading: a corner lookup per glossy GI pixel, 0.1-0.25 s on 2 busy
#: cores for bunny_npm's 50k); the cache of a finished solve is always read.
GLOSSY_CACHE_INTERVAL_S = 1.0


# --- the worker ---------------------------------------------------------------------------------


class ViewportWorker:
    """A thread that owns one `GISession` and keeps it converged for the latest view."""

    def __init__(self, settings, options: WorkerOptions | None = None, name: str = "hybridgi-viewport"):
        self.options = options or WorkerOptions()
        self._cond = threading.Condition()
        # Inbox (guarded by _cond).
        self._edits: list = []
        self._edit_gen = 0
        self._view: ViewRequest | None = None
        self._settings = settings
        self._stop = False
        self._idle = False
        # Outbox (guarded by _cond; the record itself is immutable).
        self._published = Published()
        # Worker-thread state: touched by the worker thread only.
        self._session = None
        self._snapshot = None
        self._empty = False
        self._applied_gen = 0
        self._scene_version = 0  # bumped by every sync that changed something: stale view light
        #: The cache's convergence from stored hits, one unit of work per step (`worker_solve.py`).
        self._schedule = SolveSchedule(self.options.solver_batches, self.options.first_batch_rays)
        self._frame = 0
        self._serial = 0
        self._pending_serial = 0  # `PendingGI.serial`
        self._published_cache_key = None
        self._published_depth = None  # (key, depth texels) last packed: reused while it holds
        self._glossy_cache_due = False  # a packed cache's glossy light is to be read (`_publish`)
        self._published_at = 0.0
        self._pack_s = 0.0  # seconds of the last SH texture pack and the glossy light read with it
        self._view_state: ViewState | None = None
        self._rates: collections.deque = collections.deque()
        self._updates = 0
        self._view_ms = 0.0  # wall time of lighting a new view (moving average)
        self._steps: dict[str, float] = {}
        #: The thread a still view's pixel pass traces on (`worker_pixels.PixelPass.start`).
        self._pixel_thread: futures.ThreadPoolExecutor | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        _prefetch_glossy_tables()

    # --- main-thread API ------------------------------------------------------------------------

    def post_edit(self, edit) -> int:
        """Queue a scene edit; returns its generation (done when `stats.scene_gen` reaches it)."""
        with self._cond:
            self._edits.append(edit)
            self._edit_gen += 1
            self._idle = False
            self._cond.notify_all()
            return self._edit_gen

    def post_view(self, request: ViewRequest) -> None:
        """Replace the view to light (an older one not yet started is dropped)."""
        with self._cond:
            self._view = request
            self._idle = False
            self._cond.notify_all()

    def set_settings(self, settings) -> None:
        with self._cond:
            if settings != self._settings:
                self._settings = settings
                self._idle = False
                self._cond.notify_all()

    def latest(self) -> Published:
        with self._cond:
            return self._published

    @property
    def idle(self) -> bool:
        """Nothing left to do: every edit applied, the view lit and converged."""
        with self._cond:
            return self._idle and not self._edits

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def wait(self, predicate: Callable[[Published], bool], timeout: float) -> bool:
        """Block until predicate(latest()) holds, the worker failed or stopped, or timeout (False)."""
        with self._cond:
            done = self._cond.wait_for(
                lambda: predicate(self._published) or self._published.error is not None or self._stop, timeout)
            return bool(done) and predicate(self._published)

    def wait_idle(self, timeout: float) -> bool:
        """Block until the worker has nothing left to do (True) or timeout (False)."""
        with self._cond:
            return bool(self._cond.wait_for(
                lambda: (self._idle and not self._edits) or self._published.error is not None, timeout)) \
                and self._published.error is None

    def close(self, timeout: float = 10.0) -> None:
        """Stop the thread; it closes its session itself. A step in progress (a rebuild) is
        finished first: after `timeout` the daemon thread is left to end on its own."""
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if threading.current_thread() is not self._thread:
            self._thread.join(timeout)
            if self._thread.is_alive():
                log.warning("viewport worker still busy after %.1f s; it stops after its current step", timeout)

    # --- worker thread --------------------------------------------------------------------------

    def _run(self) -> None:
        with rendering():  # each pass's freed arrays serve the next; a short GIL switch interval
            self._loop()

    def _loop(self) -> None:
        try:
            while True:
                with self._cond:
                    while not self._stop and not self._edits and not self._has_work():
                        if not self._idle and not self._tracing():
                            self._idle = True
                            # Cheap: the last step packed the cache already (pack=False).
                            self._published = self._build_published(idle=True, pack=False)
                            self._cond.notify_all()
                        self._cond.wait()
                    if self._stop:
                        return
                    edits, self._edits = self._edits, []
                    edit_gen = self._edit_gen
                    view, settings = self._view, self._settings
                    self._idle = False
                self._step(edits, edit_gen, view, settings)
        except errors.HybridGIError as err:
            self._fail(str(err))
        except Exception as err:
            # The thread ends here: log the traceback and publish the message, which the main
            # thread reports (an exception cannot cross threads by itself).
            log.exception("viewport worker failed")
            self._fail(f"internal error: {type(err).__name__}: {err}")
        finally:
            self._drop_pixels()
            if self._pixel_thread is not None:
                self._pixel_thread.shutdown(wait=True)
            if self._session is not None:
                self._session.close()
                self._session = None

    def _has_work(self) -> bool:
        """Called by the worker under the lock (for the inbox): cheap checks only, no numpy work."""
        if self._settings != getattr(self._session, "settings", self._settings):
            return True
        if self._session is None or self._session.system is None:
            return False
        state = self._view_state
        if self._view is not None and (state is None or not state.current(self._view, self._scene_version)):
            return True
        if self._tracing():
            # The pass's rays hold both cores: the worker waits for them (`_pixel_pass`). A full-res
            # direct pass beside them took as long as after them (spheres 640x360: the pixel pass
            # and the direct pass 0.44 and 0.75 s together, 0.37 and 0.33 s in turn).
            return False
        if state is not None and (state.mask is None or state.passes < self.options.direct_passes):
            return True
        if state is not None and (self._glossy_due(state) or self._fine_glossy_due(state) or self._edges_due(state)):
            return True
        if state is not None and self._pixels_due(state):
            return True
        if state is not None and state.request.debug_cells:
            cache = self._session.system.cache
            if state.cells_key != (id(cache), cache.version):
                return True  # the Cache Cells colours lag behind the cache
        return self._view_state is not None and self._schedule.has_work

    def _step(self, edits: list, edit_gen: int, view: ViewRequest | None, settings) -> None:
        t0 = time.perf_counter()
        if self._session is None:
            self._session = GISession(settings)
        resync = settings != self._session.settings
        if resync:
            self._session.set_settings(settings)
        relit = None
        if edits or resync or (view is not None and self._view_state is not None
                               and view is not self._view_state.request):
            self._drop_pixels()  # its rays read the system the edits change, for a view that is gone
        if edits or resync:
            relit = self._apply(edits, resync)
        self._applied_gen = edit_gen
        self._steps["sync"] = (time.perf_counter() - t0) * 1e3
        system = self._session.system
        if system is None:
            self._publish()
            return
        schedule = self._schedule
        schedule.attach(system)
        state = self._view_state
        if relit is not None and state is not None and view is state.request:
            # Same view, same geometry: keep its cells and mask, light it again at once (new
            # diffuse colours leave the lamps' light as it was).
            t_view = time.perf_counter()
            state.relit(self._scene_version, lamps=relit == "lamps")
            if relit == "lamps":
                self._direct_pass(system, state, state.coarse)
            self._publish()
            self._steps["relit_view"] = (time.perf_counter() - t_view) * 1e3
        moving = view is not None and (state is None or not state.current(view, self._scene_version))
        if moving:
            t_view = time.perf_counter()
            self._begin_view(system, view)
            self._publish()  # the new view's light first: the main thread reprojects it meanwhile
            ms = (time.perf_counter() - t_view) * 1e3
            self._view_ms = ms if self._view_ms == 0 else 0.7 * self._view_ms + 0.3 * ms
            schedule.cover(self._view_state.cells)
        state = self._view_state
        finished = False
        # A converged cache refines (more batches) once the still view it lights is complete: its
        # direct passes, glossy light and pixel passes first. With pixel rays the cache carries
        # only the control variate and further bounces (Cornell 640x360 final render, 32 rays a
        # cell instead of 64: Combined 0.0218 -> 0.0219 vs Cycles), so the view's own light is
        # what the image waits for; the refined cache serves the views that follow.
        hold = (not moving and state is not None and schedule.refinable and self._view_refinement_due(state))
        # A still view's first full-resolution direct pass comes before the steps that refine a
        # solved cache (the rest of a re-shade, a resolve of new cells), not before the first
        # solve over the current hits: after a lamp edit the old cache's GI is the image's largest
        # error and the short first batch re-lights it in ~0.3 s, while the full-res pass only
        # sharpens the coarse pass's light (Cornell 640x360, vs a final render: 0.072 -> 0.071).
        hold = hold or (not moving and state is not None and state.mask is not None and state.passes == 0
                        and self.options.direct_passes > 0 and schedule.solved_once)
        if state is not None and schedule.has_work and not hold:
            was_solved = schedule.solved_once
            self._solve_step(schedule, state)
            finished = schedule.solved_once and not was_solved or not schedule.has_work
            if finished and not moving:
                # The converged cache goes out now, not after the refinement below; after a lamp
                # edit with the view's pixel passes carried over (`_carry`).
                if self._carry_due(state):
                    self._carry(system, state)
                elif state.pixel_pass is None and self._refinement(state) == "pixels":
                    # A pixel pass is the view's next refinement: its rays start first, so that packing
                    # the cache (0.05-0.09 s at 640x360 on the worker thread) runs beside them.
                    self._pixel_pass(system, state)
                self._publish(force=True)
                finished = False
        if state is not None and state.request.debug_cells:
            self._cell_colors(system, state, force=moving or not schedule.has_work)
        if state is not None and not moving:
            # Refinements of a view that held still for a whole step.
            self._refine(system, state, self._refinement(state))
        # A finished solve is published at once; iterations in between at SOLVE_PUBLISH_INTERVAL_S.
        self._publish(force=finished)

    # --- scene ----------------------------------------------------------------------------------

    def _apply(self, edits: list, resync: bool) -> str | None:
        """Apply the edits to the session. Returns "lamps" when only lamps changed (and perhaps
        diffuse colours), "colours" when only diffuse colours did (`SceneChanges.colours_only`):
        the view's cells, corner mask and kept rays still hold; else None."""
        t0 = time.perf_counter()
        snapshot = self._snapshot
        positions = normals = None
        for edit in edits:
            if isinstance(edit, FullScene):
                snapshot, positions, normals = edit.snapshot, None, None
            elif isinstance(edit, MoveVertices):
                if snapshot is None:
                    continue  # nothing to move yet; the full scene that follows has the positions
                if positions is None:
                    # Copies: the main thread's snapshot arrays are shared and stay untouched.
                    positions = snapshot.geometry.positions.copy()
                    normals = snapshot.geometry.normals.copy()
                positions[edit.indices] = edit.positions
                normals[edit.indices] = edit.normals
            elif isinstance(edit, SetShading):
                if snapshot is None:
                    continue
                snapshot = _with_geometry(snapshot, positions, normals)
                positions = normals = None
                snapshot = dataclasses.replace(
                    snapshot,
                    lights=snapshot.lights if edit.lights is None else list(edit.lights),
                    world=snapshot.world if edit.world is None else edit.world,
                    materials=snapshot.materials if edit.materials is None else list(edit.materials),
                )
            else:
                raise TypeError(f"unknown scene edit {type(edit).__name__}")
        if snapshot is None:
            return None
        snapshot = _with_geometry(snapshot, positions, normals)
        self._snapshot = snapshot
        self._scene_version += 1
        try:
            report = self._session.sync(snapshot)
        except errors.EmptySceneError:
            self._empty = True
            self._view_state = None
            self._cache_ref = None
            return None
        self._empty = False
        # The session raised the cache's events (stored hits marked stale); policy here: solve
        # again from the stored hits (a new system starts over: `SolveSchedule.attach`).
        self._schedule.attach(self._session.system)
        relit = None
        if not report.rebuilt:
            ch = report.changes
            self._schedule.changed(shading=ch.shading_changed, geometry=bool(ch.boxes) or resync,
                                   materials=ch.world_changed or bool(ch.materials_changed))
            # A diffuse colour's edit is lit again as a lamp's is: the view's pixels see the same
            # points, its rays hit what they hit, only the light they bring changed.
            if ((ch.lights_changed or ch.colours_only) and not resync and not ch.geometry_changed
                    and not ch.boxes and not ch.world_changed and (not ch.materials_changed or ch.colours_only)):
                relit = "lamps" if ch.lights_changed else "colours"
        self._steps["apply"] = (time.perf_counter() - t0) * 1e3
        return relit

    # --- view -----------------------------------------------------------------------------------

    def _begin_view(self, system, view: ViewRequest) -> None:
        """Visible cells and a first, coarse pass of direct light at the GI resolution: what a
        moving camera needs at once; the direct light's own resolution follows while it holds still."""
        t0 = time.perf_counter()
        # The cells this camera sees are its open space, whatever the faces around them say
        # (`open_space.py`): the solver's next traced batch opens those it finds inside.
        system.viewpoint = camera_position(view.view)
        points, normals, pix = _visible.pixels_to_points(view.position, view.normal)
        cells = system.visible_cells(points, normals)
        state = ViewState(view, self._scene_version, (points, normals, pix), cells, self.options.coarse_share)
        self._steps["visible"] = (time.perf_counter() - t0) * 1e3
        if view.material is not None and _glossy.has_glossy(system):
            state.glossy = GlossyLevel(state.coarse, view.material, camera_eye(view.view, view.proj),
                                       system.glossy_materials)
            if not state.glossy.pix.size:
                state.glossy = None  # no pixel reflects glossy light: nothing to show
            self._steps["glossy_level"] = (time.perf_counter() - t0) * 1e3 - self._steps["visible"]
        self._view_state = state
        self._direct_pass(system, state, state.coarse)
        if state.glossy is not None:
            self._glossy_cache(system, state)

    def _direct_pass(self, system, state: ViewState, level: DirectLevel | None = None) -> None:
        """A pass of direct light: the coarse one of a new view or a lamp edit (`level` =
        state.coarse: `direct_samples` x its samples per pixel, in blocks), or a still view's
        full-resolution one, traced as final renders trace theirs (`fine_samples`)."""
        t0 = time.perf_counter()
        coarse = level is not None
        level = level or state.fine_level()
        self._frame += 1
        points, normals, pix = level.points
        samples = self.options.direct_samples * level.samples
        rays = points.shape[0] * samples
        shares = _shares(system, state.request, coarse or level is state.coarse, pix)
        if coarse or self.options.fine_samples <= 0:
            light = _direct_split(system, points, normals, self._frame, samples) if points.shape[0] else None
            if light is not None:
                light = _translucent.mix_back(light, shares, lambda rows: _direct_split(
                    system, points[rows], -normals[rows], self._frame + _translucent.BACK_SEED_OFFSET, samples))
        else:
            samples = self.options.fine_samples
            r = state.request
            shape = level.position.shape[:2]
            camera = _penumbra.filter_camera(system.scene.lights, camera_eye(r.view, r.proj))
            # A full-res pass is 0.3-0.7 s on 2 busy cores: a lamp edit or a new view that arrives
            # meanwhile drops it between two blocks of its shadow rays instead of waiting for it.
            direct = _interruptible(system, lambda: self._superseded(state))
            # Its first pass on probes where the lamps allow (`penumbra._coarse_first_pass`).
            exact_lamps = _lights.one_sample_exact_lamps(system.scene.lights)
            # Weak lamps and the penumbra pass's rays by the lamps' light, as in final renders.
            rough = _lights.rough_lights(system.scene.lights, points, normals) if system.scene.lights else None
            # The glossy closed form's visibility (`glossy_ltc`), for the fine glossy light.
            exact, per_lamp = _glossy_ltc.direct_outputs(system, points.shape[0]) if shares is None else (None, None)
            try:
                light, full = (_penumbra.adaptive_direct(
                    direct, points, normals, pix, shape, self._frame * MAX_DIRECT_BLOCKS, samples,
                    camera=camera, pool=system.updater.pool, lamps=len(system.scene.lights),
                    exact_lamps=exact_lamps, per_lamp=per_lamp, exact_out=exact, rough=rough)
                    if points.shape[0] else (None, np.zeros(0, bool)))
            except _Superseded:
                self._steps["direct_dropped"] = (time.perf_counter() - t0) * 1e3
                return
            rays = points.shape[0] * min(samples, _penumbra.FIRST_SAMPLES) + int(full.sum()) * samples
            if light is not None:
                level.visibility = _glossy_ltc.lamp_visibility(system.scene.lights, light, per_lamp, exact)
            if light is not None and shares is not None:
                try:
                    light = _translucent.mix_back(light, shares, lambda rows: _penumbra.adaptive_direct(
                        direct, points[rows], -normals[rows], pix[rows], shape,
                        (self._frame + _translucent.BACK_SEED_OFFSET) * MAX_DIRECT_BLOCKS, samples, camera=camera,
                        pool=system.updater.pool, lamps=len(system.scene.lights), exact_lamps=exact_lamps,
                        rough=None if rough is None else _lights.rough_lights(system.scene.lights, points[rows],
                                                                              -normals[rows]))[0])
                except _Superseded:
                    self._steps["direct_dropped"] = (time.perf_counter() - t0) * 1e3
                    return
        if light is not None:
            level.add(light, samples)
        else:
            level.passes += 1
        self._count_rays(rays * max(len(system.scene.lights), 1))
        self._steps["direct"] = (time.perf_counter() - t0) * 1e3
        if level is state.coarse:
            # A new view or a lamp edit: its glossy light at once, with the coarse pass's samples.
            self._glossy_pass(system, state, samples)
        state.dirty = True

    def _edges_due(self, state: ViewState) -> bool:
        """The lamps' light of the draw's jittered subframes at the view's edges is due
        (`_edge_pass`): the request names the subframes, the view has its full-resolution light
        (a level of its own) and, when pixel rays are on, a pixel pass (the larger error goes
        first), and none was traced since the view or its lamps changed."""
        r = state.request
        if r.aa_offsets is None or len(r.aa_offsets) == 0 or state.edges is not None or state.passes < 1:
            return False
        if r.direct_position is r.position:
            return False  # one resolution: the coarse pass is the fine one, at the GI pixels
        return self.options.pixel_rays <= 0 or state.pixel_passes >= 1 or state.pending is not None

    def _edge_pass(self, system, state: ViewState) -> None:
        """Trace, for each jittered subframe of the draw (`ViewRequest.aa_offsets`), the lamps'
        light of what its ray through a pixel meets, at the pixels of the full-resolution light
        where that light or the surface changes within the pixel (`subpixel.light_edges` of its
        mean, `subpixel.surface_edges`), with the final render's subframe samples.

        Why: the draw shades a subframe from the light at the pixel centres (`DirectResolvePass`),
        which leaves a sun's hard shadow as aliased as one sample per pixel and gives a faceted
        mesh's edge pixels their neighbour facet's light; final renders trace these pixels again
        in every subframe (without it the atrium's Combined 0.022 -> 0.033, bunny_npm's 0.023 ->
        0.025). The draw takes this light where its subframe sees the same point and normal."""
        t0 = time.perf_counter()
        r = state.request
        level = state.fine_level()
        h, w = level.position.shape[:2]
        view = np.asarray(r.view, np.float64).reshape(4, 4)
        depth = -(level.position[..., :3] @ view[2, :3] + view[2, 3])
        total = level.mean()[..., :3].sum(axis=2)
        # Surface edges only where some light changes too (most lie in shadow, where the lamps'
        # light is nothing on both sides: the atrium's 36.8k edge pixels -> 16.2k, 0.23 -> 0.15 s).
        edge = _subpixel.light_edges(total) | (_subpixel.surface_edges(level.position, level.normal, depth)
                                               & _subpixel.light_edges(total, SURFACE_EDGE_CONTRAST))
        pix = np.flatnonzero(edge.reshape(-1)).astype(np.int32)
        shares = _shares(system, r, False, pix)
        if shares is not None:
            # Translucent pixels take their lamps' light on the back too (`translucent.mix_back`):
            # the resolve of the full-res light, which has it, serves them.
            pix = pix[~rows_above(shares, 0.0)]
        offsets = np.asarray(r.aa_offsets, np.float32).reshape(-1, 2)
        k, m = offsets.shape[0], pix.size
        light, point, normal = (np.zeros((k, m, 3), np.float32) for _ in range(3))
        if m:
            origins, dirs = _subpixel.subframe_rays(pix, w, h, view, r.proj, offsets)
            # (`frame.SUBFRAME_MIN_SAMPLES`, the penumbra pass's first samples, at least)
            samples = max(min(self.options.fine_samples, _penumbra.FIRST_SAMPLES), self.options.fine_samples // k)
            self._frame += 1
            frame = self._frame * MAX_DIRECT_BLOCKS

            def subframe(i: int) -> int:
                """Subframe i's rays, the points they meet and the lamps' light there (a pool job:
                its rays and numpy on one thread; `system.direct` runs inline there)."""
                if self._superseded(state):
                    raise _Superseded
                hits = system.tracer.intersect(origins[i], dirs[i], trusted=True)
                seen = np.flatnonzero(hits.prim >= 0)
                surf = system.surfaces.surface(hits.prim[seen], hits.u[seen], hits.v[seen], dirs[i][seen])
                point[i, seen], normal[i, seen] = surf.position, surf.normal
                light[i, seen] = system.direct(surf.position, surf.normal, frame + i, samples=samples)
                return seen.size

            jobs = [system.updater.pool.submit(subframe, i) for i in range(k)]
            try:
                seen = sum(job.result() for job in jobs)
            except _Superseded:
                futures.wait(jobs)
                self._steps["edges_dropped"] = (time.perf_counter() - t0) * 1e3
                return
            self._count_rays(k * m + seen * samples * max(len(system.scene.lights), 1))
        state.edges = EdgeLight(frozen(pix), frozen(light), frozen(point), frozen(normal), frozen(offsets))
        state.dirty = True
        self._steps["edges"] = (time.perf_counter() - t0) * 1e3

    def _direct_due(self, state: ViewState) -> bool:
        """A still view's next full-resolution direct pass is due: not before the cache has solved
        over its current hits (a fresh cache's or a re-shaded one's: the coarse pass's light shows
        meanwhile), and each after a pixel pass while those are due. The pixel rays' GI removes
        far more error than a sharper lamp light (Cornell 640x360 vs Cycles 1024 spp, a re-lit
        cache's image: 0.040 with the coarse pass, 0.037 with a full-res pass, 0.021 with the
        full-res pass and a pixel pass), so the image waits for neither behind the other."""
        if state.passes >= self.options.direct_passes or not self._schedule.solved_once:
            return False
        # A lamp edit's carried passes (`_carry`) stand for a pixel pass: its GI is the image's
        # (the lamp light's sharpness its larger error then).
        pixel_passes = max(state.pixel_passes, int(state.carried is not None))
        return state.passes < pixel_passes or not self._pixels_due(state)

    def _glossy_due(self, state: ViewState) -> bool:
        """A glossy pass of a still view is due: fewer than `glossy_passes`, alternating with the
        direct passes while they last (so that neither makes a step, and the wait of an edit for
        it, longer)."""
        glossy = state.glossy
        return (glossy is not None and glossy.pix.size > 0 and glossy.passes < self.options.glossy_passes
                and state.fine_glossy is None
                and (glossy.passes <= state.passes or state.passes >= self.options.direct_passes))

    def _fine_glossy_key(self, system, state: ViewState) -> tuple:
        return (*self._pixel_key(system), state.scene_gen)

    def _fine_glossy_due(self, state: ViewState, pending: bool = False) -> bool:
        """The final render's glossy light of a still view is due (`_fine_glossy`): the request
        carries what it needs, the view has a full-resolution direct pass and a pixel pass over
        the cache as it is now (the image's larger errors go first; pending: the first one's rays
        are in, `_pending`), and it was not made over this cache and lighting yet."""
        r = state.request
        if (state.glossy is None or r.full_material is None or r.full_albedo is None or r.glossy_samples <= 0
                or state.passes < 1 or not self._schedule.stable):
            return False
        system = getattr(self._session, "system", None)
        if system is None:
            return False
        if (r.full_material.shape[:2] != r.direct_position.shape[:2]
                or r.full_albedo.shape[:2] != r.full_material.shape[:2]):
            return False  # not the direct light's pixels
        key = self._fine_glossy_key(system, state)
        if (not pending and self.options.pixel_rays > 0
                and (state.pixel_key != key[:-1] or state.pixel_passes < 1)):
            return False
        return state.fine_glossy_key != key

    def _superseded(self, state: ViewState) -> bool:
        """An edit or a newer view waits (a plain read of the inbox references is atomic): a still
        view's long refinements stop between their steps and are made again once it holds still."""
        return bool(self._edits) or self._view is not state.request

    def _fine_glossy(self, system, state: ViewState) -> None:
        """The final render's glossy light at the still view's full-resolution pixels
        (`glossy_image.frame_glossy`: adaptive lamp samples, traced reflections, their filters),
        which then replaces the GI pixels' running glossy light. Why: the viewport's own glossy
        light (lamp samples at the GI pixels and the cache's split-sum reflection) left a still
        view's image far off the final render wherever a lobe is sharp enough for reflection rays
        to matter (Stanford dragon 640x360 against Cycles: settled viewport Combined 0.077, final
        render 0.047; the final render without reflection rays 0.067)."""
        t0 = time.perf_counter()
        r = state.request
        level = state.fine_level()
        points, normals, pix = level.points
        h, w = level.position.shape[:2]
        image = np.zeros((h * w, 4), np.float32)
        image[pix, 3] = 1.0
        key = self._fine_glossy_key(system, state)
        if points.shape[0]:
            self._frame += 1
            irradiance = level.mean().reshape(-1, 4)[pix, :3]

            def between() -> None:
                # 0.3-1 s on 2 busy cores: an edit or a new view that arrives meanwhile drops it
                # between its steps.
                if self._superseded(state):
                    raise _Superseded

            tint = None
            if r.full_tint is not None and np.asarray(r.full_tint).shape[:2] == (h, w):
                # Textured metals: their texels' coordinates (the albedo's and emission's alphas).
                tint = np.stack([np.asarray(r.full_albedo).reshape(-1, 4)[pix, 3],
                                 np.asarray(r.full_tint).reshape(-1)[pix]], axis=-1)
            try:
                light = _glossy.frame_glossy(
                    system, points, normals, pix, (h, w), np.asarray(r.full_material).reshape(-1)[pix],
                    np.asarray(r.full_albedo).reshape(-1, 4)[pix, :3], irradiance, r.view,
                    camera_eye(r.view, r.proj), self._frame, r.glossy_samples, r.reflection_rays,
                    pool=system.updater.pool, between=between, tint=tint, visibility=level.visibility,
                    screen=state.screen_light())
            except _Superseded:
                self._steps["fine_glossy_dropped"] = (time.perf_counter() - t0) * 1e3
                return
            image[pix, :3] = light.radiance
            lamps = max(len(system.scene.lights), 1)
            self._count_rays(points.shape[0] * (_glossy_noise.FIRST_SAMPLES * lamps + r.reflection_rays))
        state.fine_glossy, state.fine_glossy_key = image.reshape(h, w, 4), key
        state.dirty = True
        self._steps["fine_glossy"] = (time.perf_counter() - t0) * 1e3

    def _glossy_pass(self, system, state: ViewState, samples: int) -> None:
        """The lamps' glossy reflection at the GI pixels, one pass of `samples` shadow rays each."""
        glossy = state.glossy
        if glossy is None or not glossy.pix.size:
            return
        t0 = time.perf_counter()
        self._frame += 1
        glossy.add(_split(system.glossy, (glossy.points, glossy.normals, glossy.to_eye, glossy.rows),
                          self._frame, samples, system.updater.pool), samples)
        self._count_rays(glossy.pix.size * samples * max(len(system.scene.lights), 1))
        self._steps["glossy"] = (time.perf_counter() - t0) * 1e3
        state.dirty = True

    def _glossy_cache(self, system, state: ViewState) -> None:
        """The cache's split-sum glossy light at the view's glossy pixels from the cache as it is
        now: when a view begins, and with a packed cache (`_build_published`, at most every
        GLOSSY_CACHE_INTERVAL_S while the solver works), so the published glossy light reads a
        cache the gather reads (not the dark iterates of a first solve that are held back)."""
        glossy = state.glossy
        cache = system.cache
        key = (id(cache), cache.version)
        if glossy.cache_key == key:
            return
        t0 = time.perf_counter()
        if glossy.pix.size:
            part = _split_rows(lambda *a: _glossy.cache_glossy(system, *a).radiance,
                               (glossy.points, glossy.normals, glossy.to_eye, glossy.rows), system.updater.pool)
            glossy.cache_part = part
        glossy.cache_key, glossy.cache_at = key, time.perf_counter()
        self._steps["glossy_cache"] = (time.perf_counter() - t0) * 1e3
        state.dirty = True

    def _cell_colors(self, system, state: ViewState, force: bool) -> None:
        """The Cache Cells view of the GI pixels, as final renders draw it; again when the cache
        changed (at most every PUBLISH_INTERVAL_S while it converges)."""
        cache = system.cache
        key = (id(cache), cache.version)
        if state.cells_key == key or not (force or time.perf_counter() - state.cells_at >= PUBLISH_INTERVAL_S):
            return
        t0 = time.perf_counter()
        points, normals, pix = state.gi_points
        h, w = state.request.position.shape[:2]
        rgba = np.zeros((h * w, 4), np.float32)
        if points.shape[0]:
            rgba[pix, :3] = _visible.cell_debug_colors(cache, points, normals)
            rgba[pix, 3] = 1.0
        state.cell_colors = rgba.reshape(h, w, 4)
        state.cells_key, state.cells_at = key, time.perf_counter()
        self._steps["cells"] = (time.perf_counter() - t0) * 1e3
        state.dirty = True

    def _trace_mask(self, system, state: ViewState) -> None:
        t0 = time.perf_counter()
        h, w = state.request.position.shape[:2]
        points, normals, pix = state.gi_points
        mask = np.zeros((h * w, 8), bool)
        for start in range(0, points.shape[0], MASK_CHUNK):
            if self._view is not state.request:
                return  # a newer view arrived (a plain read of the inbox reference is atomic)
            chunk = slice(start, start + MASK_CHUNK)
            mask[pix[chunk]] = system.corner_visibility(points[chunk], normals[chunk])
        state.mask = _gather_layout.pack_corner_mask(mask.reshape(h, w, 8))
        state.visible = mask[pix]
        self._count_rays(8 * points.shape[0])
        self._steps["visibility"] = (time.perf_counter() - t0) * 1e3
        state.dirty = True

    def _view_refinement_due(self, state: ViewState) -> bool:
        """A still view's own light is not complete: its mask, glossy or direct passes, or pixel passes."""
        return (state.mask is None or self._glossy_due(state) or state.passes < self.options.direct_passes
                or self._pixels_due(state) or self._fine_glossy_due(state) or self._edges_due(state))

    def _refinement(self, state: ViewState) -> str | None:
        """The still view's next refinement (`_refine`), the first due in this order: its corner
        mask, a lamp edit's carried GI, glossy passes, the final render's glossy light, the edge
        light, full-res direct passes, pixel passes; None when none is due."""
        if state.mask is None:
            return "mask"
        if self._carry_due(state):
            return "carry"
        if self._glossy_due(state) and self._schedule.solved_once:
            return "glossy"
        if self._fine_glossy_due(state):
            return "fine_glossy"
        if self._edges_due(state):
            return "edges"
        if self._direct_due(state):
            return "direct"
        if self._pixels_due(state):
            return "pixels"
        return None

    def _refine(self, system, state: ViewState, refinement: str | None) -> None:
        """One step of the refinement `_refinement` named."""
        if refinement == "mask":
            self._trace_mask(system, state)
        elif refinement == "carry":
            self._carry(system, state)
        elif refinement == "glossy":
            self._glossy_pass(system, state, self.options.direct_samples)
        elif refinement == "fine_glossy":
            self._fine_glossy(system, state)
        elif refinement == "edges":
            self._edge_pass(system, state)
        elif refinement == "direct":
            self._direct_pass(system, state)
        elif refinement == "pixels":
            self._pixel_pass(system, state)

    def _pixel_key(self, system) -> tuple:
        """What a view's pixel passes were traced over: the cache, its lighting epoch (events
        change it; refining batches do not: a refined cache estimates the same light) and whether
        every batch is re-shaded since the last shading edit (the passes traced over the first
        re-shaded batch's solve are traced again once the rest is: `ViewState.refines`)."""
        return (id(system.cache), self._schedule.epoch, self._schedule.reshaded)

    def _pixels_due(self, state: ViewState) -> bool:
        """A pixel-ray pass is due: the cache has converged and no solve is under way
        (`SolveSchedule.stable`), the mask traced, and fewer passes than asked over this cache."""
        if self.options.pixel_rays <= 0 or state.visible is None or not self._schedule.stable:
            return False
        system = getattr(self._session, "system", None)
        if system is None:
            return False
        return state.pixel_key != self._pixel_key(system) or state.pixel_passes < self.options.pixel_passes

    def _pixel_pass(self, system, state: ViewState) -> None:
        """A pass of per-pixel final-gather rays at the GI pixels (`worker_pixels`: the final
        renders' algorithm and filter settings): started on its own thread, and once it is done
        filtered here and averaged into the view's running sum. A pass over another cache
        version starts over."""
        r = state.request
        points, normals, pix = state.gi_points
        key = self._pixel_key(system)
        if state.pixel_key is not None and state.pixel_key != key and not state.refines(key):
            state.reset_pixels()  # passes over an older cache (the pass in progress too)
        if state.pixel_pass is not None and state.pixel_pass.key != key:
            state.drop_pixel_pass()
        if state.pixel_pass is None:
            if self._pixel_thread is None:
                self._pixel_thread = futures.ThreadPoolExecutor(1, thread_name_prefix="hybridgi-viewport-pixels")
            state.pixel_pass = _pixels.PixelPass(key, state.pass_number(key), state.screen_light())
            if state.reshade_due:
                # A lamp edit's first pass: the kept rays shaded again (no ray traced again).
                state.reshade_due = False
                side, state.relit_side = state.relit_side, None  # released once taken (~0.6 KB a GI pixel)
                side = side[1] if side is not None and side[0] == system.cache.version else None
                state.pixel_pass.start_reshade(self._pixel_thread, system, state.kept, state.visible,
                                               on_done=self._wake, side=side)
            else:
                state.pixel_pass.start(self._pixel_thread, system, points, normals, state.visible,
                                       self.options.pixel_rays, pix, r.position.shape[1], on_done=self._wake,
                                       keep=True)
            return
        pass_ = state.pixel_pass
        if not pass_.done:
            return
        state.pixel_pass = None
        gi = pass_.result()
        if pass_.traced is not None:
            state.kept = pass_.traced
        self._count_rays(gi.rays)
        self._steps["pixel_rays"] = pass_.ms
        t1 = time.perf_counter()
        raster = _raster_settings.RasterSettings()
        if r.full_res and r.direct_position.shape[:2] != r.position.shape[:2]:
            if state.pixel_sum is None:
                self._pending(system, state, gi, raster)
                if self._superseded(state):
                    return  # an edit or a new view goes first; these rays are of the old one
                t1 = time.perf_counter()
            rays = gi.rays
            full = _pixels.full_res(system, pass_, gi, r.position, pix, points, normals, r.view,
                                    self.options.pixel_rays, state.fine_level().points,
                                    r.direct_position.shape[:2], raster)
            indirect, direct = full.indirect, full.direct
            self._count_rays(full.gi.rays - rays)  # the detail pixels' rays
        else:
            indirect, direct = _pixels.images(gi, r.position, pix, points, normals, r.view, raster)
        state.add_pixels(indirect, direct, key, gi.channels()[1])
        self._steps["pixel_filter"] = (time.perf_counter() - t1) * 1e3

    def _pending(self, system, state: ViewState, gi, raster) -> None:
        """The view's first pixel pass over its cache has its rays: published for the draw to
        resolve on the GPU (`PendingGI`), then the view's first full-res direct pass if it has
        none (and its edge light), and only then the worker's own resolve (its filter,
        interpolation and detail pixels in numpy, 0.3-0.4 s at 640x360 on 2 busy cores). Why: the
        image waited for that resolve and then for the direct pass (car 640x360, worker timeline:
        within its target at 1.0 s, now at 0.75 s; Cornell after a light move 1.5 -> 1.0 s); the
        detail pixels (car: 0.0033 -> 0.0032) follow."""
        r = state.request
        points, normals, pix = state.gi_points
        self._pending_serial += 1
        state.pending = PendingGI(
            self._pending_serial, dataclasses.replace(gi), r.position, pix, points, normals, r.view,
            state.fine_level().points, r.direct_position.shape[:2], raster.pixel_filter,
            raster.bilateral_plane_sigma, raster.bilateral_normal_power)
        state.dirty = True
        self._publish(force=True)
        if state.passes == 0 and self.options.direct_passes > 0:
            self._direct_pass(system, state)
            self._publish(force=True)
        # Then the view's final-render glossy light (`_fine_glossy`), the larger error in a glossy
        # scene than the worker's own resolve of the rays the draw shows already (bunny_npm 640x360,
        # worker timeline: the resolve 0.0333 -> 0.0335, the glossy light then 0.0237), or, without
        # glossy layers, the edge light (morse_apartment: 0.058 -> 0.071 at 1.5 s with its five
        # lamps' edges before its glossy light).
        if self._superseded(state):
            return
        if self._fine_glossy_due(state, pending=True):
            self._fine_glossy(system, state)
            self._publish(force=True)
        elif state.glossy is None and self._edges_due(state):
            self._edge_pass(system, state)
            self._publish(force=True)

    def _carry_due(self, state: ViewState) -> bool:
        """A lamp (or colour) edit's carried pixel GI is due: the view had pixel passes before it,
        none since, and the cache has solved over the re-lit hits."""
        return (state.carry is not None and state.carried is None and state.pixel_sum is None
                and state.visible is not None and self._schedule.solved_once)

    def _carry(self, system, state: ViewState) -> None:
        """The view's pixel passes from before a lamp (or colour) edit, scaled to the re-lit cache
        (`gi_carry`), shown until the first pixel pass over it: the re-lit image without waiting
        ~0.6 s for its rays."""
        t0 = time.perf_counter()
        points, normals, pix = state.gi_points
        indirect, direct, cache_old = state.carry
        side = _pixel_gather.cache_side(system, points, normals, state.visible)
        cache_new = side["res"][:, 9:16]
        # The re-shade of the view's kept rays over this cache takes the same gather (`_pixel_pass`).
        state.relit_side = (system.cache.version, side)
        nearest, full_pix = _carry_map(state, indirect.shape[:2])
        ratio, extra = _gi_carry.smoothed_change(cache_old, cache_new, pix, normals, state.request.position.shape[:2])
        carried = _gi_carry.carried(indirect, direct, ratio, extra, nearest, full_pix)
        state.carried = (frozen(carried[0]), frozen(carried[1]))
        state.dirty = True
        self._steps["carry"] = (time.perf_counter() - t0) * 1e3

    def _tracing(self) -> bool:
        """A pixel pass of the view is tracing on its own thread (worker thread only)."""
        state = self._view_state
        return state is not None and state.pixel_pass is not None and state.pixel_pass.running

    def _drop_pixels(self) -> None:
        """Stop the view's pixel pass in flight, if any, and wait for it (`ViewState.drop_pixel_pass`)."""
        if self._view_state is not None:
            self._view_state.drop_pixel_pass()

    def _wake(self) -> None:
        """Called by the pixel thread when its pass ends: the waiting worker goes on."""
        with self._cond:
            self._cond.notify_all()

    # --- cache ---------------------------------------------------------------------------------

    def _solve_step(self, schedule: SolveSchedule, state: ViewState) -> None:
        t0 = time.perf_counter()
        rays = schedule.step(state.cells)
        self._updates += 1
        self._count_rays(rays, update=True)
        self._steps["update"] = (time.perf_counter() - t0) * 1e3
        for k, v in schedule.steps_ms.items():
            self._steps[f"solve_{k}"] = v

    # --- publishing -----------------------------------------------------------------------------

    def _count_rays(self, rays: int, update: bool = False) -> None:
        now = time.perf_counter()
        self._rates.append((now, int(rays), update))
        while self._rates and now - self._rates[0][0] > RATE_WINDOW_S:
            self._rates.popleft()

    def _stats(self) -> WorkerStats:
        now = time.perf_counter()
        recent = [r for r in self._rates if now - r[0] <= RATE_WINDOW_S]
        span = max(now - recent[0][0], 1e-3) if len(recent) > 1 else RATE_WINDOW_S
        state = self._view_state
        visible = state.cells if state is not None else np.zeros(0, np.int64)
        system = getattr(self._session, "system", None)
        if self._schedule.solved_once and system is not None and self._schedule.system is system:
            settled = np.isin(visible, system.solver.cells)
        else:
            settled = np.zeros(visible.size, bool)
        return WorkerStats(
            updates=self._updates,
            updates_per_s=sum(1 for r in recent if r[2]) / span,
            rays_per_s=sum(r[1] for r in recent) / span,
            visible_cells=int(visible.size),
            converged=float(settled.mean()) if settled.size else 0.0,
            steps_ms=MappingProxyType(dict(self._steps)),
            scene_gen=self._applied_gen,
        )

    def _publish(self, force: bool = True) -> None:
        published = self._build_published(idle=False, force=force)
        with self._cond:
            self._published = published
            self._cond.notify_all()
        if self._glossy_cache_due and self._view_state is not None and self._view_state.glossy is not None:
            # The glossy light of the cache just published, in a second publication: the first
            # converged image is not held back by it (0.1-0.25 s on bunny_npm, 2 busy cores).
            self._glossy_cache_due = False
            t0 = time.perf_counter()
            self._glossy_cache(self._session.system, self._view_state)
            self._pack_s += time.perf_counter() - t0  # a cost of that publication too
            published = self._build_published(idle=False, force=False)
            with self._cond:
                self._published = published
                self._cond.notify_all()

    def _build_published(self, idle: bool, pack: bool = True, force: bool = True) -> Published:
        """A new `Published` from the worker's state; arrays handed out are copies never written
        again. pack : whether the cache may be packed now; force : even within PUBLISH_INTERVAL_S."""
        system = getattr(self._session, "system", None)
        cache_frame, view_result = self._published.cache, self._published.view
        if system is None:
            cache_frame = view_result = None
        else:
            cache = system.cache
            key = (id(cache), cache.version, id(cache.sh_direct))
            old = self._published_cache_key
            new_cache = old is None or old[0] != key[0] or old[2] != key[2]
            since = self._published_at
            if self._schedule.has_work:
                interval = max(SOLVE_PUBLISH_INTERVAL_S, SOLVE_PUBLISH_PACKS * self._pack_s)
                since = max(since, self._schedule.changed_at)
            else:
                interval = PUBLISH_INTERVAL_S
            due = force or new_cache or time.perf_counter() - since >= interval
            # A cache nothing was traced into yet shows nothing: the main thread's empty frame
            # stands in (packing a 48^3 grid's depth moments costs ~0.4 s before the first batch).
            traced = bool(cache.samples.any())
            if not force and (self._schedule.holding(FIRST_SOLVE_HOLD_S) or self._schedule.refining):
                # (A batch traced in part has replaced its cells' filtered direct band with the
                # raw mean: the cache is shown again once that batch is solved and filtered.)
                due = False
            depth_key = (key[0], key[2], self._schedule.blends)
            fresh = self._published_depth is not None and self._published_depth[0] == depth_key
            sh_due = key != old and due
            # (The depth alone may join the published frame of this very cache.)
            depth_due = not fresh and self._depth_wanted() and (sh_due or cache_frame is not None and not new_cache)
            if pack and (sh_due or depth_due) and traced:
                t0 = time.perf_counter()
                size = _gather_layout.DEFAULT_MAX_TEXTURE_SIZE  # never ask the GPU from this thread
                _gather_layout.check_cache_textures(cache.grid.count, cache.settings.sh_coeffs,
                                                    cache.settings.depth_texels, size)
                # Solver iterations change the radiance bands only: the depth moments (the larger
                # texture) are packed again only after steps that blend traced rays, and only once
                # a view reads them (`_depth_wanted`).
                if depth_due:
                    self._published_depth = (depth_key, frozen(_gather_layout.pack_depth(cache, size)))
                    fresh = True
                if sh_due:
                    t_sh = time.perf_counter()
                    sh_tex = frozen(_gather_layout.pack_sh(cache, size))
                    self._pack_s = time.perf_counter() - t_sh
                else:
                    sh_tex = cache_frame.sh_texels
                depth_tex = self._published_depth[1] if fresh else None
                self._serial += 1
                cache_frame = CacheFrame(self._serial, cache.grid, cache.settings, sh_tex, depth_tex)
                self._steps["pack"] = (time.perf_counter() - t0) * 1e3
                glossy = self._view_state.glossy if self._view_state is not None else None
                if sh_due:
                    self._published_cache_key = key
                    self._published_at = time.perf_counter()
                if sh_due and glossy is not None and (not self._schedule.has_work
                                           or time.perf_counter() - glossy.cache_at >= GLOSSY_CACHE_INTERVAL_S):
                    self._glossy_cache_due = True  # read this very cache once it is out (`_publish`)
            state = self._view_state
            if state is None:
                view_result = None
            elif state.dirty:
                self._serial += 1
                view_result = state.result(self._serial)
                state.dirty = False
        stats = dataclasses.replace(self._stats(), idle=idle)
        return Published(cache=cache_frame, view=view_result, stats=stats, empty=self._empty)

    def _depth_wanted(self) -> bool:
        """Whether a published cache should carry its depth moments. Only the gather's Chebyshev
        test reads them, and a still view with its corner mask never does: the first converged
        cache goes out without them (packing 57 MB of moments for a 48^3 grid took 0.25-0.3 s of
        the Cornell box's first GI image on 2 busy cores), and they follow once a view lacks
        its mask (a camera move) or the still view's own light is complete. A view drawn without
        its mask meanwhile reads the cache without the test (`PackedGatherPass`)."""
        state = self._view_state
        return state is None or state.mask is None or not self._view_refinement_due(state)

    def _fail(self, message: str) -> None:
        with self._cond:
            self._published = dataclasses.replace(self._published, error=message)
            self._stop = True
            self._cond.notify_all()


class _Superseded(Exception):
    """A still view's refinement in progress is no longer wanted: an edit or a newer view came."""


# --- snapshot helpers (pure numpy) ----------------------------------------------------------------


def _carry_map(state: ViewState, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(nearest GI point, flat pixel) of each geometry pixel of the view's pixel-pass textures of
    `shape` (`gi_carry.nearest_lo_point`), made once per view (the geometry is the view's), by its
    first lamp edit's carry: ~50 ms at 640x360, which every new view's first pixel pass would
    otherwise pay before its image goes out."""
    if state.carry_map is None:
        points, _normals, pix = state.gi_points
        h, w = state.request.position.shape[:2]
        if shape == (h, w):
            state.carry_map = (np.arange(pix.shape[0]), pix)
        else:
            full_points, _n, full_pix = state.fine_level().points
            state.carry_map = (_gi_carry.nearest_lo_point(full_points, full_pix, shape[1], points, pix, (h, w)),
                               full_pix)
    return state.carry_map


def _shares(system, request, coarse: bool, pix: np.ndarray) -> np.ndarray | None:
    """(n, 3) the translucent shares (`translucent.pixel_shares`) of a direct level's pixels
    `pix`: the GI pixels' material texels for the coarse level, the direct light's for the fine
    one; None in a scene without a Translucent BSDF (or a request that carries no texels)."""
    table = _translucent.share_table(system.scene.materials)
    texels = request.material if coarse else request.direct_material
    if table is None or texels is None:
        return None
    return _translucent.pixel_shares(table, np.asarray(texels).reshape(-1)[pix])


def _direct_split(system, points: np.ndarray, normals: np.ndarray, frame: int, samples: int) -> np.ndarray:
    """`system.direct` of a direct pass in blocks of DIRECT_BLOCK_POINTS points on the worker
    pool, block i with frame number frame * MAX_DIRECT_BLOCKS + i (its own samples). The blocks
    are fixed, so the light does not depend on the pool's thread count. `system.direct` itself
    splits only above 2^18 shadow rays, so a viewport pass (57,600 GI pixels at 4 samples) ran on
    the worker thread alone."""
    n = points.shape[0]
    blocks = min(-(-n // DIRECT_BLOCK_POINTS), MAX_DIRECT_BLOCKS)
    if blocks <= 1:
        return system.direct(points, normals, frame * MAX_DIRECT_BLOCKS, samples=samples)
    bounds = np.linspace(0, n, blocks + 1).astype(np.intp)
    pool = system.updater.pool
    jobs = [pool.submit(system.direct, points[a:b], normals[a:b], frame * MAX_DIRECT_BLOCKS + i, samples)
            for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True))]
    return np.concatenate([j.result() for j in jobs])


def _interruptible(system, superseded: Callable[[], bool]):
    """`system.direct` in fixed blocks of DIRECT_BLOCK_POINTS points, block i with frame number
    frame * MAX_DIRECT_BLOCKS + i, raising `_Superseded` before a block once superseded() holds.
    The blocks are fixed, so the light does not depend on the pool's thread count or on timing."""

    def direct(points, normals, frame, samples=None, lights=None, **outputs):
        # outputs : `system.direct`'s per-point output arrays (partial, unshadowed, exact,
        # per_lamp), written block by block through views of them, and its other keywords
        # (ratio_samples) as they are; lights : lamp indices.
        n = points.shape[0]
        blocks = min(-(-n // DIRECT_BLOCK_POINTS), MAX_DIRECT_BLOCKS)
        bounds = np.linspace(0, n, blocks + 1).astype(np.intp)
        out = []
        for i, (a, b) in enumerate(zip(bounds[:-1], bounds[1:], strict=True)):
            if superseded():
                raise _Superseded
            views = {k: v[a:b] if isinstance(v, np.ndarray) else v for k, v in outputs.items()}
            out.append(system.direct(points[a:b], normals[a:b], frame * MAX_DIRECT_BLOCKS + i, samples=samples,
                                     lights=lights, **views))
        return np.concatenate(out) if out else np.zeros((0, 3), np.float32)

    return direct


_TABLES_PREFETCHED = threading.Event()


def _prefetch_glossy_tables() -> None:
    """Read the GGX tables (`specular.tables`, once per process: ~4 ms from the shipped file,
    0.15-0.35 s where they must be computed) on a thread of their own while the worker syncs its
    first scene, so that a new view's glossy light does not wait for them (computed, they held the
    atrium's first light back by 0.36 s)."""
    if _TABLES_PREFETCHED.is_set():
        return
    _TABLES_PREFETCHED.set()
    from hybridgi_core import specular  # noqa: PLC0415

    threading.Thread(target=specular.tables, name="hybridgi-ggx-tables", daemon=True).start()


def _split(fn, arrays: tuple, frame: int, samples: int, pool) -> np.ndarray:
    """fn(*arrays, frame, samples) in blocks of DIRECT_BLOCK_POINTS rows on the pool, block i
    with frame number frame * MAX_DIRECT_BLOCKS + i (as `_direct_split`)."""
    n = arrays[0].shape[0]
    blocks = min(-(-n // DIRECT_BLOCK_POINTS), MAX_DIRECT_BLOCKS)
    if blocks <= 1:
        return fn(*arrays, frame * MAX_DIRECT_BLOCKS, samples)
    bounds = np.linspace(0, n, blocks + 1).astype(np.intp)
    jobs = [pool.submit(fn, *(a[lo:hi] for a in arrays), frame * MAX_DIRECT_BLOCKS + i, samples)
            for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:], strict=True))]
    return np.concatenate([j.result() for j in jobs])


def _split_rows(fn, arrays: tuple, pool) -> np.ndarray:
    """fn(*arrays) in blocks of DIRECT_BLOCK_POINTS rows on the pool (numpy work that releases
    the GIL for most of its time: both cores of a 2-core pool)."""
    n = arrays[0].shape[0]
    blocks = min(-(-n // DIRECT_BLOCK_POINTS), MAX_DIRECT_BLOCKS)
    if blocks <= 1:
        return fn(*arrays)
    bounds = np.linspace(0, n, blocks + 1).astype(np.intp)
    jobs = [pool.submit(fn, *(a[lo:hi] for a in arrays)) for lo, hi in zip(bounds[:-1], bounds[1:], strict=True)]
    return np.concatenate([j.result() for j in jobs])


def _with_geometry(snapshot, positions, normals):
    if positions is None:
        return snapshot
    geometry = dataclasses.replace(snapshot.geometry, positions=positions, normals=normals)
    return dataclasses.replace(snapshot, geometry=geometry)
