"""Glossy reflections by rays: what a smooth glossy lobe mirrors, per pixel.

`glossy.cache_reflection` reflects the hemisphere's mean incident radiance (split sum): a polished
floor or a metal then shows no image of the room, only its average colour, and even a rough lobe
ignores the view and the Fresnel. Here a pixel whose lobe is smoother than TRACE_ROUGHNESS traces
`rays` reflection rays,
sampled from the GGX distribution of visible normals (Heitz, JCGT 2018) about its view
direction, and shades their hits as the pixel rays shade theirs (`pixel_gather.hit_radiance`:
the world or an emitter straight along the ray; else the hit's lamp light through shadow rays
plus the cache read there, times its albedo).

Each sample weighs G2(v, l) / G1(v) (the VNDF estimator of the lobe's reflectance without its
Fresnel term) times its lobes' Fresnel (`glossy.traced_fresnel`), and the two returned radiances
are the weighted means: Cycles' Glossy Color holds the lobes' albedo, so Glossy Direct / Indirect
are their Fresnel-weighted mean incident light. The split between them is Cycles': light straight
from the world or an emitter is direct, light of other surfaces indirect. Between
TRACE_ROUGHNESS / 2 and TRACE_ROUGHNESS the traced estimate would blend into the cache's; every
lobe (roughness at most 1) is now traced wholly.

Area lamps in sharp lobes: sampling the lamp (`glossy.glossy_direct`) finds a lobe much narrower
than the lamp only rarely, and then with a huge BRDF value (a chrome ball's highlight is speckled,
pixels 20x too bright beside black ones). Where a lamp's solid angle exceeds BSDF_LAMP_RATIO times
the lobe's, the reflection rays that meet the lamp (unblocked: nearer than their geometry hit)
bring its radiance instead, and lamp sampling skips that lamp at that pixel (`bsdf_lamps`,
`lamp_glossy_without`): each lamp is estimated once per pixel, by whichever sampling suits it.

numpy + embreex only (bpy-free); `raster/frame.py` calls it for the centre raster's pixels.
"""

from __future__ import annotations

import numpy as np

from . import glossy as glossy_mod
from .camera import camera_position
from .lights import GLOSSY_LAMP_BUDGET, _area_shape, _onb, spread_attenuation, stratified_uv
from .pixel_gather import filter_at_pixels, hit_radiance
from .rows import row_patterns
from .sampling import frame_rng
from .specular import _lambda
from .tiled_nets import tiled_uv

