"""Glossy lamp samples where a highlight is noisy: the lamps' glossy light of a final-render frame.

Why: the glossy lobes' lamp light (`glossy.glossy_direct`) took `glossy_samples` samples per pixel
and lamp everywhere, yet its noise sits in few pixels: highlights of lobes narrower than the lamp
and lamps half hidden behind the surface's own relief (the dragon's scales under its small area
lamp: there 16 samples left Combined 0.0499 against Cycles 16 spp + OIDN's 0.0487, 64 gave 0.0472).
A rough lobe under a lamp it sees whole varies little over the lamp: a few samples say what many
say. So a first pass takes FIRST_SAMPLES samples per pixel and lamp and measures each estimate's
variance from the spread of its samples (`glossy_direct(variance=)`); the pixels whose standard
error exceeds NOISE x the pixel's lamp light (its diffuse and glossy share), grown by DILATE
pixels (a noisy pixel whose few samples happened to agree is found through a neighbour's), take
`samples` new samples, and only those: the first pass chose them, so mixing its samples in would
bias the estimate towards whatever made it look noisy.

numpy only (no bpy).
"""

from __future__ import annotations

import numpy as np

from .lights import draw_lamps, rough_lights
from .penumbra import dilate, weak_lamps
from .pixel_gather import LUMA
from .reflection import lamp_glossy_without
from .sampling import frame_rng

#: Samples per pixel and lamp of the first pass, which finds the noisy pixels (and is the answer
#: everywhere else).
FIRST_SAMPLES = 4
#: Standard error of a pixel's first estimate, relative to its lamp light, above which it is
#: sampled again.
NOISE = 0.1
#: Pixels around a noisy pixel that are sampled again too.
DILATE = 1
#: Added to the frame number of the second pass's samples: a stream of its own.
SEED_OFFSET = 1 << 21
#: Added to the frame number of the weak lamps' one sample.
WEAK_SEED_OFFSET = 1 << 22
#: Added to the settings' seed for the draw of the weak lamp that takes that sample.
WEAK_PICK_SEED = 9


def adaptive_lamp_glossy(system, points, normals, to_eye, rows, pix: np.ndarray, shape: tuple[int, int],
                         frame: int, samples: int, skip: np.ndarray, level: np.ndarray,
                         widen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """((n, 3) float32 the lamps' glossy radiance at the pixels `pix` (flat indices into an image
    of `shape` (h, w)), (n,) bool the pixels that took `samples` samples per lamp; the others
    took FIRST_SAMPLES).

    points, normals, to_eye, rows, skip : as `reflection.lamp_glossy_without`'s. level : (n,)
    the luminance of the pixels' other lamp light (diffuse), the scale of the noise they tolerate.
    widen : optional (n,) alpha^2 the receivers' lobes gain (`specular_aa.footprint_alpha2`)."""
    n = np.asarray(points).reshape(-1, 3).shape[0]
    first = min(FIRST_SAMPLES, samples)
    if samples <= first or n == 0:
        return (lamp_glossy_without(system, points, normals, to_eye, rows, frame, samples, skip, widen=widen),
                np.ones(n, bool))
    # Lamps weak at a receiver (`penumbra.WEAK_SHARE` of its lamps' rough light) take one sample
    # of one of them there, never resampled (`_weak_lamps_light`): morse_apartment's four round
    # lamps beside its area lamp took 4-32 samples each per pixel for ~0.2% of its light.
    rough = rough_lights(system.scene.lights, points, normals) if len(system.scene.lights) > 1 else None
    weak = weak_lamps(rough)
    faint = np.zeros((n, 3), np.float32)
    if weak is not None:
        weak &= ~skip
        if weak.any():
            faint = _weak_lamps_light(system, points, normals, to_eye, rows, frame + WEAK_SEED_OFFSET, weak, rough,
                                      widen)
            skip = skip | weak
    variance = np.zeros(n, np.float32)
    light = lamp_glossy_without(system, points, normals, to_eye, rows, frame, first, skip, variance=variance,
                                widen=widen)
    light += faint
    scale = np.asarray(level, np.float32).reshape(-1) + light @ LUMA
    noisy = variance > np.square(np.float32(NOISE) * scale)
    if not noisy.any():
        return light, noisy
    h, w = shape
    image = np.zeros(h * w, bool)
    image[pix[noisy]] = True
    again = dilate(image.reshape(h, w), DILATE).reshape(-1)[pix]
    redo = np.flatnonzero(again)
    light[redo] = lamp_glossy_without(system, points[redo], normals[redo], to_eye[redo], rows[redo],
                                      frame + SEED_OFFSET, samples, skip[redo],
                                      widen=None if widen is None else widen[redo]) + faint[redo]
    return light, again


def _weak_lamps_light(system, points, normals, to_eye, rows, frame: int, weak: np.ndarray,
                      rough: np.ndarray, widen: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) float32 the glossy light of the lamps weak at each receiver (weak (n, L)): one
    sample of one of them, drawn in proportion to its rough light (rough (n, L),
    `lights.rough_lights`) and weighted by 1 / its probability. Unbiased; its noise stays within
    the weak lamps' small share of the receiver's light. Why one, not one sample of each:
    morse_apartment's four round lamps cost four lamp passes (156 ms of its 640x360 glossy light
    for ~0.2% of the light; one draw: ~50 ms)."""
    n, lamps = weak.shape
    out = np.zeros((n, 3), np.float32)
    r = np.where(weak, np.nan_to_num(np.asarray(rough, np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    np.maximum(r, 0.0, out=r)
    total = r.sum(axis=1)
    live = np.flatnonzero(total > 0)  # weak lamps with no rough light at all give no glossy light either
    if live.size == 0:
        return out
    p = (r[live] / total[live, None]).astype(np.float32)
    pick = draw_lamps(p, 1, frame_rng(system.settings.seed + WEAK_PICK_SEED, frame))[:, 0]
    at = np.arange(live.size)
    empty = p[at, pick] <= 0  # (a lamp that is not weak there: u at 0 or past the cdf's rounding)
    pick[empty] = np.argmax(p[empty], axis=1)
    chance = p[at, pick]
    skip = np.ones((live.size, lamps), bool)
    skip[at, pick] = False
    light = lamp_glossy_without(system, points[live], normals[live], to_eye[live], rows[live], frame, 1, skip,
                                widen=None if widen is None else widen[live])
    out[live] = light / chance[:, None]
    return out
