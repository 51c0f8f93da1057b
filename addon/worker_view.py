"""The worker's running state for the latest view: its visible cells, the corner-visibility mask,
and the direct light it refines while the view holds still (worker thread only, pure numpy).
"""

from __future__ import annotations

import numpy as np

from hybridgi_core import glossy_image as _glossy
from hybridgi_core import visible as _visible
from hybridgi_core.lights import RATIO_MIN_SAMPLES
from hybridgi_core.screen_light import ScreenLight

from .worker_messages import ViewRequest, ViewResult, frozen


class DirectLevel:
    """Running sum of direct-light passes at one resolution (worker thread only)."""

    def __init__(self, position: np.ndarray, normal: np.ndarray, points: tuple, samples: int = 1):
        self.position, self.normal = position, normal
        self.points = points  # (points, normals, flat pixels)
        self.samples = samples  # shadow-ray samples per pixel and coarse pass, in units of direct_samples
        h, w = position.shape[:2]
        self.sum = np.zeros((h * w, 4), np.float32)
        self.sum[points[2], 3] = 1.0
        self.passes = 0
        self.weight = 0  # the passes' samples (a pass's light counts by its samples)
        #: (n, lamps) the last full-resolution pass's lamp visibility at the points
        #: (`glossy_ltc.lamp_visibility`), or None: the fine glossy light's closed form.
        self.visibility = None

    def add(self, light: np.ndarray, samples: int) -> None:
        """One pass's light (n, 3) at the level's points, traced with `samples` rays per pixel."""
        self.sum[self.points[2], :3] += light * np.float32(samples)
        self.passes += 1
        self.weight += samples

    @property
    def samples_per_pixel(self) -> int:
        return self.weight

    def mean(self) -> np.ndarray:
        h, w = self.position.shape[:2]
        out = self.sum.copy()
        out[:, :3] /= max(self.weight, 1)
        return out.reshape(h, w, 4)


def reflecting(glossy_materials) -> np.ndarray:
    """(m,) bool: materials whose glossy lobes reflect light (a Glossy Color above 0 at some view
    angle: `GlossyMaterials.reflects`, which the final render's glossy step checks too)."""
    return np.asarray(glossy_materials.reflects, bool).copy()


class GlossyLevel:
    """The glossy layers' light at a level's pixels (the GI's; worker thread only): the lamps' part
    summed over passes (shadow rays, noisy) and the cache's split-sum part, read again when the
    cache changes (`cache_key`). Only pixels whose material reflects some glossy light are
    computed (a layer of weight 0, as a Principled BSDF with Specular IOR Level 0, reflects none)."""

    def __init__(self, level: DirectLevel, material: np.ndarray, eye, glossy_materials):
        points, normals, pix = level.points
        self.position, self.normal = level.position, level.normal
        h, w = level.position.shape[:2]
        self.shape = (h, w)
        rows = _glossy.material_rows(np.asarray(material).reshape(-1)[pix], glossy_materials)  # -1: none it knows
        sel = np.flatnonzero(np.append(reflecting(glossy_materials), False)[rows])
        self.points, self.normals, self.rows = points[sel], normals[sel], rows[sel]
        self.pix = pix[sel]
        self.all_pix = pix  # every geometry pixel of the level (a = 1: glossy-free ones show 0)
        self.to_eye = _glossy.directions_to_eye(self.points, eye).astype(np.float32)
        self.lamp_sum = np.zeros((self.pix.size, 3), np.float32)  # the passes' light x their samples
        self.passes = 0
        self.weight = 0  # the passes' samples (a pass's light counts by its samples, as `DirectLevel`'s)
        self.cache_part = np.zeros((self.pix.size, 3), np.float32)
        self.cache_key = None
        self.cache_at = 0.0

    def reset_lamps(self) -> None:
        self.lamp_sum[:] = 0.0
        self.passes = 0
        self.weight = 0

    def add(self, light: np.ndarray, samples: int) -> None:
        """One pass's lamp light (n, 3) at the glossy pixels, traced with `samples` rays each. Why
        by its samples: a new view's first pass takes the coarse pass's samples (16 at 640x360),
        the next ones one; an even mean of the two doubled the first pass's noise (bunny_npm's
        viewport image 0.0333 -> 0.0376 from the sixteen-sample pass to the mean with the next)."""
        self.lamp_sum += light * np.float32(samples)
        self.passes += 1
        self.weight += samples

    def lamp_mean(self) -> np.ndarray:
        """(n, 3) the lamps' glossy light at the glossy pixels, the passes' mean by their samples."""
        return self.lamp_sum / np.float32(max(self.weight, 1))

    def image(self) -> np.ndarray:
        """(h, w, 4) float32 lamp mean + cache part, a = 1 on every geometry pixel of the level."""
        h, w = self.shape
        out = np.zeros((h * w, 4), np.float32)
        out[self.all_pix, 3] = 1.0
        out[self.pix, :3] = self.lamp_mean() + self.cache_part
        return out.reshape(h, w, 4)