_F32 = np.float32
#: Lobes at least this rough keep the cache's hemisphere mean (`glossy.cache_reflection`); from
#: half of it the traced estimate blends into that mean (`traced_share`). 2: every lobe (roughness
#: at most 1) is traced wholly, the cache's mean kept only where a receiver's rays found nothing.
#: Why: the mean about the normal ignores the view and the Fresnel; 1.0 (blending from roughness
#: 0.5) read a floor of roughness 0.8 under city.exr, 160x90 against 512 spp, Glossy Direct
#: 0.326 (+32%; traced: 0.043), roughness 1.0 0.207 -> 0.039, a metal floor and wall of
#: roughness 1.0 Combined 0.062 -> 0.037 (at 0.8 0.021 -> 0.029, its only loss), for no more
#: rays below roughness 1 (they were traced for the blend).
TRACE_ROUGHNESS = 2.0
#: Seed offset of the reflection rays' stream (pixel rays use 2, the direct light 1).
SEED_OFFSET = 3
#: Pixels x rays per work item (fixed: the result does not depend on the thread count). 128k, not
#: 32k: fewer GIL hand-overs (`pixel_gather.CHUNK_RAYS`; the glossy step of bunny_npm's r16 rung
#: 1.35 -> 1.18 s with `glossy.CHUNK`).
CHUNK_RAYS = 131072
#: An area lamp is sampled by the reflection rays (not by lamp sampling) at pixels where its solid
#: angle exceeds this many times the lobe's (~4 pi alpha^2: the reflected cone of the GGX lobe).
#: 2 gave roughness-0.3 lobes under a 2 m lamp to 4 rays (glass Glossy Direct 0.17 -> 0.49 vs
#: Cycles); 16 keeps those to lamp sampling (0.16) and still sends a roughness-0.1 chrome ball's
#: lamp (ratio ~150) to the rays.
BSDF_LAMP_RATIO = 16.0
#: Directions drawn from the sky map's power per receiver (`SkySampler`), weighed against the
#: lobe's own samples by multiple importance sampling (`_sky_mis`), where the world has a map.
SKY_SAMPLES = 2
#: A-trous passes over the traced light (`filter_reflections`), taps 1 and 2 pixels apart: a rough
#: floor's reflection of a bright sky is smooth over many pixels, and 8 rays each under one pass
#: left it blotchy. The lobe-width term (`reflection_power`) keeps curved sharp lobes from that
#: reach, but not a flat floor's view turning across the image, which the normals do not show: a
#: third pass (taps 4 pixels apart) blurred a grazing floor's reflection at 64x48
#: (`test_reflection_rays_weigh_their_light_by_the_fresnel` 0.040) and morse_apartment's. HDRI
#: probes at 320x180 against Cycles 1024 spp, passes 1 / 2 / 3: a ball on a roughness-0.6 floor
#: 0.0325 / 0.0225 / 0.0199, with a metal torus 0.0586 / 0.0466 / 0.0455, a coated ball 0.0293 at 2
#: (0.0268 at 3); morse_apartment r32 0.04671 at 3, 0.04603 at 2.
FILTER_PASSES = 2
#: The filter's normal exponent for lobes so rough that the lobe-width term is weaker (as the
#: pixel rays' filter has it).
FILTER_NORMAL_POWER = 8.0
#: A tap's normal weight max(0, n_p . n_q)^p, p = REFLECTION_SHARPNESS / alpha^2, falls to 1/e where
#: the normals part by alpha / sqrt(2): a neighbour whose mirror direction is ~1.4 lobe widths
#: away no longer counts. Why: with one exponent (8) a metal torus (roughness 0.3) under an HDRI
#: spread its bright grazing crescent a pixel inwards and dimmed it; 3 passes of it read the torus
#: 0.022 -> 0.073 of Combined. Measured on that probe (3 passes then): 2 -> 0.0245, 4 -> 0.0197,
#: 8 -> 0.0201, 16 -> 0.0233.
REFLECTION_SHARPNESS = 4.0
#: Lobes at least this rough have their lamp-sampled Glossy Direct filtered (`filter_lamp_glossy`):
#: their highlights span many pixels; a smoother lobe's small sharp highlight keeps its pixels.
LAMP_FILTER_ROUGHNESS = 0.45


def traced_share(rough: np.ndarray) -> np.ndarray:
    """(n,) weight of the traced estimate against the cache's: 1 up to TRACE_ROUGHNESS / 2,
    falling linearly to 0 at TRACE_ROUGHNESS."""
    half = 0.5 * TRACE_ROUGHNESS
    return np.clip((TRACE_ROUGHNESS - np.asarray(rough, np.float64)) / half, 0.0, 1.0)


