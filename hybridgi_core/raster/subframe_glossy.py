"""The glossy light a jittered subframe's samples take: the centre raster's pixel's, or its
neighbour's where the subframe sees the neighbour's surface.

Why: final renders compute the glossy light once, at the centre raster's pixels
(`glossy_image.frame_glossy`), and each subframe added that pixel's light to whatever surface it
saw there. At a silhouette, the subframes that see an object in a pixel whose centre saw the
background or the floor behind took that pixel's glossy light, not the object's: a metal, whose
light is all glossy, lost its rim (the bright grazing crescent of a torus under an HDRI was one
pixel inside Cycles'), and a floor's pixel beside a chrome ball took the chrome's.

So where a subframe sees another surface than the centre did (`subpixel.subframe_surfaces`), its
sample takes the glossy light of the nearest neighbouring centre pixel on its surface
(`subpixel.same_surface`: 4-neighbours first, then the diagonals). Where no neighbour is (a thin
surface the centre raster missed), the neighbour with geometry whose normal is nearest the
sample's, if any faces its way; else the pixel's own, as before.

numpy only (no bpy, no gpu).
"""

from __future__ import annotations

import numpy as np

from .subpixel import same_surface

#: (dy, dx) of the neighbours searched, nearest first.
NEIGHBOURS = ((0, 1), (0, -1), (1, 0), (-1, 0), (1, 1), (1, -1), (-1, 1), (-1, -1))
#: Least cosine between a sample's normal and the fallback neighbour's (no neighbour on its surface).
FALLBACK_COS = 0.5


def subframe_glossy(glossy: np.ndarray, centre, hit: np.ndarray, same: np.ndarray, position: np.ndarray,
                    normal: np.ndarray, width: int) -> np.ndarray | None:
    """(h w, 4) float32 the glossy radiance a subframe adds per pixel, or None where it is the
    centre's `glossy` (h w, 4) at every pixel that matters (the subframe sees the centre's surface
    or nothing). centre : the frame's `subpixel.CentreSample`; hit, same : `subframe_surfaces`;
    position, normal : the subframe's read-backs ((h, w, 4), (h, w, >= 3)), normal the one
    `subframe_surfaces` compared (`subpixel.compared_normal`)."""
    need = np.flatnonzero(hit & ~same)
    if need.size == 0:
        return None
    n_pix = hit.shape[0]
    height = n_pix // width
    pos = position.reshape(n_pix, -1)[need]
    nrm = normal.reshape(n_pix, -1)[need, :3]
    y, x = np.divmod(need, width)
    c_pos, c_nrm, c_depth = centre.position, centre.surface_normal, centre.depth
    source = np.full(need.size, -1, np.int64)
    fallback = np.full(need.size, -1, np.int64)
    best_cos = np.full(need.size, FALLBACK_COS, np.float32)
    for dy, dx in NEIGHBOURS:
        inside = (source < 0) & (y + dy >= 0) & (y + dy < height) & (x + dx >= 0) & (x + dx < width)
        at = np.flatnonzero(inside)
        nb = need[at] + dy * width + dx
        geo = c_pos[nb, 3] > 0.5
        at, nb = at[geo], nb[geo]
        if at.size == 0:
            continue
        match = same_surface(c_pos[nb], c_nrm[nb], pos[at], nrm[at], c_depth[nb])
        source[at[match]] = nb[match]
        cos = np.einsum("ij,ij->i", c_nrm[nb, :3], nrm[at]).astype(np.float32)
        closer = ~match & (cos > best_cos[at])
        best_cos[at[closer]] = cos[closer]
        fallback[at[closer]] = nb[closer]
    source = np.where(source >= 0, source, fallback)
    moved = np.flatnonzero(source >= 0)
    if moved.size == 0:
        return None
    out = np.array(glossy, np.float32, copy=True)
    out[need[moved]] = glossy[source[moved]]
    return out
