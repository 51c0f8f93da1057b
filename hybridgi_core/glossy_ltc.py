"""The glossy lobes' light from area lamps in closed form, shadowed by the diffuse light's visibility.

Why: lamp sampling (`glossy_noise.adaptive_lamp_glossy`: 4 samples per pixel and lamp, 32 where
noisy, each with a shadow ray and the lobe's terms) was most of a glossy frame: 1.3 M samples,
~1.5 s of a core for bunny_npm at 640x360. Each lobe's unshadowed light from a polygonal lamp is
its albedo x the lamp's radiance x the integral of its linearly transformed cosine over the
polygon (`ltc.polygon_integral`; the lobe's Fresnel taken where that light arrives on average,
the rest of its albedo as `glossy._lobe_terms` has it); the shadows are the centre raster's
diffuse light of the same lamp over its exact unshadowed irradiance (`penumbra.adaptive_direct`'s
exact_out), exact wherever the lamp is wholly seen or wholly hidden.

What stays with lamp sampling (`closed_form`): penumbrae, lamps the receiver's horizon cuts and
grazing views (unless their light is dim), lamps other than area lamps (points, spots and suns are
small: few samples are exact), area lamps with a Spread below 180 degrees, collimated beams,
sheared lamps, lamps hidden from diffuse rays (no diffuse visibility to borrow), pixels whose
visibility is unknown (a weak lamp's single ray, the translucent back's blend), Beckmann lobes,
and lobes smoother than MIN_ROUGHNESS (a smooth lobe's highlight is the lamp's shape).

numpy only (no bpy).
"""

from __future__ import annotations

import numpy as np

from . import glossy, ltc, polygon_light
from .glossy_noise import NOISE
from .lights import _area_shape
from .pixel_gather import LUMA

#: Smoothest lobe (Blender roughness) whose area-lamp light is taken in closed form. The fit reads
#: a lamp's light within 3% down to 0.1 (against 400k area samples of the lobe: a 1 m lamp in
#: the mirror direction 0.965 / 0.941 at 0.1, 0.556 / 0.546 at 0.25); a chrome-like Glossy BSDF
#: 0.15 under a 2 m lamp had its highlight from reflection rays, speckled (160x90 Combined 0.177
#: against Cycles; 0.141 in closed form).
MIN_ROUGHNESS = 0.1
#: Most grazing view (its cosine to the normal) whose lamp light is taken in closed form.
MIN_VIEW_COSINE = 0.3
#: How far off the closed form is taken to read where it is not `trusted` (10-30% on a lamp the
#: horizon cuts or a grazing view, 2-3 x in a lobe's tail): such a pair is taken where this share
#: of its light is within the noise lamp sampling may leave. 1: where all of it is (640x360, r24
#: rung: dragon_npm Combined 0.0553 with lamp sampling alone, 0.0558 at 1, 0.0577 at 0.3; the
#: dragon's lamp samples 1.34 M -> 0.40 M).
UNTRUSTED_ERROR = 1.0
#: Visibility within this of 0 or 1 is a lamp wholly seen or hidden (the ratio estimator's
#: float32 rounding), where the diffuse light's visibility is the lobe's too.
SHARP = 1e-3
#: Most lamps whose per-lamp diffuse light a frame keeps for the closed form's visibility
#: (`direct_outputs`: (n, lamps, 3) float32 more); more take lamp sampling.
LAMP_LIMIT = 8
#: Receivers per pool job. 16k, not the glossy items' 128k rays (`reflection.CHUNK_RAYS`): its
#: float64 (n, 4) temporaries stay in the caches (160k receivers on two threads, alone: 97 ms in
#: 16k jobs, 128 in 64k); in the frame both read the same (bunny_npm r16, four alternating runs).
CHUNK = 1 << 14


def eligible_lamps(lights) -> np.ndarray:
    """(L,) bool: the area lamps whose glossy light the closed form gives (module docstring)."""
    out = np.zeros(len(lights), bool)
    for j, light in enumerate(lights):
        seen = light.for_glossy()
        if light.kind != "AREA" or float(light.power) <= 0.0 or float(seen.power) == 0.0:
            continue
        if float(light.spread) < np.pi or not np.isfinite(float(seen.power)):
            continue
        shape = _area_shape(light)
        out[j] = shape.area > 0 and shape.rectangular
    return out


def eligible_rows(mats) -> np.ndarray:
    """(m,) bool: the material rows whose every live lobe is GGX (single or multiple scattering)
    and at least MIN_ROUGHNESS rough."""
    live = np.abs(mats.k).sum(axis=(2, 3)) > 0  # (L, m)
    ok = ~live | (~mats.beckmann & (mats.lobe_rough >= MIN_ROUGHNESS))
    return ok.all(axis=0) & live.any(axis=0)