def sample_reflections(normals: np.ndarray, to_eye: np.ndarray, rough: np.ndarray, u: np.ndarray,
                       v: np.ndarray, with_cos: bool = False) -> tuple[np.ndarray, ...]:
    """Reflection directions (m, s, 3) float32 and weights G2 / G1 (m, s) (0 below the horizon)
    of GGX lobes of roughness `rough` (m,) (alpha = rough^2, as Cycles maps it) at unit normals
    and view directions (m, 3), from uniform numbers u, v (m, s): Heitz's visible-normal sampling,
    in float32 as Cycles' kernel takes it (float64 cost twice the time: a third of the reflection
    rays' CPU). with_cos : also (m, s) the cosine between the view and each sample's microfacet
    normal (the Fresnel's angle)."""
    n = np.asarray(normals, _F32)
    e = np.asarray(to_eye, _F32)
    t1, t2 = _onb(n[:, 0:1], n[:, 1:2], n[:, 2:3])
    t1 = np.concatenate(t1, axis=1)
    t2 = np.concatenate(t2, axis=1)
    # The view in the pixel's frame (z = normal), stretched by the roughness.
    alpha = np.maximum(np.asarray(rough, _F32), _F32(1e-3)) ** 2
    dot = lambda a, b: a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]  # noqa: E731
    vx, vy, vz = dot(e, t1), dot(e, t2), np.maximum(dot(e, n), _F32(1e-4))
    sx, sy = alpha * vx, alpha * vy
    length = np.sqrt(sx * sx + sy * sy + vz * vz)
    hx, hy, hz = sx / length, sy / length, vz / length
    lensq = hx * hx + hy * hy
    inv = np.where(lensq > 0, 1.0 / np.sqrt(np.maximum(lensq, 1e-30)), 0.0)
    ax, ay = np.where(lensq > 0, -hy * inv, 1.0), np.where(lensq > 0, hx * inv, 0.0)  # T1 (z = 0)
    bx, by, bz = -hz * ay, hz * ax, hx * ay - hy * ax  # T2 = Vh x T1
    col = lambda a: a[:, None]  # noqa: E731
    r = np.sqrt(np.asarray(u, _F32))
    phi = _F32(2.0 * np.pi) * np.asarray(v, _F32)
    p1, p2 = r * np.cos(phi), r * np.sin(phi)
    s = col(0.5 * (1.0 + hz))
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * p2
    p3 = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    mx = p1 * col(ax) + p2 * col(bx) + p3 * col(hx)
    my = p1 * col(ay) + p2 * col(by) + p3 * col(hy)
    mz = p2 * col(bz) + p3 * col(hz)
    # Unstretch: the microfacet normal in the pixel's frame.
    mx, my, mz = col(alpha) * mx, col(alpha) * my, np.maximum(mz, 0.0)
    norm = np.sqrt(mx * mx + my * my + mz * mz)
    mx, my, mz = mx / norm, my / norm, mz / norm
    cos_vm = col(vx) * mx + col(vy) * my + col(vz) * mz
    lx, ly, lz = 2.0 * cos_vm * mx - col(vx), 2.0 * cos_vm * my - col(vy), 2.0 * cos_vm * mz - col(vz)
    alpha2 = col(alpha * alpha)
    lam_v = _lambda(alpha2, col(vz))
    weight = np.where(lz > 0, (1.0 + lam_v) / (1.0 + lam_v + _lambda(alpha2, np.maximum(lz, 1e-6))), 0.0)
    # The direction in world space, one component plane at a time: (m, s, 3) broadcasts and a
    # norm over the last axis of 3 cost ~4x these plane operations.
    comps = [lx * col(t1[:, k]) + ly * col(t2[:, k]) + lz * col(n[:, k]) for k in range(3)]
    inv = 1.0 / np.maximum(np.sqrt(comps[0] * comps[0] + comps[1] * comps[1] + comps[2] * comps[2]), 1e-30)
    world = np.empty(lx.shape + (3,), _F32)
    for k in range(3):
        np.multiply(comps[k], inv, out=world[..., k], casting="same_kind")
    if with_cos:
        return world, weight.astype(_F32), np.clip(cos_vm, 0.0, 1.0).astype(_F32)
    return world, weight.astype(_F32)


