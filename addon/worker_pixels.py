"""The viewport worker's per-pixel final gather of a still view, traced beside the worker's
other steps (pure numpy + embreex, never bpy).

Final renders call `pixel_gather.gi_images` once per frame. A viewport pass of 32 rays at the GI
resolution costs 0.4-1 s on 2 busy cores, too long for one worker step: a lamp or camera edit
would wait for all of it. So the pass is the final render's one `pixel_gather.trace_pixels`
call over every GI pixel, run on a thread of its own (`PixelPass.start`) while the worker waits
for it, or for an edit or a new view, which stop it between two of its work items
(`PixelPass.drop`); once it is done the worker filters the whole image's residual and makes the
textures exactly as `gi_images` does from its rays (`images`, `full_res`).

Why one call, not slices of it a step each: each slice ended with a barrier on the pool (the
slower of its two work items) and a worker step; the Cornell box's 14 slices of 4096 pixels took
0.56 s where the same rays in one call take ~0.4 s.

A pass keeps its traced rays (`PixelPass.traced`): after a lamp edit the view's pixels and
geometry hold, so its first pass shades them again over the re-lit cache (`start_reshade`,
`pixel_gather.reshade_pixels`) instead of tracing new ones: a third less work (Cornell 640x360,
after a light move: 192 vs 270 ms).
"""

from __future__ import annotations

import threading
import time
from concurrent import futures

import numpy as np

from hybridgi_core import pixel_gather
from hybridgi_core.levels import hit_lookup
from hybridgi_core.settings import MULTI_BOUNCE

#: Frame numbers per pass: pass k traces frame FRAME_BASE + k * FRAMES_PER_PASS.
FRAME_BASE = 1 << 24
FRAMES_PER_PASS = 1024
#: Most rays a pass keeps traced for a lamp edit to shade again (`PixelPass.start(keep=)`): 28
#: bytes a ray (its direction and hit, `BegunPixels.slim`), so ~235 MB at most (a 1280x720 view's
#: 230k GI pixels of 32 rays: 206 MB); a larger view traces its passes again after a lamp edit.
KEEP_RAYS_MAX = 1 << 23