def direct_outputs(system, n: int, per_lamp: np.ndarray | None = None):
    """(exact, per_lamp): the outputs `penumbra.adaptive_direct` fills at n receivers for the
    closed form's `visibility` ((n, lamps) NaN-filled exact unshadowed irradiance; each lamp's
    light, the caller's per_lamp or a new (n, lamps, 3) with more than one lamp), or (None,
    per_lamp) where no lamp or material takes the closed form."""
    lights = system.scene.lights
    if not (0 < len(lights) <= LAMP_LIMIT and eligible_lamps(lights).any()
            and bool(getattr(system, "glossy_materials", None) is not None and system.glossy_materials.reflects.any()
                     and eligible_rows(system.glossy_materials).any())):
        return None, per_lamp
    if len(lights) > 1 and per_lamp is None:
        per_lamp = np.zeros((n, len(lights), 3), np.float32)
    return np.full((n, len(lights)), np.nan), per_lamp


def lamp_visibility(lights, light: np.ndarray, per_lamp: np.ndarray | None, exact: np.ndarray | None):
    """`visibility` from `adaptive_direct`'s light (n, 3) and the outputs of `direct_outputs`
    (None where it gave none)."""
    if exact is None:
        return None
    return visibility(per_lamp if len(lights) > 1 else light[:, None, :], exact, lights)


def visibility(lamp_light: np.ndarray, exact: np.ndarray, lights) -> np.ndarray:
    """(n, L) float32 each lamp's visibility at n receivers: its diffuse light's luminance
    (lamp_light (n, L, 3)) over its exact unshadowed irradiance (exact (n, L), colourless) times
    its colour's; 0 where it gives no light, NaN where its exact light is unknown (lamp sampling
    takes that pixel), at most 1."""
    colour = np.array([float(np.asarray(light.color, np.float64) @ LUMA) for light in lights])
    lum = lamp_light @ LUMA.astype(np.float32)
    with np.errstate(divide="ignore", invalid="ignore"):
        vis = lum / (exact * colour[None, :])
    vis = np.where(lum > 0, vis, 0.0)
    vis = np.where(np.isfinite(vis) | (lum <= 0), np.clip(vis, 0.0, 1.0), np.nan)
    return vis.astype(np.float32)


def closed_form(lights, mats, points, normals, to_eye, rows, vis: np.ndarray | None, skip: np.ndarray,
                level: np.ndarray, pool=None) -> tuple[np.ndarray, np.ndarray]:
    """((n, 3) float32 the glossy radiance towards the eye of the (receiver, lamp) pairs taken in
    closed form, (n, L) bool those pairs); lamp sampling takes the rest (`glossy_noise`).

    A pair is a candidate where its lamp and material are eligible, its visibility vis (n, L) is
    known (None: no pair) and `skip` (n, L) leaves it (the reflection rays' lamps). It is taken
    where the closed form is `trusted` and the lamp wholly seen or wholly hidden, or where its
    light is so dim against the pixel's lamp light (level (n,): the diffuse light's luminance,
    plus the closed forms') that UNTRUSTED_ERROR of it is within the noise lamp sampling leaves
    (`glossy_noise.NOISE`): a grazing view, where it reads 10-30% off.

    Why not in penumbrae (a visibility strictly between 0 and 1): the lobe weighs another part of
    the lamp than the diffuse cosine does. A metal floor at the edge of a ball's shadow under a 2 m
    lamp read 50% bright with the diffuse visibility (Glossy Direct 0.047 against Cycles, 0.029
    with lamp samples there). The lobe's own visibility from 16 shadow rays per pixel (shadowed
    over unshadowed lamp samples of one stream, filtered as lamp samples are) matched the metal
    but read bunny_npm's penumbrae noisier than lamp sampling does (Combined 0.0276 against 0.0271)."""
    n = points.shape[0]
    pairs = np.zeros((n, len(lights)), bool)
    if vis is None or n == 0:
        return np.zeros((n, 3), np.float32), pairs
    lamps = eligible_lamps(lights)
    ok_rows = eligible_rows(mats)
    good = (rows >= 0) & ok_rows[np.clip(rows, 0, ok_rows.size - 1)]
    pairs[:] = good[:, None] & lamps[None, :] & np.isfinite(vis) & ~skip
    # Only receivers whose every lamp could leave lamp sampling: one that samples another lamp
    # anyway saves little by one lamp fewer (morse_apartment samples its four round lamps at every
    # pixel; its area lamp's closed form cost 146 ms of a 1.3 s frame and saved no sampling time).
    sampled = ~(pairs | skip) & np.array([glossy.glows(lt.for_glossy()) for lt in lights])[None, :]
    pairs &= ~sampled.any(axis=1)[:, None]
    if not pairs.any():
        return np.zeros((n, 3), np.float32), pairs
    light = lamp_light(lights, mats, points, normals, to_eye, rows, vis, pairs, pool)  # (n, L, 3)
    lum = light @ LUMA.astype(np.float32)
    scale = np.asarray(level, np.float32).reshape(-1) + lum.sum(axis=1)
    dim = lum * np.float32(UNTRUSTED_ERROR) <= np.float32(NOISE) * scale[:, None]
    whole = (vis >= np.float32(1.0 - SHARP)) | (vis <= np.float32(SHARP))
    pairs &= (trusted(lights, normals, to_eye) & whole) | dim
    return np.einsum("nl,nlc->nc", pairs.astype(np.float32), light), pairs


