"""The centre raster's direct light as jittered subframes reuse it: filtered over the pixel
filter's share that the subframes do not sample.

Why: a final render of K subframes resolves its film with a K-th of the filter's share of each
neighbour (`subpixel.reconstruction_taps`), because K jittered samples already sample the filter.
But a subframe's pixel that still sees the centre's surface reuses its own pixel's centre light
(`subpixel.subframe_direct`), wherever in the filter its jittered sample landed: on those pixels
the direct light is never spread over the filter, only by the K-th. So a soft shadow's remaining
noise came through at full strength with 2 subframes where one sample, filtered over its
neighbours, averaged it (dragon_npm 640x360 Diffuse Direct 0.029 at one subframe, 0.034 at two),
and the light was sharper than Cycles' filtered pixels. This module gives the reused light the
missing (1 - 1/K) of the share, on the pixel's own surface only (`subpixel.same_plane` between
neighbours), so a silhouette's other side, which the jitter itself mixes in, is not mixed twice.
Pixels on a light edge keep their own light: subframes trace them again.

Pure numpy: (h * w, c) planes in, the same shape out.
"""

from __future__ import annotations

import numpy as np

from .subpixel import SAME_COS, SAME_PLANE, neighbour_pairs, reconstruction_taps


def reuse_taps(count: int, filter_size: float, filter_type: str) -> np.ndarray:
    """(2 r + 1,) weights summing to 1: the filter's share of each neighbour that one sample gets
    (`reconstruction_taps(1)`) less the K-th the film already applies; [1] for K = 1 or a filter
    that keeps every pixel as it is."""
    one = reconstruction_taps(1, filter_size, filter_type)
    if one.size == 1 or count <= 1:
        return np.ones(1)
    taps = one * (1.0 - 1.0 / int(count))
    r = one.size // 2
    taps[r] = 0.0
    taps[r] = 1.0 - taps.sum()
    return taps


def filter_on_surface(light: np.ndarray, position: np.ndarray, normal: np.ndarray, depth: np.ndarray,
                      shape: tuple[int, int], taps: np.ndarray, keep: np.ndarray | None = None) -> np.ndarray:
    """light (h * w, c) float32 filtered separably by `taps` (odd length), each tap counted only
    where the neighbour lies on the pixel's surface: its normal within SAME_COS of the pixel's
    and its point within SAME_PLANE x view depth of the pixel's tangent plane (as a subframe's
    sample is told the centre's surface); the weights renormalised per pixel.

    position (h * w, >= 4) float32 (w = 1 on geometry), normal (h * w, >= 3) unit, depth (h * w,)
    the view depth. keep : (h * w,) bool pixels that keep their own light (light edges), or None.
    Pixels without geometry are neither read nor changed. Returns a new array."""
    light = np.asarray(light, np.float32)
    if taps.size == 1:
        return light.copy()
    h, w = shape
    geo = np.asarray(position[:, 3] > 0.5).reshape(h, w)
    pos = [np.ascontiguousarray(position[:, k], np.float32).reshape(h, w) for k in range(3)]
    nrm = [np.ascontiguousarray(normal[:, k], np.float32).reshape(h, w) for k in range(3)]
    reach = (np.float32(SAME_PLANE) * np.asarray(depth, np.float32)).reshape(h, w)
    out = np.where(geo[..., None], light.reshape(h, w, -1), np.float32(0.0))  # a background's NaN reads as 0
    r = taps.size // 2
    for axis in (0, 1):
        acc = out * np.float32(taps[r])
        total = np.full((h, w), np.float32(taps[r]))
        for k in range(1, r + 1):
            a, b = neighbour_pairs(axis, k)  # each pixel a and its neighbour b, k further along the axis
            d = [pos[j][b] - pos[j][a] for j in range(3)]  # once for the pair, read both ways
            both = geo[a] & geo[b]
            both &= (nrm[0][a] * nrm[0][b] + nrm[1][a] * nrm[1][b] + nrm[2][a] * nrm[2][b]) >= SAME_COS
            t = np.float32(taps[r + k])
            for me, other in ((a, b), (b, a)):
                plane = d[0] * nrm[0][me] + d[1] * nrm[1][me] + d[2] * nrm[2][me]
                wgt = (both & (np.abs(plane) <= reach[me])).astype(np.float32)
                wgt *= t
                acc[me] += wgt[..., None] * out[other]
                total[me] += wgt
        out = acc
        out /= total[..., None]
    out = out.reshape(light.shape)
    unchanged = ~geo.reshape(-1) if keep is None else ~geo.reshape(-1) | keep
    out[unchanged] = light[unchanged]
    return out