def bsdf_lamps(lights, points: np.ndarray, normals: np.ndarray, rough: np.ndarray,
               to_eye: np.ndarray | None = None) -> np.ndarray:
    """(n, L) bool: which of the L lamps the reflection rays of each receiver estimate (area lamps
    facing it whose solid angle exceeds BSDF_LAMP_RATIO x its lobe's; the module docstring). With
    `to_eye` (n, 3), only where the lamp lies within the lobe's core (`_in_core`)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    out = np.zeros((pts.shape[0], len(lights)), bool)
    alpha = np.asarray(rough, np.float64).reshape(-1) ** 2
    lobe = 4.0 * np.pi * alpha * alpha
    for j, light in enumerate(lights):
        light = light.for_glossy()
        if light.kind != "AREA" or float(light.power) == 0.0 or float(light.spread) <= 0.0:
            continue  # a Spread-0 lamp is a collimated beam: lamp sampling finds it
        shape = _area_shape(light)
        if shape.area <= 0:
            continue
        to = shape.centre.astype(np.float64)[None, :] - pts
        d2 = np.maximum((to * to).sum(1), 1e-12)
        cos_l = -(to @ shape.normal.astype(np.float64)) / np.sqrt(d2)  # > 0: the receiver faces its front
        facing = (cos_l > 0) & ((to * nrm).sum(1) > -np.sqrt(shape.area))
        big = facing & (shape.area * np.maximum(cos_l, 0.0) / d2 > BSDF_LAMP_RATIO * lobe)
        if to_eye is not None:
            # Only where the lamp is big enough: most receivers' lobes are far wider than any lamp.
            rows = np.flatnonzero(big)
            v, nr = np.asarray(to_eye, np.float64).reshape(-1, 3)[rows], nrm[rows]
            mirror = 2.0 * (v * nr).sum(1, keepdims=True) * nr - v
            big[rows] = _in_core(mirror, to[rows], d2[rows], shape.area, alpha[rows])
        out[:, j] = big
    return out


#: Lobe widths (2 alpha, radians) beyond a lamp's edge within which its reflection rays estimate it.
CORE_WIDTHS = 2.0


def _in_core(mirror: np.ndarray, to: np.ndarray, d2: np.ndarray, area: float, alpha: np.ndarray) -> np.ndarray:
    """(n,) bool: receivers whose mirror direction (n, 3) points at the lamp (centre `to` (n, 3)
    away, squared distance d2, area) or within CORE_WIDTHS lobe widths of its edge. Why: in a
    sharp lobe's tail the rays meet the lamp once in many pixels, each meeting weighing the lamp's
    full radiance over the ray count: a chrome ball's highlight sat in a halo of white specks
    reaching 15 pixels out (Glossy BSDF 0.15 under a 2 m lamp, 160x90 Combined 0.177 against
    Cycles, C16 0.077), where lamp sampling, smooth across the lamp there, needs few samples."""
    cos = (mirror * to).sum(1) / np.sqrt(d2) / np.maximum(np.linalg.norm(mirror, axis=1), 1e-12)
    angle = np.arccos(np.clip(cos, -1.0, 1.0))
    radius = np.arctan(np.sqrt(area / np.pi) / np.sqrt(d2))
    return angle <= radius + CORE_WIDTHS * 2.0 * alpha


def lamp_glossy_without(system, points, normals, to_eye, rows, frame: int, samples: int,
                        skip: np.ndarray, variance: np.ndarray | None = None,
                        widen: np.ndarray | None = None) -> np.ndarray:
    """(n, 3) the lamps' glossy radiance by lamp sampling (`GISystem.glossy`), each receiver
    without the lamps `skip` (n, L) marks for it (the reflection rays estimate those).
    variance : an optional (n,) output, the estimate's luminance variance (`glossy.glossy_direct`).
    widen : optional (n,) alpha^2 the receivers' lobes gain (`specular_aa.footprint_alpha2`)."""
    n = np.asarray(points).reshape(-1, 3).shape[0]
    if not skip.any():
        return system.glossy(points, normals, to_eye, rows, frame, samples=samples, variance=variance, widen=widen)
    if len(system.scene.lights) > GLOSSY_LAMP_BUDGET:
        # Many lamps: one pass whose draws per receiver are among the lamps it keeps. A call per
        # pattern of skipped lamps (below) met ~1300 patterns over 50 lamps, each a picked pass of
        # its own: a room lit by 50 point lamps spent 36 s of CPU there in a 47-s profiled 320x180 render.
        return system.glossy(points, normals, to_eye, rows, frame, samples=samples, variance=variance,
                             allowed=~np.asarray(skip, bool), widen=widen)
    out = np.zeros((n, 3), _F32)
    if variance is not None:
        variance[:] = 0.0
    # One call per set of skipped lamps, with the lamps it leaves: the closed form (`glossy_ltc`)
    # skips an area lamp at most receivers, and a call per lamp cost morse_apartment's four round
    # lamps four passes over the same receivers.
    patterns, inverse = row_patterns(skip)
    for k, pattern in enumerate(patterns):
        if pattern.all():
            continue
        sel = np.flatnonzero(inverse == k)
        lights = None if not pattern.any() else [light for light, s in zip(system.scene.lights, pattern, strict=True)
                                                 if not s]
        var = None if variance is None else np.zeros(sel.size, _F32)
        out[sel] = system.glossy(points[sel], normals[sel], to_eye[sel], rows[sel], frame, samples=samples,
                                 lights=lights, variance=var, widen=None if widen is None else widen[sel])
        if var is not None:
            variance[sel] = var
    return out


