"""Depth of field of final renders: the camera's thin lens, sampled by the pixel filter's subframes.

Cycles' perspective camera with depth of field (`kernel/camera/camera.h`, `camera_sample_aperture`)
starts each camera ray at a point of the aperture, `lens_uv` = a uniform sample of the unit disk
(or of a regular polygon of `blades` corners turned by `rotation`), its x divided by the aperture
ratio, times the aperture radius, and aims it at the point where the pinhole ray meets the plane
of focus (camera depth = the focus distance). Every sample of a pixel takes another lens point.

A raster pass is a pinhole camera: moving its eye to the lens point (the view translated in the
camera's own x, y) and shifting its projection so that the plane of focus keeps its pixels (the
sheared frustum of an off-axis eye) renders exactly the rays Cycles shoots through that lens point.
The final render's jittered subframes (`subpixel.py`) each take one lens point, so their average is
Cycles' estimator with a stratified set of lens samples shared by every pixel (`lens_points`:
Hammersley points through the disk's or polygon's area-preserving map, paired with the pixel
offsets by another stratification, so the two patterns do not align). The unjittered centre raster
keeps the lens centre: the cache and the pixel rays light what the pinhole sees, and each
subframe resolves the surfaces its lens point sees anew where they differ (`subframe_surfaces`).

Orthographic cameras take no lens here (their rays do not converge; warned by the add-on).
Pure numpy; the add-on reads the camera (`addon/pipeline.camera_lens`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Subframes a frame with depth of field takes at least: its lens samples are what blurs the
#: out-of-focus surfaces (fewer show as ghost copies of them; Pixel Samples above this take more).
MIN_SUBFRAMES = 16
#: Circle of confusion (radius, pixels) below which no surface the camera sees is visibly blurred:
#: the frame keeps its own subframe count (a lens that barely blurs does not pay for 16).
SHARP_COC_PX = 1.0


@dataclass(frozen=True)
class Lens:
    """A perspective camera's thin lens, in Cycles' terms.

    radius : aperture radius, metres (Cycles' `aperturesize`: focal length / (2 f-stop))
    focus : distance of the plane of focus along the view axis, metres
    blades : aperture polygon corners (0: a disk; fewer than 3 is a disk, as in Cycles)
    rotation : the polygon's rotation, radians
    ratio : anamorphic ratio (the lens point's x is divided by it)
    """

    radius: float
    focus: float
    blades: int = 0
    rotation: float = 0.0
    ratio: float = 1.0

    def __post_init__(self) -> None:
        for name in ("radius", "focus", "rotation", "ratio"):
            if not math.isfinite(getattr(self, name)):
                raise ValueError(f"lens {name} must be finite, got {getattr(self, name)}")
        if self.radius < 0.0 or self.focus <= 0.0 or self.ratio <= 0.0:
            raise ValueError(f"lens radius must be >= 0, focus and ratio > 0 (got {self.radius}, "
                             f"{self.focus}, {self.ratio})")

    @property
    def active(self) -> bool:
        return self.radius > 0.0


def _radical_inverse3(i: np.ndarray) -> np.ndarray:
    """Base-3 radical inverse of integers i (the pixel offsets use base 2 for their y)."""
    i = np.asarray(i, np.int64).copy()
    out = np.zeros(i.shape, np.float64)
    scale = 1.0 / 3.0
    while np.any(i > 0):
        out += (i % 3) * scale
        i //= 3
        scale /= 3.0
    return out


def concentric_disk(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n, 2) points of the unit disk from (u, v) in [0, 1)^2 by Shirley's concentric map
    (area preserving: uniform in, uniform out; strata stay compact)."""
    a, b = 2.0 * np.asarray(u, np.float64) - 1.0, 2.0 * np.asarray(v, np.float64) - 1.0
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    safe_a = np.where(a == 0.0, 1.0, a)
    safe_b = np.where(b == 0.0, 1.0, b)
    phi = np.where(first, (math.pi / 4.0) * (b / safe_a), math.pi / 2.0 - (math.pi / 4.0) * (a / safe_b))
    phi = np.where((a == 0.0) & (b == 0.0), 0.0, phi)
    return np.stack([r * np.cos(phi), r * np.sin(phi)], axis=1)


def regular_polygon(u: np.ndarray, v: np.ndarray, corners: int, rotation: float) -> np.ndarray:
    """(n, 2) uniform points of the regular polygon of `corners` corners inscribed in the unit
    circle, turned by `rotation`, from (u, v) in [0, 1)^2 (as Cycles' regular_polygon_sample: u
    picks the triangle fan's sector and, rescaled, the point within it)."""
    u = np.asarray(u, np.float64) * corners
    sector = np.minimum(np.floor(u), corners - 1)
    u = u - sector
    step = 2.0 * math.pi / corners
    a0 = rotation + sector * step
    a1 = a0 + step
    # A uniform point of the triangle (centre, corner a0, corner a1).
    su = np.sqrt(u)
    s, t = su * (1.0 - np.asarray(v, np.float64)), su * np.asarray(v, np.float64)
    return np.stack([s * np.cos(a0) + t * np.cos(a1), s * np.sin(a0) + t * np.sin(a1)], axis=1)


def lens_points(count: int, lens: Lens) -> np.ndarray:
    """(count, 2) float64 lens points (camera x, y in metres) of the `count` subframes: a
    Hammersley set in another order than the pixel offsets' (x = the base-3 radical inverse,
    y = (i + 0.5) / count turned half a stratum), through the aperture's shape, scaled."""
    i = np.arange(int(count))
    u = np.mod(_radical_inverse3(i) + 0.5 / max(count, 1), 1.0)
    v = np.mod((i + 0.5) / max(count, 1) + 0.5, 1.0)
    unit = regular_polygon(u, v, lens.blades, lens.rotation) if lens.blades >= 3 else concentric_disk(u, v)
    unit[:, 0] /= lens.ratio
    return unit * lens.radius


def lens_view(view: np.ndarray, point) -> np.ndarray:
    """The (4, 4) float32 view (world to camera) of an eye moved to lens `point` (camera x, y)."""
    shift = np.eye(4)
    shift[0, 3], shift[1, 3] = -float(point[0]), -float(point[1])
    return (shift @ np.asarray(view, np.float64).reshape(4, 4)).astype(np.float32)


def focus_offset(proj: np.ndarray, point, lens: Lens, width: int, height: int) -> np.ndarray:
    """(2,) pixels to add to a subframe's jitter (`subpixel.jittered_projection`) so that the eye
    moved to lens `point` keeps the plane of focus on its pixels: seen from the moved eye, a point
    of that plane moves by -P00 point.x / focus in NDC x; a jitter of dx pixels moves NDC x by
    -2 dx / width, so dx = -P00 point.x width / (2 focus) undoes it (y alike)."""
    p = np.asarray(proj, np.float64).reshape(4, 4)
    return np.array([-p[0, 0] * float(point[0]) * width / (2.0 * lens.focus),
                     -p[1, 1] * float(point[1]) * height / (2.0 * lens.focus)])


def coc_pixels(lens: Lens, proj: np.ndarray, depth: np.ndarray, width: int) -> float:
    """The largest circle of confusion (radius, pixels) over view depths `depth` (metres along
    the view axis; non-finite or beyond 1e9: the background, ignored): radius x |1/d - 1/focus|
    in focal-length units, times P00 width / 2 (`focus_offset`'s scale)."""
    d = np.asarray(depth, np.float64).reshape(-1)
    d = d[np.isfinite(d) & (d > 0.0) & (d < 1e9)]
    if d.size == 0:
        return 0.0
    p00 = abs(float(np.asarray(proj, np.float64).reshape(4, 4)[0, 0]))
    spread = max(abs(1.0 / float(d.min()) - 1.0 / lens.focus), abs(1.0 / float(d.max()) - 1.0 / lens.focus))
    return float(lens.radius * spread * p00 * width / 2.0)


def subframes_for(lens: Lens | None, count: int, coc: float) -> int:
    """A frame's subframe count under `lens` (None: `count`): at least MIN_SUBFRAMES lens points
    where the largest circle of confusion `coc` (pixels, `coc_pixels`) is visible, else `count`."""
    if lens is None or coc < SHARP_COC_PX:
        return count
    return max(count, MIN_SUBFRAMES)


def centre_offsets(points: np.ndarray, pix: np.ndarray, width: int, height: int, view: np.ndarray,
                   proj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((n,), (n,)) float32 pixels from the centres of full-res pixels `pix` (flat) to where the
    centre raster (pinhole `view`, `proj`) sees points (n, 3): a lens subframe's sample of a
    pixel is a surface point the centre image shows elsewhere (by up to its circle of confusion),
    and the GI resolve reads the GI pixels around that place (`pixel_gather.GIResolver.at`)."""
    m = np.asarray(proj, np.float64).reshape(4, 4) @ np.asarray(view, np.float64).reshape(4, 4)
    p = np.asarray(points, np.float64).reshape(-1, 3)
    clip = p @ m[:3, :3].T + m[:3, 3]
    w = p @ m[3, :3] + m[3, 3]
    w = np.where(np.abs(w) > 1e-12, w, 1e-12)
    x = (clip[:, 0] / w * 0.5 + 0.5) * width - 0.5
    y = (clip[:, 1] / w * 0.5 + 0.5) * height - 0.5
    pix = np.asarray(pix, np.int64)
    return (x - pix % width).astype(np.float32), (y - pix // width).astype(np.float32)