def trusted(lights, normals: np.ndarray, to_eye: np.ndarray) -> np.ndarray:
    """(n, L) bool: where the closed form reads the lamp within a few percent: a view at least
    MIN_VIEW_COSINE from grazing (no LTC fits the lobe of a grazing view: the fit's L1 0.3-0.5;
    morse_apartment's floor seen at cos 0.07 read 22% off). A lamp the receiver's horizon cuts is
    trusted: `ltc.polygon_integral` clips it to the surface's horizon as well as to the fit's own
    (tilted) one, which read it 10-30% off unclipped (bunny_npm's facets under a lamp 1 m above
    the ears; random cut lamps: 6.0% -> 4.3% mean error, weighted by their light)."""
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    out = np.zeros((nrm.shape[0], len(lights)), bool)
    out[:] = (np.einsum("ij,ij->i", nrm, np.asarray(to_eye, np.float64).reshape(-1, 3)) >= MIN_VIEW_COSINE)[:, None]
    return out


def lamp_light(lights, mats, points, normals, to_eye, rows, vis: np.ndarray, pairs: np.ndarray,
               pool=None) -> np.ndarray:
    """(n, L, 3) float32 the glossy radiance towards the eye of each lamp of the (receiver, lamp)
    pairs (n, L) marks (0 elsewhere): per lobe, its albedo (the Fresnel where the light arrives)
    x lamp radiance x `ltc.polygon_integral`, times the lamp's visibility vis (n, L). pool :
    blocks of CHUNK receivers on it (the frame's pixel rays finish before the glossy light: the
    tail would run on one core)."""
    n = points.shape[0]
    if pool is None or n <= CHUNK:
        return _lamp_light(lights, mats, points, normals, to_eye, rows, vis, pairs)
    starts = range(0, n, CHUNK)
    jobs = [pool.submit(_lamp_light, lights, mats, *(a[s : s + CHUNK] for a in (points, normals, to_eye, rows, vis,
                                                                              pairs)))
            for s in starts]
    return np.concatenate([job.result() for job in jobs])


def _lamp_light(lights, mats, points, normals, to_eye, rows, vis, pairs) -> np.ndarray:
    n = points.shape[0]
    out = np.zeros((n, len(lights), 3), np.float32)
    mu = np.clip(np.einsum("ij,ij->i", normals, to_eye), 0.0, 1.0)
    for j, light in enumerate(lights):
        sel = np.flatnonzero(pairs[:, j] & (vis[:, j] > 0))
        if sel.size == 0:
            continue
        lamp = light.for_glossy()
        shape = _area_shape(lamp)
        polygon = polygon_light.lamp_polygon(shape.centre, shape.half_u, shape.half_v, shape.round)
        # The polygon faces the receivers on its emitting side only (one-sided lamps).
        front = ((points[sel] - shape.centre.astype(np.float64)) @ shape.normal.astype(np.float64)) > 0
        sel = sel[front]
        if sel.size == 0:
            continue
        radiance = float(lamp.power) / (np.pi * shape.area) * np.asarray(lamp.color, np.float64)
        r = rows[sel]
        total = np.zeros((sel.size, 3))
        for slot in range(mats.k.shape[0]):
            live = np.abs(mats.k[slot, r]).sum(axis=(1, 2)) > 0
            if not live.any():
                continue
            at, rl = sel[live], r[live]
            share, cos_hv = ltc.polygon_integral(polygon, points[at], normals[at], to_eye[at],
                                                 mats.lobe_rough[slot, rl])
            k, e = glossy.slot_coefficients(mats, slot, rl, np.maximum(mu[at], 1e-4))
            fresnel = np.einsum("mj,mjc->mc", glossy.fresnel_terms(mats, slot, rl, cos_hv), k)
            total[live] += (e * share)[:, None] * fresnel
        out[sel, j] = total * radiance[None, :] * vis[sel, j, None]
    return out