class ViewState:
    """The worker's running state for the latest view (worker thread only): visible cells, the
    corner mask, and direct light at two levels, coarse (GI resolution, one pass, as soon as the
    view arrives) and fine (the direct light's resolution, refined while the view holds still)."""

    def __init__(self, request: ViewRequest, scene_gen: int, gi_points: tuple, cells: np.ndarray,
                 coarse_share: float = 1.0):
        self.request = request
        self.scene_gen = scene_gen
        self.gi_points = gi_points  # (points, normals, flat pixels) at the GI resolution
        self.cells = cells
        # The coarse pass traces `coarse_share` of the rays of one fine pass (more samples on fewer
        # pixels), so soft shadows shimmer no more while the camera moves than once it stops.
        ratio = coarse_share * request.direct_position.shape[0] * request.direct_position.shape[1] / max(
            request.position.shape[0] * request.position.shape[1], 1)
        # At least the ratio estimator's samples (`lights.RATIO_MIN_SAMPLES`): a wholly lit pixel's
        # area lamp is then exact, not a one-ray guess (Cornell 640x360, the re-lit image after a
        # light move, 0.1 s after it: Combined 0.085 -> 0.073 vs Cycles).
        self.coarse = DirectLevel(request.position, request.normal, gi_points,
                                  int(np.clip(round(ratio), RATIO_MIN_SAMPLES, 16)))
        self._fine: DirectLevel | None = None
        self.mask: np.ndarray | None = None
        self.visible: np.ndarray | None = None  # (n, 8) bool corner visibility of the GI points
        #: Running sums of the pixel-ray passes: [indirect, direct] (h, w, 4), the passes, and the
        #: cache key they were traced over (another cache: they start over).
        self.pixel_sum: list | None = None
        self.pixel_passes = 0
        self.pixel_key = None
        self.pixel_pass = None  # `worker_pixels.PixelPass` in progress
        self.pixel_next: list | None = None  # [sum, passes, key] over a refined cache (`refines`)
        #: The sum of the passes' cache values at the GI points ((n, 7), `PixelGI.channels`),
        #: beside `pixel_sum` (and in `pixel_next`'s fourth item): what a lamp edit's carry scales.
        self.pixel_cache: np.ndarray | None = None
        #: A lamp edit's carried pixel GI (`gi_carry`): (indirect, direct, cache) of the passes
        #: before it, and the carried (indirect, direct) once the re-lit cache is solved.
        self.carry: tuple | None = None
        self.carried: tuple | None = None
        #: The traced rays of the view's last pixel pass that kept them (`PixelPass.traced`): a lamp
        #: edit's first pass shades them again (`reshade_due`) instead of tracing new ones.
        self.kept = None
        self.reshade_due = False
        #: (cache version, `pixel_gather.cache_side` at the GI points) made by a lamp edit's carry,
        #: which the re-shade over the same cache takes instead of gathering it again.
        self.relit_side = None
        #: Pixel passes are numbered from frame_base (their frames, so their directions); a lamp
        #: edit moves it past every number used (frames_used), so the passes after a re-shaded one
        #: never trace its directions again.
        self.frame_base = 0
        self.frames_used = 0
        #: The first pixel pass over the view's cache, rays in, resolve under way (`PendingGI`).
        self.pending = None
        self.carry_map: tuple | None = None  # (nearest GI point, flat pixel) of each textured pixel
        self.cell_colors: np.ndarray | None = None  # Cache Cells view, when the request asks
        self.cells_key = None
        self.cells_at = 0.0
        self.glossy: GlossyLevel | None = None  # made by the worker with the first fine pass
        #: The final render's glossy light at the direct light's pixels ((h, w, 4) radiance, a = 1
        #: on geometry: `glossy_image.frame_glossy`) and the cache and lighting it was made with.
        self.fine_glossy: np.ndarray | None = None
        self.fine_glossy_key = None
        #: The lamps' light of the draw's jittered subframes at the light edges (`EdgeLight`),
        #: traced once the full-res light and a pixel pass are in (`ViewportWorker._edge_pass`).
        self.edges = None
        self.dirty = False

    def fine_level(self) -> DirectLevel:
        if self._fine is None:
            r = self.request
            if r.direct_position is r.position:
                self._fine = self.coarse  # one resolution: the coarse pass is the first fine one
            else:
                points = _visible.pixels_to_points(r.direct_position, r.direct_normal)
                self._fine = DirectLevel(r.direct_position, r.direct_normal, points)
        return self._fine

    @property
    def passes(self) -> int:
        """Passes of the light that is published: fine once it has one, else the coarse one."""
        return self._fine.passes if self._fine is not None else 0

    def screen_light(self) -> ScreenLight | None:
        """The view's lamp light as the pixel rays' hits read it (`screen_light`): the fine level's
        once it has a pass, else the coarse one's (None before either has one). Why: the hits the
        camera sees then take the view's own lamp light, averaged over several samples, instead of
        one shadow ray per hit and lamp, as final renders shade them."""
        level = self._fine if self._fine is not None and self._fine.passes > 0 else self.coarse
        if level.passes == 0:
            return None
        points, normals, pix = level.points
        h, w = level.position.shape[:2]
        light = level.mean().reshape(-1, 4)[pix, :3]
        return ScreenLight.from_pixels(self.request.view, self.request.proj, (w, h), points, normals, pix, light)

    def relit(self, scene_gen: int, lamps: bool = True) -> None:
        """Lamps or diffuse colours changed and nothing else: the visible cells and the corner
        mask (geometry alone) stay; with `lamps` the direct light starts over (the worker traces
        its coarse pass at once), else (new colours only) the lamps' light at the pixels and its
        edges stay too. Saves the light move a new view's visible cells and mask (~0.1-0.2 s on 2
        busy cores), and a colour's edit the view's lamp passes as well."""
        self.scene_gen = scene_gen
        r = self.request
        if lamps:
            self.coarse = DirectLevel(r.position, r.normal, self.gi_points, self.coarse.samples)
            self._fine = None
            if self.glossy is not None:
                self.glossy.reset_lamps()  # the cache's part stays until the cache re-solves
            self.edges = None
        # The final render's glossy light reflects other surfaces (reflection rays): their colours.
        self.fine_glossy, self.fine_glossy_key = None, None
        if self.pixel_sum is not None and self.pixel_cache is not None:
            n = self.pixel_passes
            self.carry = (self.pixel_sum[0] / n, self.pixel_sum[1] / n, self.pixel_cache / n)
        # else: an edit before the last one's pixel pass carries the same passes again
        self.carried = None
        self.reset_pixels()
        # The pixels' rays hit what they hit before: the first pass shades a kept pass again.
        self.reshade_due = self.kept is not None
        self.relit_side = None
        self.frame_base = self.frames_used
        self.dirty = True

    def drop_pixel_pass(self) -> None:
        """Stop the pixel pass in flight, if any, wait for it and forget it (`PixelPass.drop`)."""
        if self.pixel_pass is not None:
            self.pixel_pass.drop()
            self.pixel_pass = None

    def reset_pixels(self) -> None:
        self.drop_pixel_pass()  # its rays were traced over what is reset
        self.pixel_sum, self.pixel_passes, self.pixel_key = None, 0, None
        self.pending = None
        self.pixel_next, self.pixel_cache = None, None

    def refines(self, key) -> bool:
        """Whether passes over `key` refine the shown ones: the same cache and lighting epoch,
        re-shaded further since (`ViewportWorker._pixel_key`). They are summed apart and
        replace the shown passes once there are as many, so the image never falls back to the
        gather meanwhile."""
        return (self.pixel_key is not None and self.pixel_sum is not None and key != self.pixel_key
                and key[:2] == self.pixel_key[:2])

    def passes_over(self, key) -> int:
        """Passes summed so far over `key`."""
        if self.refines(key):
            return self.pixel_next[1] if self.pixel_next is not None and self.pixel_next[2] == key else 0
        return self.pixel_passes

    def pass_number(self, key) -> int:
        """The next pass's number over `key` (its frames: `PixelPass.index`), counted as used."""
        number = self.frame_base + self.passes_over(key)
        self.frames_used = max(self.frames_used, number + 1)
        return number

    def add_pixels(self, indirect: np.ndarray, direct: np.ndarray, key, cache: np.ndarray) -> None:
        """One pixel-ray pass over the cache `key` (cache: its (n, 7) values at the GI points);
        a pass over another cache starts over, one over a refined cache is summed apart until it
        replaces the shown ones (`refines`)."""
        if self.refines(key):
            nxt = self.pixel_next if self.pixel_next is not None and self.pixel_next[2] == key else [None, 0, key, None]
            nxt[0] = [indirect.copy(), direct.copy()] if nxt[0] is None else [nxt[0][0] + indirect, nxt[0][1] + direct]
            nxt[3] = cache.copy() if nxt[3] is None else nxt[3] + cache
            nxt[1] += 1
            self.pixel_next = nxt
            if nxt[1] >= self.pixel_passes:
                self.pixel_sum, self.pixel_passes, self.pixel_key, self.pixel_cache = nxt[0], nxt[1], key, nxt[3]
                self.pixel_next = None
                self.dirty = True
            return
        if key != self.pixel_key:
            self.reset_pixels()
        self.pending = None  # resolved: the worker's own textures replace the draw's
        if self.pixel_sum is None:
            self.pixel_sum = [indirect.copy(), direct.copy()]
            self.pixel_cache = cache.copy()
        else:
            self.pixel_sum[0] += indirect
            self.pixel_sum[1] += direct
            self.pixel_cache += cache
        self.pixel_passes += 1
        self.pixel_key = key
        self.dirty = True

    def current(self, request: ViewRequest, scene_gen: int) -> bool:
        return request is self.request and scene_gen == self.scene_gen

    def result(self, serial: int) -> ViewResult:
        # The fine light replaces the coarse one once it is no noisier per pixel.
        fine = self._fine
        level = fine if fine is not None and fine.samples_per_pixel >= self.coarse.samples_per_pixel else self.coarse
        r = self.request
        gi = (None, None)
        pending = None
        if self.pixel_sum is not None:
            gi = (frozen(self.pixel_sum[0] / self.pixel_passes), frozen(self.pixel_sum[1] / self.pixel_passes))
        elif self.pending is not None:
            pending = self.pending  # the pass's own rays, resolved by the draw, before a carried image
        elif self.carried is not None:
            gi = self.carried  # a lamp edit's carried passes until its own pass (`gi_carry`)
        return ViewResult(
            key=r.key, serial=serial, scene_gen=self.scene_gen, position=level.position, normal=level.normal,
            view=r.view, proj=r.proj, direct=frozen(level.mean()), passes=level.passes,
            corner_mask=None if self.mask is None else frozen(self.mask.copy()),
            cells=None if self.cell_colors is None else frozen(self.cell_colors.copy()),
            gi_position=r.position, gi_normal=r.normal,
            gi_indirect=gi[0], gi_direct=gi[1], gi_pending=pending,
            pixel_passes=self.pixel_passes, edges=self.edges if level is fine else None,
            **self._glossy_fields(),
        )

    def _glossy_fields(self) -> dict:
        """The published glossy light: the final render's (`fine_glossy`) once made, else the GI
        pixels' running one."""
        if self.fine_glossy is not None:
            fine = self.fine_level()
            # Never written once made (a new one replaces it): published as it is.
            return dict(glossy=frozen(self.fine_glossy), glossy_position=fine.position,
                        glossy_normal=fine.normal, glossy_passes=self.glossy.passes if self.glossy is not None else 0)
        if self.glossy is None:
            return dict(glossy=None, glossy_position=None, glossy_normal=None, glossy_passes=0)
        return dict(glossy=frozen(self.glossy.image()), glossy_position=self.glossy.position,
                    glossy_normal=self.glossy.normal, glossy_passes=self.glossy.passes)