def traced_reflection(system, lookup, points: np.ndarray, normals: np.ndarray, to_eye: np.ndarray,
                      rough: np.ndarray, rays: int, frame: int, lamps: np.ndarray | None = None,
                      pixels: tuple[np.ndarray, int] | None = None, screen=None, rows: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(direct (n, 3), indirect (n, 3), weight sum (n,), lamp (n, 3)) float32: the mean radiance
    `rays` reflection rays per receiver bring from the world or emitters, from other surfaces and
    from the area lamps `lamps` (n, L) marks for it (`bsdf_lamps`; None: none), on the worker
    pool. A receiver whose samples all went below the horizon has weight sum 0 (its estimate is
    0: keep the cache's there). pixels : (pix (n,), width) the receivers' flat pixel indices in an
    image `width` wide: each tile's rays stratify together (`tiled_nets`), for the image filter.
    screen : the frame's `screen_light.ScreenLight` or None: hits the image shows read their lamp
    light there (`pixel_gather.hit_radiance`), others trace their own shadow rays. rows : (n,)
    the receivers' rows of `system.glossy_materials`: each sample is weighed by its lobes' Fresnel
    (`glossy.traced_fresnel`), as Cycles' passes weigh their light; None: by G2 / G1 alone."""
    pts = np.ascontiguousarray(points, _F32).reshape(-1, 3)
    n = pts.shape[0]
    out = np.zeros((n, 10), _F32)
    if n == 0 or rays <= 0:
        return out[:, 0:3], out[:, 3:6], out[:, 6], out[:, 7:10]
    nrm = np.ascontiguousarray(normals, _F32).reshape(-1, 3)
    eye = np.ascontiguousarray(to_eye, _F32).reshape(-1, 3)
    rough = np.asarray(rough, np.float64).reshape(-1)
    per = max(1, CHUNK_RAYS // rays)
    starts = range(0, n, per)
    seed = system.settings.seed + SEED_OFFSET
    lights = system.scene.lights
    if lamps is None or not lamps.any():
        lamps = None
    tiles = (lambda a: None) if pixels is None else (lambda a: (pixels[0][a:a + per], pixels[1], seed * 7919 + frame))
    jobs = [system.updater.pool.submit(_chunk, system, lookup, pts[a:a + per], nrm[a:a + per], eye[a:a + per],
                                       rough[a:a + per], rays, frame_rng(seed, frame * 7919 + i),
                                       None if lamps is None else lamps[a:a + per], lights, tiles(a), screen,
                                       None if rows is None else np.asarray(rows)[a:a + per])
            for i, a in enumerate(starts)]
    for a, job in zip(starts, jobs, strict=True):
        out[a:a + per] = job.result()
    return out[:, 0:3], out[:, 3:6], out[:, 6], out[:, 7:10]


def _lamp_radiance(lights, lamps: np.ndarray, origins: np.ndarray, dirs: np.ndarray, reach: np.ndarray) -> np.ndarray:
    """(N, 3) radiance of the marked area lamps (lamps (N, L) bool per ray) that rays (origins,
    dirs) meet on their emitting side nearer than `reach` (N,) (their geometry hit, or inf)."""
    out = np.zeros((dirs.shape[0], 3), _F32)
    for j in np.flatnonzero(lamps.any(axis=0)):
        light = lights[j].for_glossy()
        shape = _area_shape(light)
        rows = np.flatnonzero(lamps[:, j])
        o, d = origins[rows].astype(np.float64), dirs[rows].astype(np.float64)
        nl = shape.normal.astype(np.float64)
        facing = d @ nl
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((shape.centre.astype(np.float64)[None, :] - o) @ nl) / facing
        r = o + d * t[:, None] - shape.centre.astype(np.float64)[None, :]
        hu, hv = shape.half_u.astype(np.float64), shape.half_v.astype(np.float64)
        # Coordinates on the (possibly sheared) parallelogram: r = a hu + b hv.
        g = np.array([[hu @ hu, hu @ hv], [hu @ hv, hv @ hv]])
        ab = np.linalg.solve(g, np.stack([r @ hu, r @ hv]))
        a, b = ab[0], ab[1]
        inside = (a * a + b * b <= 1.0) if shape.round else ((np.abs(a) <= 1.0) & (np.abs(b) <= 1.0))
        hit = (facing < 0) & (t > 0) & (t < reach[rows]) & inside
        radiance = (_F32(float(light.power) / (np.pi * shape.area)) * light.color.astype(_F32))[None, :]
        cone = spread_attenuation(light, -facing[hit], np.sqrt(np.maximum(1.0 - facing[hit] ** 2, 0.0))
                                  / np.maximum(-facing[hit], 1e-30))
        out[rows[hit]] += radiance if cone is None else radiance * cone.astype(_F32)[:, None]
    return out


def _chunk(system, lookup, p, nrm, eye, rough, rays, rng, lamps=None, lights=(), tiles=None, screen=None, rows=None):
    """Worker: (m, 10) weighted mean direct rgb, indirect rgb, the weight sum and the marked
    area lamps' rgb of m receivers. tiles : (pix, width, key) for `tiled_nets.tiled_uv`, or None.
    rows : (m,) glossy material rows (their Fresnel weighs the samples), or None."""
    m = p.shape[0]
    u, v = stratified_uv(rng, m, rays) if tiles is None else tiled_uv(tiles[0], tiles[1], rays, tiles[2])
    dirs, weight, cos_hi = sample_reflections(nrm, eye, rough, u, v, with_cos=True)
    if rows is not None:
        mu = np.einsum("ij,ij->i", nrm, eye)
        weight = weight * glossy_mod.traced_fresnel(system.glossy_materials, rows, mu, cos_hi)
    tracer = system.tracer
    eps = _F32(tracer.epsilon)
    origins = np.repeat(p + nrm * eps, rays, axis=0)
    flat_dirs = dirs.reshape(-1, 3)
    live = np.flatnonzero(weight.reshape(-1) > 0)
    radiance = np.zeros((m * rays, 9), _F32)
    if live.size:
        s = system.settings
        tfar = _F32(s.ray_length) if s.ray_length > 0 else _F32(np.inf)
        hits = tracer.intersect(origins[live], flat_dirs[live], tfar, trusted=True)
        radiance[live, 0:6] = hit_radiance(system, lookup, origins[live], flat_dirs[live], hits, rng,
                                           glossy_lamps=False, screen=screen)
        if lamps is not None:
            reach = np.where(hits.prim >= 0, hits.t, np.inf)
            radiance[live, 6:9] = _lamp_radiance(lights, np.repeat(lamps, rays, axis=0)[live], origins[live],
                                                 flat_dirs[live], reach)
    w = weight.reshape(m, rays, 1)
    total = w.sum(axis=1)
    sky = system.updater.scene.world.sky_map if live.size else None
    sky_sum = None
    if sky is not None and SKY_SAMPLES > 0:
        sky_sum = _sky_mis(system, sky, p, nrm, eye, rough, rays, rng, radiance, flat_dirs, live, hits, rows)
    weighted = (radiance.reshape(m, rays, 9) * w).sum(axis=1)
    if sky_sum is not None:
        weighted[:, 0:3] += sky_sum
    mean = weighted / np.maximum(total, _F32(1e-12))
    return np.concatenate([mean[:, 0:6], total, mean[:, 6:9]], axis=1)


def _ggx_terms(n: np.ndarray, v: np.ndarray, wi: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(D(h), G1(v), G2(v, wi)) float32 of GGX lobes (alpha (N,)) at unit normals n, views v and
    reflection directions wi (N, 3), h their half vector (Smith height-correlated G2, as
    `sample_reflections` weighs its samples)."""
    dot = lambda a, b: a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]  # noqa: E731
    h = v + wi
    h /= np.maximum(np.sqrt(dot(h, h)), _F32(1e-30))[:, None]
    a2 = alpha * alpha
    nh = np.clip(dot(n, h), 0.0, 1.0)
    d = a2 / (_F32(np.pi) * (nh * nh * (a2 - 1.0) + 1.0) ** 2)
    lam_v = _lambda(a2, np.maximum(dot(n, v), _F32(1e-4)))
    lam_l = _lambda(a2, np.maximum(dot(n, wi), _F32(1e-6)))
    return d.astype(_F32), (1.0 / (1.0 + lam_v)).astype(_F32), (1.0 / (1.0 + lam_v + lam_l)).astype(_F32)


def _lobe_densities(n: np.ndarray, v: np.ndarray, wi: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((N,) density p_b of `sample_reflections` drawing wi, (N,) the lobe's f cos without Fresnel
    there) for GGX lobes (alpha (N,)) at unit normals n and views v (N, 3): G1 D / (4 n.v) and
    D G2 / (4 n.v), whose ratio is the samples' weight G2 / G1."""
    d, g1, g2 = _ggx_terms(n, v, wi, alpha)
    four_nv = 4.0 * np.maximum(np.einsum("ij,ij->i", n, v), _F32(1e-4))
    return g1 * d / four_nv, d * g2 / four_nv


def _sample_fresnel(mats, rows, nrm, eye, dirs) -> np.ndarray:
    """(m, s) float32 `glossy.traced_fresnel` of m receivers (rows, unit normals and views (m, 3))
    towards their s sample directions dirs (m, s, 3)."""
    v = np.asarray(eye, _F32)
    h = dirs + v[:, None, :]
    h /= np.maximum(np.linalg.norm(h, axis=-1, keepdims=True), _F32(1e-30))
    cos_hi = np.einsum("msk,mk->ms", h, v)
    mu = np.einsum("ij,ij->i", np.asarray(nrm, _F32), v)
    return glossy_mod.traced_fresnel(mats, rows, mu, cos_hi)


def _sky_mis(system, sky, p, nrm, eye, rough, rays, rng, radiance, flat_dirs, live, hits, rows=None) -> np.ndarray:
    """(m, 3) the sky's part of m receivers' weighted radiance sum (the numerator of `_chunk`'s
    mean, in units of its ray weights) from SKY_SAMPLES directions drawn by the map's power
    (`environment.SkySampler`) besides the lobe's `rays`, by the balance heuristic: a sample of
    either kind that sees the sky brings L D G2 / (4 n.v (N_b p_b + N_s p_s)) x N_b (p_b the lobe's
    visible-normal density, p_s the sampler's). The lobe's own rays that escaped keep their share
    N_b p_b / (N_b p_b + N_s p_s) of their radiance (scaled in `radiance` here).

    Why: the map's compact bright regions (a sun too weak to become a lamp, a window) are met by a
    lobe's rays once in many pixels, at 60-900 x the sky's mean: fireflies on rough metal."""
    m = p.shape[0]
    sampler = sky.sampler()
    alpha = (np.maximum(np.asarray(rough, _F32), _F32(1e-3)) ** 2).astype(_F32)
    nb, ns = _F32(rays), _F32(SKY_SAMPLES)
    # The lobe's rays that escaped: their share of the sky's light.
    escaped = live[hits.prim < 0]
    if escaped.size:
        owner = escaped // rays
        wi = flat_dirs[escaped]
        pb, _fcos = _lobe_densities(nrm[owner], eye[owner], wi, alpha[owner])
        share = nb * pb / np.maximum(nb * pb + ns * sampler.pdf(wi), _F32(1e-30))
        radiance[escaped, 0:3] *= share[:, None]
    # The sampler's directions.
    k = m * SKY_SAMPLES
    u = rng.random((3, k))
    dirs, ps = sampler.sample(u[0], u[1], u[2])
    owner = np.repeat(np.arange(m), SKY_SAMPLES)
    n, v = nrm[owner], eye[owner]
    above = np.flatnonzero(np.einsum("ij,ij->i", n, dirs) > 0)
    out = np.zeros((m, 3), _F32)
    if above.size == 0:
        return out
    owner, n, v, wi, ps = owner[above], n[above], v[above], dirs[above], ps[above]
    tracer = system.tracer
    s = system.settings
    tfar = _F32(s.ray_length) if s.ray_length > 0 else _F32(np.inf)
    origins = p[owner] + n * _F32(tracer.epsilon)
    seen = np.flatnonzero(tracer.intersect(origins, wi, tfar, trusted=True).prim < 0)
    if seen.size == 0:
        return out
    owner, n, v, wi, ps = owner[seen], n[seen], v[seen], wi[seen], ps[seen]
    pb, fcos = _lobe_densities(n, v, wi, alpha[owner])
    if rows is not None:
        fcos = fcos * _sample_fresnel(system.glossy_materials, np.asarray(rows)[owner], n, v, wi[:, None, :])[:, 0]
    weight = nb * fcos / np.maximum(nb * pb + ns * ps, _F32(1e-30))
    light = sky.radiance(wi) * weight[:, None]
    for c in range(3):
        out[:, c] = np.bincount(owner, weights=light[:, c], minlength=m)
    return out


def reflection_power(rough: np.ndarray) -> np.ndarray:
    """(n,) float32 the normal exponent of each receiver's reflection filter (`filter_reflections`)
    for lobes of roughness `rough` (n,) (alpha = rough^2): REFLECTION_SHARPNESS / alpha^2, at
    least FILTER_NORMAL_POWER."""
    alpha2 = np.maximum(np.asarray(rough, np.float32), np.float32(1e-3)) ** 4
    return np.maximum(np.float32(FILTER_NORMAL_POWER), np.float32(REFLECTION_SHARPNESS) / alpha2).astype(np.float32)


def filter_reflections(direct: np.ndarray, indirect: np.ndarray, total: np.ndarray, points: np.ndarray,
                       normals: np.ndarray, pix: np.ndarray, shape: tuple[int, int], view: np.ndarray,
                       passes: int = FILTER_PASSES, pool=None, filter=None,
                       rough: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The traced light (n, 3) x 2 of receivers at flat pixels `pix` of an image of `shape`,
    averaged edge-aware (`pixel_gather.filter_at_pixels`: taps on the same plane and facing the
    same way) over the receivers whose rays found light (total > 0). A few rays per pixel leave
    a polished floor's reflection of a bright edge speckled; the neighbours on its surface see
    nearly the same reflection, as far as their normals part by less than their lobe's width
    (rough (n,): the lobes' roughness, `reflection_power`; None: one exponent for all).
    filter : as `filter_at_pixels`'."""
    if passes <= 0 or pix.size == 0:
        return direct, indirect
    camera = camera_position(view)
    power = FILTER_NORMAL_POWER if rough is None else reflection_power(rough)
    out = filter_at_pixels(np.concatenate([direct, indirect], axis=1), total > 0, points, normals, pix, shape,
                           camera, passes, pool, filter=filter, normal_power=power)
    return out[:, 0:3], out[:, 3:6]


def filter_lamp_glossy(light: np.ndarray, rough: np.ndarray, points: np.ndarray, normals: np.ndarray,
                       pix: np.ndarray, shape: tuple[int, int], view: np.ndarray, pool=None, filter=None) -> np.ndarray:
    """(n, 3) the lamps' glossy radiance `light` of receivers at flat pixels `pix` of an image of
    `shape` seen through `view` (lamp sampling, `lamp_glossy_without`), averaged one a-trous pass over each receiver's surface (same plane,
    normal within the filter's cos^8) where the lobe is at least LAMP_FILTER_ROUGHNESS rough.

    Why: 16 lamp samples of a roughness-0.5 lobe under an area lamp larger than the lobe speckle
    the highlight (the default Principled BSDF's Glossy Direct on the Stanford dragon: 0.035 of
    Combined against Cycles, 0.018 filtered); Cycles' denoised image has none of it. filter : as
    `filter_at_pixels`'."""
    keep = np.asarray(rough) >= LAMP_FILTER_ROUGHNESS
    if not keep.any():
        return light
    camera = camera_position(view)
    return filter_at_pixels(light, keep, points, normals, pix, shape, camera, 1, pool, filter=filter)
