"""Specular antialiasing: a glossy lobe widened by the spread of its pixel's normals.

Why: final renders and the viewport compute the glossy light once per pixel, at the centre
raster's sample (`glossy_image.begin_glossy`); Cycles averages it over the pixel. On a curved
surface a highlight smaller than a pixel is then all or nothing: the sun's reflection in a coated
ball (roughness 0.05) read 1179 in one pixel against Cycles' 142, one pixel making 60% of a
320x180 image's Combined error, and a roughness-0.3 torus's highlight peaks 30% bright.

The cure is Tokuyoshi and Kaplanyan's ("Improved geometric specular antialiasing", I3D 2019):
the normals a pixel covers spread its microfacet distribution, so its lobe's alpha^2 grows by
2 sigma^2 (|dn/dx|^2 + |dn/dy|^2), at most KAPPA, with dn/dx and dn/dy the normal's change per
pixel and sigma^2 the variance of the area the sample stands for. Here that area is the pixel's
box (sigma^2 = 1/12): the film's reconstruction filter already spreads each pixel's light over
its neighbours (`subpixel.reconstruction_taps`). A lobe's light integrates to its albedo at any
width, so widening moves a highlight's energy within the pixel's reach and keeps it.

The lamps' glossy samples take the whole widening (`glossy.glossy_direct`'s widen); the
reflection rays' lobes RAY_WIDEN_SHARE of it (`widened_roughness`), since their filter spreads
their light over the surface's neighbours as well.

The change per pixel is the smaller of the two one-sided differences along each axis to a
neighbour with geometry: a pixel beside a crease or a silhouette keeps its own side's curvature,
not the jump to the other surface.

numpy only (no bpy).
"""

from __future__ import annotations

import numpy as np

#: Variance (pixels^2, per axis) of the area a centre sample stands for: the pixel's box.
SIGMA2 = 1.0 / 12.0
#: Share of a pixel's added alpha^2 the reflection rays' lobes take (`glossy_image.begin_glossy`):
#: their light is filtered over neighbours on the surface (`reflection.filter_reflections`), which
#: spreads it too. HDRI probes at 320x180 against Cycles 1024 spp, share 0 / 0.25 / 0.5 / 1: a
#: coated ball (roughness 0.05) 0.0295 / 0.0276 / 0.0268 / 0.0260 (the stripes along its bright
#: grazing rim), with a metal torus 0.0474 / 0.0461 / 0.0455 / 0.0457, a smooth ball 0.0201 /
#: 0.0197 / 0.0199 / 0.0206.
RAY_WIDEN_SHARE = 0.5
#: Most alpha^2 a pixel's normals add (Tokuyoshi and Kaplanyan's clamp): a crease's or a normal
#: map's jump within a pixel blurs its highlights, not turns them diffuse.
KAPPA = 0.18


def footprint_alpha2(normals: np.ndarray, pix: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(n,) float32 the alpha^2 the spread of the normals within each pixel adds to its lobes.
    normals : (n, 3) unit normals at the image pixels `pix` (n,) (flat indices into an image of
    `shape` (h, w)); the other pixels have no geometry."""
    h, w = shape
    n = np.asarray(normals, np.float32).reshape(-1, 3)
    pix = np.asarray(pix, np.int64).reshape(-1)
    image = np.full((h * w, 3), np.nan, np.float32)
    image[pix] = n
    image = image.reshape(h, w, 3)
    total = np.zeros((h, w), np.float32)
    for axis in (0, 1):
        total += _least_change2(image, axis)
    add = np.minimum(np.float32(2.0 * SIGMA2) * total, np.float32(KAPPA))
    return add.reshape(-1)[pix]


def _least_change2(image: np.ndarray, axis: int) -> np.ndarray:
    """(h, w) the squared change of the normal per pixel along `axis` of an (h, w, 3) image (NaN:
    no geometry): the smaller one-sided difference where both neighbours have geometry, the one
    there is where only one has, 0 where neither has."""
    step = np.diff(image, axis=axis)
    sq = (step * step).sum(axis=-1)  # NaN where either pixel has no geometry
    pad = [(0, 0), (0, 0)]
    pad[axis] = (1, 0)
    before = np.pad(sq, pad, constant_values=np.nan)
    pad[axis] = (0, 1)
    after = np.pad(sq, pad, constant_values=np.nan)
    least = np.fmin(before, after)  # the other where one is NaN
    return np.nan_to_num(least, nan=0.0).astype(np.float32)


def widened_roughness(rough: np.ndarray, add: np.ndarray) -> np.ndarray:
    """(n,) float32 the roughness (Blender's: alpha = roughness^2) of lobes of roughness `rough`
    whose alpha^2 grows by `add` (n,), at most 1; `rough` itself where nothing is added."""
    rough = np.asarray(rough, np.float32)
    add = np.asarray(add, np.float32)
    wide = np.minimum(rough**4 + add, np.float32(1.0)) ** np.float32(0.25)
    return np.where(add > 0, np.maximum(wide, rough), rough).astype(np.float32)
