"""Lamp light at ray hits read from the image's own direct-light buffer where the camera sees them.

A pixel ray's hit is shaded with the lamps' irradiance at the hit (`lights.direct_irradiance`:
light samples and their shadow rays). In interiors most of those hits land on surfaces the camera
sees, whose lamp irradiance the frame has already computed per full-res pixel, with more samples,
the penumbra pass and the sun's disc (`penumbra.adaptive_direct`). A hit that projects onto a
pixel whose G-buffer sample lies on the same surface (within the pixel's footprint of the hit,
in its plane, with the same facing) takes that pixel's irradiance; the rest trace their own
shadow rays. Hits inside one pixel read one value (the light at the pixel's centre), which only
smooths light that varies within a pixel's footprint.

Why: the hits' shadow rays were a third of the pixel rays' time on lamp-lit rooms. Reading the
buffer is a projection and three gathers per hit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: A hit matches a pixel whose G-buffer sample lies within this many of the pixel's footprints of
#: it (the centre of a pixel is at most ~0.71 footprints from any point the pixel covers).
LATERAL_FOOTPRINTS = 1.5
#: ... and within this many footprints of its tangent plane (the same surface, not an occluder
#: or a wall behind it that the pixel happens to show).
PLANE_FOOTPRINTS = 0.25
#: ... and whose normal is within ~25 degrees of the hit's (a curved surface's normal turns within
#: a pixel; the lamp light with it).
NORMAL_COS = 0.9
#: Footprints never smaller than this share of the distance to the eye along the surface (grazing
#: views stretch a pixel along the surface; the lateral test divides by the cosine up to here).
MIN_COS = 0.2


@dataclass
class ScreenLight:
    """The frame's full-res lamp irradiance and the G-buffer it was computed at.

    view_proj : (4, 4) float64, world -> clip (column vectors, the G-buffer's projection)
    size : (width, height) of the image
    position, normal : (h * w, 3) float32, the G-buffer's centre samples (bottom-up rows)
    irradiance : (h * w, 3) float32 lamp irradiance at those samples
    valid : (h * w,) bool, pixels that hold geometry and a computed irradiance
    focal : |P[1, 1]| of the projection (a pixel's footprint is 2 w_clip / (focal h))
    """

    view_proj: np.ndarray
    focal: float
    size: tuple[int, int]
    position: np.ndarray
    normal: np.ndarray
    irradiance: np.ndarray
    valid: np.ndarray
    #: The frame's pixels sample the emissive triangles (`emitters.py`): the pixel rays leaving
    #: them drop what they find of those (`pixel_gather._chunk_shade`). `irradiance` never holds it.
    emitters_sampled: bool = False

    def __post_init__(self) -> None:
        # position | normal | irradiance in one (h w, 9) row per pixel: a hit reads one row (a
        # cache line or two) instead of three arrays of an image's size (the atrium's pixel-ray
        # shading 4% faster on one thread). `from_pixels` writes the three as views of one.
        base = self.position.base
        if not (base is not None and base.shape == (self.position.shape[0], 9) and base.flags.c_contiguous
                and self.normal.base is base and self.irradiance.base is base):
            base = np.ascontiguousarray(np.concatenate([self.position, self.normal, self.irradiance], axis=1),
                                        np.float32)
        self._rows = base

    @classmethod
    def from_pixels(cls, view: np.ndarray, proj: np.ndarray, size: tuple[int, int], points: np.ndarray,
                    normals: np.ndarray, pix: np.ndarray, irradiance: np.ndarray) -> ScreenLight:
        """From the flat G-buffer pixels (`visible.pixels_to_points`: points, normals, pix) and
        the irradiance (n, 3) computed at them."""
        w, h = size
        rows = np.zeros((h * w, 9), np.float32)
        position, normal, light = rows[:, 0:3], rows[:, 3:6], rows[:, 6:9]
        valid = np.zeros(h * w, bool)
        position[pix], normal[pix], light[pix], valid[pix] = points, normals, irradiance, True
        proj = np.asarray(proj, np.float64).reshape(4, 4)
        vp = proj @ np.asarray(view, np.float64).reshape(4, 4)
        return cls(vp, abs(float(proj[1, 1])), (int(w), int(h)), position, normal, light, valid)

    def lookup(self, points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(found (m,) int indices into points, irradiance (m', 3) float32 at them) for points
        (m, 3) with unit normals (m, 3): the hits whose surface the image shows (module
        docstring)."""
        w, h = self.size
        vp = self.view_proj.astype(np.float32)
        # Column by column: numpy's (m, 3) @ (3, k) is a BLAS call that costs ~10x this.
        cx, cy, cw = (points[:, 0] * vp[r, 0] + points[:, 1] * vp[r, 1] + points[:, 2] * vp[r, 2] + vp[r, 3]
                      for r in (0, 1, 3))
        ahead = cw > np.float32(1e-6)
        inv_w = np.where(ahead, np.float32(1.0) / np.where(ahead, cw, np.float32(1.0)), np.float32(0.0))
        x = (cx * inv_w + 1.0) * np.float32(0.5 * w)
        y = (cy * inv_w + 1.0) * np.float32(0.5 * h)
        inside = ahead & (x >= 0) & (x < w) & (y >= 0) & (y < h)
        cand = np.flatnonzero(inside)
        if cand.size == 0:
            return cand, np.zeros((0, 3), np.float32)
        idx = np.floor(y[cand]).astype(np.int64) * w + np.floor(x[cand]).astype(np.int64)
        keep = np.take(self.valid, idx)
        cand, idx = cand[keep], idx[keep]
        p, n = np.take(points, cand, axis=0), np.take(normals, cand, axis=0)
        g = np.take(self._rows, idx, axis=0)
        gp, gn = g[:, 0:3], g[:, 3:6]
        d = gp - p
        cos_n = np.einsum("ij,ij->i", gn, n)
        # The pixel's footprint at the hit: 2 w_clip / (P[1,1] h) (perspective and orthographic),
        # stretched along the surface by the view's grazing angle (up to 1 / MIN_COS).
        foot = np.float32(2.0 / (self.focal * h + 1e-30)) * np.take(cw, cand)
        foot = np.maximum(foot, np.float32(1e-7))
        plane = np.abs(np.einsum("ij,ij->i", d, gn))
        dist2 = np.einsum("ij,ij->i", d, d)
        lateral = np.float32(LATERAL_FOOTPRINTS / MIN_COS) * foot
        ok = np.flatnonzero((cos_n > np.float32(NORMAL_COS)) & (plane < np.float32(PLANE_FOOTPRINTS) * foot)
                            & (dist2 < lateral * lateral))
        return cand[ok], np.take(g, ok, axis=0)[:, 6:9]
