"""The viewport worker's per-pixel final gather of a still view, one slice of pixels a step
(worker thread only, pure numpy + embreex).

Final renders call `pixel_gather.gi_images` once per frame. A viewport pass of 32 rays at the GI
resolution costs 1-1.5 s on 2 busy cores, too long for one worker step: a lamp or camera edit
would wait for all of it. So the rays are traced in slices of SLICE_POINTS pixels, one slice a
step (`pixel_gather.trace_pixels`, each slice its own frame numbers), and the last step filters
the whole image's residual and makes the textures exactly as `gi_images` does from its rays
(`images`); a new view, a lamp edit or another cache drops the pass in progress.
"""

from __future__ import annotations

import numpy as np

from hybridgi_core import pixel_gather
from hybridgi_core.levels import hit_lookup
from hybridgi_core.settings import MULTI_BOUNCE

#: GI pixels per step of a pass (2 of `pixel_gather`'s work items at 32 rays, one per thread of
#: a 2-core pool: ~0.2 s a step on 2 busy cores; 8192 took 0.35-0.45 s).
SLICE_POINTS = 4096
#: Frame numbers per pass: slice i of pass k traces frame FRAME_BASE + k * FRAMES_PER_PASS + i.
FRAME_BASE = 1 << 24
FRAMES_PER_PASS = 1024


class PixelPass:
    """One pass in progress over the GI points of a view, against one cache version (`key`)."""

    def __init__(self, key, n_points: int, index: int, screen=None):
        self.key = key
        #: The view's lamp light the hits read where the camera sees them (`ViewState.screen_light`;
        #: None: every hit traces its own shadow rays), one for the whole pass.
        self.screen = screen
        self.index = index  # the pass's number among the view's passes (its frames)
        self.bounds = list(range(0, n_points, SLICE_POINTS)) + [n_points]
        self.parts: list[pixel_gather.PixelGI] = []
        #: The cache as the slices' hits read it, built once per pass (one per slice cost ~17 ms
        #: each on the Cornell box's 48^3 grid, a fifth of a slice).
        self.lookup = None

    @property
    def done(self) -> bool:
        return len(self.parts) >= len(self.bounds) - 1

    @property
    def frame(self) -> int:
        """The frame number of the pass's first slice (its detail pixels draw from frame + DETAIL_FRAME)."""
        return FRAME_BASE + self.index * FRAMES_PER_PASS

    def trace_next(self, system, points, normals, visible, rays: int, pix=None, width: int = 0) -> int:
        """Trace the next slice; returns its rays. pix, width : the points' flat pixel indices in
        the GI image and its width: the slices' rays stratify with their neighbours' across the
        whole pass (`tiled_nets`, one key per pass)."""
        i = len(self.parts)
        a, b = self.bounds[i], self.bounds[i + 1]
        if self.lookup is None and rays > 0:
            self.lookup = hit_lookup(system, bounced=system.settings.indirect_quality == MULTI_BOUNCE)
        tiles = None if pix is None else (pix[a:b], width, self.frame)
        gi = pixel_gather.trace_pixels(system, points[a:b], normals[a:b], rays, self.frame + i, visible[a:b],
                                       lookup=self.lookup, pixels=tiles, screen=self.screen)
        self.parts.append(gi)
        return gi.rays

    def gathered(self) -> pixel_gather.PixelGI:
        """The slices as one `PixelGI` over every point."""
        cat = lambda name: np.concatenate([getattr(p, name) for p in self.parts])  # noqa: E731
        return pixel_gather.PixelGI(cat("direct"), cat("indirect"), cat("ao"), cat("cache_direct"),
                                    cat("cache_indirect"), cat("cache_ao"), variance=cat("variance"),
                                    indirect_variance=cat("indirect_variance"), sh=cat("sh"),
                                    rays=sum(p.rays for p in self.parts))


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


def full_res(system, pass_: PixelPass, position_lo: np.ndarray, pix: np.ndarray, points: np.ndarray,
             normals: np.ndarray, view: np.ndarray, rays: int, full: tuple, full_shape: tuple[int, int],
             raster) -> pixel_gather.FullResGI:
    """A whole image's rays resolved at every full-res pixel as final renders resolve theirs
    (`pixel_gather.full_res_resolve`); full : (points, normals, flat pixels) of the full-res
    G-buffer of shape full_shape (h, w). The detail pixels' rays are traced here."""
    h, w = full_shape
    return pixel_gather.full_res_resolve(
        system, pass_.gathered(), position_lo, pix, points, normals, view, pass_.frame, rays, full[0], full[1],
        full[2], (w, h), passes=raster.pixel_filter, plane_sigma=raster.bilateral_plane_sigma,
        normal_power=raster.bilateral_normal_power, lookup=pass_.lookup, screen=pass_.screen)