class PixelPass:
    """One pass over the GI points of a view, against one cache version (`key`), traced on a
    thread of its own. The worker thread owns it: `start`, `done`, `result` and `drop` are called
    there; the thread only traces."""

    def __init__(self, key, index: int, screen=None):
        self.key = key
        self.index = index  # the pass's number among the view's passes (its frames)
        #: The view's lamp light the hits read where the camera sees them (`ViewState.screen_light`;
        #: None: every hit traces its own shadow rays), one for the whole pass.
        self.screen = screen
        #: The cache as the hits read it, built by the pass (the detail pixels' rays read it too).
        self.lookup = None
        #: The pass's traced rays (`pixel_gather.BegunPixels`), kept when the pass ran to its end
        #: and `start(keep=True)`: a lamp edit's first pass shades them again (`start_reshade`).
        self.traced: pixel_gather.BegunPixels | None = None
        self.ms = 0.0  # the pass's own wall time
        self._stop = threading.Event()
        self._future: futures.Future | None = None

    @property
    def frame(self) -> int:
        """The frame number of the pass (its detail pixels draw from frame + DETAIL_FRAME)."""
        return FRAME_BASE + self.index * FRAMES_PER_PASS

    @property
    def running(self) -> bool:
        return self._future is not None and not self._future.done()

    @property
    def done(self) -> bool:
        return self._future is not None and self._future.done()

    def start(self, executor, system, points, normals, visible, rays: int, pix=None, width: int = 0,
              on_done=None, keep: bool = False) -> None:
        """Trace the pass on `executor` (one thread; the rays' work items go to the system's pool).
        pix, width : the points' flat pixel indices in the GI image and its width: each tile's
        rays stratify together (`tiled_nets`, one key per pass). on_done() is called from that
        thread when the pass ends (to wake the worker). keep : hold the traced rays once the pass
        ran to its end (`traced`), if they are at most KEEP_RAYS_MAX."""
        tiles = None if pix is None else (pix, width, self.frame)
        keep = keep and rays > 0 and points.shape[0] * rays <= KEEP_RAYS_MAX

        def trace() -> pixel_gather.PixelGI:
            t0 = time.perf_counter()
            if rays > 0:
                self.lookup = hit_lookup(system, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
            begun = pixel_gather.begin_pixels(system, points, normals, rays, self.frame, visible, lookup=self.lookup,
                                              pixels=tiles, stop=self._stop.is_set)
            gi = pixel_gather.finish_pixels(begun, self.screen)
            if keep and not self._stop.is_set() and begun.traced:
                begun.slim()
                self.traced = begun
            self.ms = (time.perf_counter() - t0) * 1e3
            return gi

        self._run(executor, trace, on_done)

    def start_reshade(self, executor, system, traced: pixel_gather.BegunPixels, visible, on_done=None,
                      side: dict | None = None) -> None:
        """Shade an earlier pass's traced rays again on `executor` (`pixel_gather.reshade_pixels`:
        the system's current cache and this pass's `screen` light, no ray traced again): a lamp
        edit's first pass over a still view. The rays stay kept (`traced`) for the next edit.
        side : the current cache's `pixel_gather.cache_side` at the pass's points, if made."""

        def reshade() -> pixel_gather.PixelGI:
            t0 = time.perf_counter()
            self.lookup = hit_lookup(system, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
            gi = pixel_gather.reshade_pixels(traced, system, self.frame, visible, lookup=self.lookup,
                                             screen=self.screen, stop=self._stop.is_set, side=side)
            self.traced = traced
            self.ms = (time.perf_counter() - t0) * 1e3
            return gi

        self._run(executor, reshade, on_done)

    def _run(self, executor, fn, on_done) -> None:
        self._future = executor.submit(fn)
        if on_done is not None:
            self._future.add_done_callback(lambda _f: on_done())

    def result(self) -> pixel_gather.PixelGI:
        """The finished pass's rays (raises what the tracing raised)."""
        return self._future.result()

    def drop(self) -> None:
        """Stop the pass between two of its work items and wait for it: the system it reads may
        change next. Its result is thrown away."""
        self._stop.set()
        if self._future is not None:
            futures.wait([self._future])


def images(gi, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray, normals: np.ndarray,
           view: np.ndarray, raster) -> tuple[np.ndarray, np.ndarray]:
    """(gi_indirect, gi_direct) (h, w, 4) textures from a whole image's rays: the filtered
    residual over the cache's value, as `pixel_gather.gi_images` makes them (keep in step)."""
    h, w = position_lo.shape[:2]
    _est, cache, valid, res, pos, nrm, camera, var = pixel_gather.image_planes(gi, pix, points, normals, view, h, w)
    filtered = pixel_gather.filter_residual(
        res.reshape(h, w, 7), pos.reshape(h, w, 3), nrm.reshape(h, w, 3), valid.reshape(h, w), camera,
        raster.pixel_filter, raster.bilateral_plane_sigma, raster.bilateral_normal_power,
        variance=var.reshape(h, w, 2)).reshape(h * w, 7)
    return pixel_gather.textures(cache + filtered[pix], pix, h, w)


def full_res(system, pass_: PixelPass, gi, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray,
             normals: np.ndarray, view: np.ndarray, rays: int, full: tuple, full_shape: tuple[int, int],
             raster) -> pixel_gather.FullResGI:
    """A finished pass's rays `gi` resolved at every full-res pixel as final renders resolve
    theirs (`pixel_gather.full_res_resolve`); full : (points, normals, flat pixels) of the
    full-res G-buffer of shape full_shape (h, w). The detail pixels' rays are traced here."""
    h, w = full_shape
    return pixel_gather.full_res_resolve(
        system, gi, position_lo, pix, points, normals, view, pass_.frame, rays, full[0], full[1],
        full[2], (w, h), passes=raster.pixel_filter, plane_sigma=raster.bilateral_plane_sigma,
        normal_power=raster.bilateral_normal_power, lookup=pass_.lookup, screen=pass_.screen)
