"""Direct irradiance from Blender lamps with Cycles' conventions, shadowed by shadow rays.

One implementation shades both the probe-ray hits of the irradiance cache and the G-buffer pixels
of the deferred pass, so the cache and the final image can never disagree about a lamp.

Conventions (Cycles 4.x/5.0, each checked numerically against its Diffuse Direct pass):

- POINT of power P: intensity P / (4 pi) W/sr; E = I cos / d^2. With a radius r it emits
  L = P / (4 pi^2 r^2) from a disc facing the receiver ("Soft Falloff", Blender's default) or
  from a sphere (`_radius_chunk`).
- SPOT: as POINT, times smoothstep((cos_axis - cos(size/2)) / ((1 - cos(size/2)) * blend)),
  where cos_axis is taken in the lamp's local frame, so object scale squashes the cone as in
  Cycles (`spot_light_to_local` uses the inverse transform).
- SUN: Strength is the irradiance on a surface facing it; light arrives from -direction within a
  cone of full angle `angle`.
- AREA: one-sided radiance P / (pi A) on the local -Z side; A from the matrix-scaled extents.
  Samples are drawn uniformly in the solid angle the lamp's rectangle subtends (Urena et al.
  2013; DISK/ELLIPSE reject the corners of their bounding rectangle), so a single sample is
  bounded by 2 pi L and unbiased right up to the lamp's face; uniform area sampling with
  1 / d^2 is either unbounded or, clamped, biased by tens of percent within a lamp size of it.

Everything is numpy (float32 out; float64 where precision needs it): worker threads call it, so
it never touches bpy.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass

import numpy as np

from . import polygon_light
from .snapshot import Light
from .trace import Tracer

log = logging.getLogger(__name__)

#: Rays (receivers x samples) per chunk: bounds temporaries to a few MB for any number of points.
#: 16k was fastest on one thread (the float64 temporaries stay in cache), but two pool threads on
#: 16k chunks were no faster than one: each numpy call on a few thousand receivers lasts a few us,
#: and the threads spend it handing the GIL back and forth. 32k: the full-res first penumbra pass
#: (Cornell 640x360, 127k receivers x 8) 180 -> 150 ms on the pool. 64k (stop 61, this 2-core VM,
#: five alternating runs of the r16 rung at 640x360, medians without GPU passes): bunny_npm 1.44 ->
#: 1.38 s, dragon_npm 1.76 -> 1.69, spheres 1.15 -> 1.15, Cornell 0.71 -> 0.71 (13 of 20 pairs
#: faster; the direct step 644 -> 623, 559 -> 518, 629 -> 623, 332 -> 310 ms); a 52k-pixel penumbra
#: at 48 samples on a pool of two ran 0.74 x one thread's speed at 32k, 1.17 x at 128k.
CHUNK_RAYS = 1 << 16

#: Sheared area lamps only (area sampling): a sample closer than this fraction of its patch size,
#: sqrt(A / samples), counts as that far away, keeping the 1/d^2 estimate finite on the lamp.
AREA_MIN_DISTANCE_FRACTION = 1e-2
#: Fewest shadow samples per receiver for which an area lamp's direct light is the closed-form
#: unshadowed irradiance times the samples' visibility ratio (`polygon_light`). With fewer (probe
#: hits take one), a sample that misses a disc or falls behind the horizon would leave no
#: visibility to scale by: the plain estimate stays.
RATIO_MIN_SAMPLES = 4
#: Widest sun disc (radians, its full angle) whose light one sample gives (`one_sample_exact`): the
#: cosine of one direction in the disc differs from the disc's mean by at most ~tan(theta) x
#: angle / 2 (0.05: 1.4% at 30 degrees from the normal; Blender's default sun is 0.009).
ONE_SAMPLE_SUN_ANGLE = 0.05
#: Lamps each ray hit (probe and pixel rays) is shaded by when a scene samples more: the hit picks
#: that many of them at random, in proportion to their rough unshadowed light there
#: (`_pick_lamps`), and weighs each by one over its probability, as Cycles' light tree picks one
#: lamp per bounce. A hit's light is averaged over a cell's or a pixel's rays anyway; shading all
#: of 16 soft lamps cost the Cornell box 7 s of shadow-ray CPU in the warm-up alone. 8, not 4: the
#: five-lamp apartment's Diffuse Indirect lost 2.6% (0.1227 -> 0.1259) to the picks' noise at 4.
HIT_LAMP_BUDGET = 8
#: With more lamps than this, the glossy lobes' lamp light draws this many per receiver by their
#: rough light (`_pick_lamps`: systematic draws weighted by one over their probability,
#: unbiased), as Cycles' light tree picks lamps, instead of sampling every lamp at every pixel:
#: 120 point lamps over a monkey (320x180) took 7.8 s of glossy lamp samples (`GISystem.glossy`).
GLOSSY_LAMP_BUDGET = 8
#: Fewest sampled lamps whose hits go through `_roulette_lamps`. Its rough light per hit and lamp
#: costs about what shading one lamp does, and with two lamps it can skip at most the weaker one
#: where that one is under 1 / HIT_LAMP_BUDGET of the light: spheres' two soft lamps, the pixel
#: rays' shading 572 -> 548 ms wall, 954 -> 905 ms CPU (medians of 12, same process) without it,
#: Combined 0.00730 -> 0.00728 (each hit shaded by both lamps: less noise).
ROULETTE_MIN_LAMPS = 3
#: Share of a receiver's total rough light that every lamp's pick probability gets at least (so
#: that a lamp the rough estimate rates at zero is still picked now and then: unbiased).
PICK_FLOOR = 0.02

_F32 = np.float32


# --------------------------------------------------------------------------------------------
# Sample patterns
# --------------------------------------------------------------------------------------------


def _radical_inverse_base2(i: np.ndarray) -> np.ndarray:
    """(k,) float64 van der Corput sequence of the non-negative integers i."""
    i = i.astype(np.uint32)
    i = ((i << 16) | (i >> 16)).astype(np.uint32)
    i = ((i & 0x00FF00FF) << 8) | ((i & 0xFF00FF00) >> 8)
    i = ((i & 0x0F0F0F0F) << 4) | ((i & 0xF0F0F0F0) >> 4)
    i = ((i & 0x33333333) << 2) | ((i & 0xCCCCCCCC) >> 2)
    i = ((i & 0x55555555) << 1) | ((i & 0xAAAAAAAA) >> 1)
    return i.astype(np.float64) / 2.0**32


def hammersley(n: int) -> np.ndarray:
    """(n, 2) float64 Hammersley points in [0, 1)^2: stratified in both axes for any n."""
    return _hammersley(int(n)).copy()


@functools.lru_cache(maxsize=64)
def _hammersley(n: int) -> np.ndarray:
    """`hammersley` computed once per n (each chunk of every lamp asks for the same set; the bit
    reversal costs ~0.3 ms even for one point)."""
    i = np.arange(n)
    out = np.stack([(i + 0.5) / n, _radical_inverse_base2(i)], axis=1)
    out.flags.writeable = False
    return out


def stratified_uv(rng: np.random.Generator, m: int, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-receiver randomly shifted Hammersley sets (Cranley-Patterson rotation).

    Each point is uniformly distributed (so estimates are unbiased) while the set of one receiver
    stays stratified; only one 2D offset per receiver is drawn, which keeps the rng cheap.

    Returns u, v : (m, samples) float32 in [0, 1).
    """
    pattern = _hammersley(int(samples)).astype(_F32)
    offset = rng.random((m, 2), dtype=_F32)
    u = pattern[None, :, 0] + offset[:, None, 0]
    v = pattern[None, :, 1] + offset[:, None, 1]
    u -= np.floor(u)
    v -= np.floor(v)
    return u, v


def concentric_disk(u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Shirley-Chiu map of [0, 1)^2 onto the unit disc: uniform in area, keeps stratification.

    u, v : float32 arrays of one shape -> x, y : float32 arrays of that shape.
    """
    a = 2.0 * u - 1.0
    b = 2.0 * v - 1.0
    first = np.abs(a) > np.abs(b)
    r = np.where(first, a, b)
    # Guard the centre (a = b = 0) where both angle formulas divide by zero.
    safe_a = np.where(a == 0, 1.0, a)
    safe_b = np.where(b == 0, 1.0, b)
    phi = np.where(first, (np.pi / 4) * (b / safe_a), (np.pi / 2) - (np.pi / 4) * (a / safe_b))
    return (r * np.cos(phi)).astype(_F32), (r * np.sin(phi)).astype(_F32)


def _onb(ax: np.ndarray, ay: np.ndarray, az: np.ndarray):
    """Two unit tangents of unit vectors (Duff et al. 2017, branchless, exact at the poles)."""
    sign = np.copysign(_F32(1.0), az)
    a = -1.0 / (sign + az)
    b = ax * ay * a
    t1 = (1.0 + sign * ax * ax * a, sign * b, -sign * ax)
    t2 = (b, sign + ay * ay * a, -ay)
    return t1, t2


# --------------------------------------------------------------------------------------------
# Light geometry
# --------------------------------------------------------------------------------------------


@dataclass
class _AreaShape:
    """An area lamp in world space, with the matrix's scale applied."""

    centre: np.ndarray  # (3,) float32
    half_u: np.ndarray  # (3,) float32, centre to edge along the local X extent (scaled)
    half_v: np.ndarray  # (3,) float32
    normal: np.ndarray  # (3,) float32, unit, the emitting side (local -Z)
    area: float  # m^2, scaled (pi/4 of the bounding parallelogram for DISK / ELLIPSE)
    round: bool  # DISK / ELLIPSE
    rectangular: bool  # u and v extents orthogonal (no shear): solid-angle sampling applies
    corner: np.ndarray  # (3,) float64, centre - half_u - half_v
    frame: tuple  # three (3,) float64 unit vectors: u axis, v axis, normal
    len_u: float  # metres, full extents
    len_v: float
    extent: float  # metres, the larger extent: scale of the "on the light plane" tolerance


def _area_shape(light: Light) -> _AreaShape:
    m = light.matrix
    sx = float(light.size)
    sy = float(light.size if light.shape in ("SQUARE", "DISK") else light.size_y)
    eu = m[:3, 0] * sx
    ev = m[:3, 1] * sy
    # np.cross's formula, written out: np.cross costs ~30 us, and shapes are built per block.
    cross = np.array([eu[1] * ev[2] - eu[2] * ev[1], eu[2] * ev[0] - eu[0] * ev[2], eu[0] * ev[1] - eu[1] * ev[0]])
    par = float(np.linalg.norm(cross))
    round_shape = light.shape in ("DISK", "ELLIPSE")
    area = par * (np.pi / 4 if round_shape else 1.0)
    normal = cross / par if par > 0 else -m[:3, 2]
    # The emitting side is local -Z even if the matrix mirrors (negative scale) the X/Y axes.
    if np.dot(normal, -m[:3, 2]) < 0:
        normal = -normal
    len_u, len_v = float(np.linalg.norm(eu)), float(np.linalg.norm(ev))
    unit_u = eu / max(len_u, 1e-300)
    unit_v = ev / max(len_v, 1e-300)
    rectangular = par > 0 and abs(float(np.dot(unit_u, unit_v))) < 1e-6
    if par > 0 and not rectangular:
        log.debug("area light %r is sheared: area sampling instead of solid-angle sampling", light.name)
    return _AreaShape(
        centre=m[:3, 3].astype(_F32),
        half_u=(0.5 * eu).astype(_F32),
        half_v=(0.5 * ev).astype(_F32),
        normal=normal.astype(_F32),
        area=area,
        round=round_shape,
        rectangular=rectangular,
        corner=m[:3, 3] - 0.5 * eu - 0.5 * ev,
        frame=(unit_u, unit_v, normal),
        len_u=len_u,
        len_v=len_v,
        extent=max(len_u, len_v),
    )


def _area_points(shape: _AreaShape, u: np.ndarray, v: np.ndarray):
    """World positions (x, y, z) on the shape for sample coordinates u, v in [0, 1)."""
    if shape.round:
        a, b = concentric_disk(u, v)
    else:
        a, b = 2.0 * u - 1.0, 2.0 * v - 1.0
    c, hu, hv = shape.centre, shape.half_u, shape.half_v
    return tuple(c[k] + a * hu[k] + b * hv[k] for k in range(3))


def light_position_samples(light: Light, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, 3) float32 world-space points uniformly distributed on the lamp's emitting shape.

    AREA: the (scaled) square, rectangle, disc or ellipse; POINT/SPOT: the sphere of `radius`
    (its centre when the radius is 0). A SUN has no position and raises ValueError.
    """
    if light.kind == "SUN":
        raise ValueError("a sun light has no position to sample")
    if light.kind == "AREA":
        u, v = stratified_uv(rng, 1, n)
        x, y, z = _area_points(_area_shape(light), u[0], v[0])
        return np.stack([x, y, z], axis=1).astype(_F32)
    d = rng.normal(size=(n, 3))
    d /= np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30)
    return (light.position[None, :] + float(light.radius) * d).astype(_F32)


def spread_attenuation(light: Light, cos_a, tan_a):
    """Factor on an AREA lamp's radiance leaving it at angle a from its normal (cos_a, tan_a:
    arrays of one shape), or None for a full spread (pi: Lambertian, factor 1).

    Cycles' `area_light_spread_attenuation` (kernel/light/area.h): a soft-box grid's share of the
    lamp not hidden by its slats, max(tan(spread / 2) - tan a, 0), normalized (scene/light.cpp) by
    1 / (tan(spread / 2) - spread / 2) so the cosine-weighted integral over the hemisphere stays
    pi: the lamp's power is the same, concentrated in the cone. A spread of 0 is a beam along the
    normal (factor pi within 0.05 degrees of it, as Cycles)."""
    spread = float(light.spread)
    if light.kind != "AREA" or spread >= np.pi:
        return None
    half = 0.5 * spread
    tan_half = float(np.tan(half))
    cos_a = np.asarray(cos_a)
    if tan_half <= 0.0:
        return np.where(cos_a > 0.9999997, np.pi, 0.0).astype(cos_a.dtype)
    norm = 1.0 / (tan_half - half) if half > 0.05 else 3.0 / half**3
    tan_a = np.where(cos_a > 0, np.asarray(tan_a), np.inf)
    return (np.maximum(tan_half - tan_a, 0.0) * norm).astype(cos_a.dtype)


def spread_reach(light: Light, z0: np.ndarray) -> np.ndarray | None:
    """(m,) float64 half-width of the square about each receiver's foot on an AREA lamp's plane
    (z0 : (m,) its signed distance to the plane, < 0 on the emitting side) outside which the
    lamp's spread cone sends it nothing: tan(spread / 2) x distance. None for a full spread, or a
    beam (spread 0, `spread_attenuation`'s own case).

    Why: a soft box of spread 60 degrees lights a receiver from a small part of its area; samples
    over the whole lamp mostly land where `spread_attenuation` is 0 (Diffuse Direct 0.047 against
    Cycles where the same lamp at full spread gives 0.008). Cycles clamps its samples to the same
    square (`area_light_spread_clamp_light`); outside it the integrand is 0, so nothing changes but
    the noise."""
    spread = float(light.spread)
    if light.kind != "AREA" or spread >= np.pi or spread <= 0.0:
        return None
    return np.tan(0.5 * spread) * np.abs(np.asarray(z0, np.float64))


def smoothstep01(x: np.ndarray) -> np.ndarray:
    """Cycles' `smoothstepf`: the cubic 3x^2 - 2x^3 on x clamped to [0, 1]."""
    t = np.clip(x, 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def spot_attenuation(light: Light, to_point: np.ndarray) -> np.ndarray:
    """(k,) float32 cone factor of a SPOT for world directions lamp -> receiver, times its IES
    profile where it has one (`Light.profile`: a POINT's too; `Light.directional`).

    to_point : (k, 3) float32, not necessarily unit. The direction is taken into the lamp's local
    frame with the inverse matrix (as Cycles' `spot_light_to_local`), so a non-uniformly scaled
    lamp has an elliptic cone; with uniform scale this is the cosine to `Light.direction`.
    """
    m3 = light.matrix[:3, :3]
    try:
        inv = np.linalg.inv(m3).astype(_F32)
    except np.linalg.LinAlgError:
        # A zero-scaled lamp has no local frame; the emission axis is the best available.
        inv = None
    if inv is None:
        local_z = -(to_point @ light.direction)
        norm = np.linalg.norm(to_point, axis=1)
    else:
        local = to_point @ inv.T
        local_z = local[:, 2]
        norm = np.linalg.norm(local, axis=1)
    profile = getattr(light, "profile", None)
    shaped = None if profile is None else profile(to_point if inv is None else local)
    if light.kind != "SPOT":
        return np.ones(to_point.shape[0], _F32) if shaped is None else shaped
    cos_axis = -local_z / np.maximum(norm, 1e-30)
    cos_half = np.cos(0.5 * float(light.spot_size))
    blend = float(light.spot_blend)
    if blend <= 0.0:
        cone = (cos_axis > cos_half).astype(_F32)
    else:
        cone = smoothstep01((cos_axis - cos_half) / ((1.0 - cos_half) * blend)).astype(_F32)
    return cone if shaped is None else cone * shaped


# --------------------------------------------------------------------------------------------
# Per-light irradiance of one chunk (structure of arrays: px, py, pz are (m,) float32)
# --------------------------------------------------------------------------------------------


def shadow_query(tracer, glass: bool = False):
    """The tracer's query for shadow rays: `occluded_shadow` where its scene has triangles shadow
    rays pass (objects hidden from shadow rays, materials transparent to them:
    `EmbreeTracer.has_shadow_skips`) or, for a lamp that glass stops (`glass`, `stopped_by_glass`),
    refractive glass (`EmbreeTracer.has_glass`), else `occluded` (every other scene takes the same
    calls as before, wrappers of `occluded` included)."""
    if glass and getattr(tracer, "has_glass", False):
        return functools.partial(tracer.occluded_shadow, glass=True)
    return tracer.occluded_shadow if getattr(tracer, "has_shadow_skips", False) else tracer.occluded


def stopped_by_glass(light: Light) -> bool:
    """Whether refractive glass (`Material.refractive`) stops the lamp's light: Cycles' shadow rays
    stop at glass, and its light behind glass comes only from rays that happen to hit the lamp
    through it. Suns, point and spot lamps are too small to be hit: a sun through a glazed window
    leaves no sunlit patch at 1024 spp. An area lamp is (3 m, 5 m behind a pane: 62% of its open
    light at 256 spp, converging), so its light passes."""
    return light.kind != "AREA"


def _shadow_to_targets(tracer, p, nrm, idx, tx, ty, tz, epsilon, glass=False):
    """Visibility of targets (tx, ty, tz) from receivers p[idx] (offset along their normals);
    glass : refractive glass blocks (`shadow_query`)."""
    origins = np.take(_lifted(p, nrm, epsilon), idx, axis=0)
    dx, dy, dz = tx - origins[:, 0], ty - origins[:, 1], tz - origins[:, 2]
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    tfar = dist - epsilon
    # Only rays with some reach can be blocked (0 < t <= tfar); those have a finite unit
    # direction from finite receivers (checked by the caller) and lamp points: traced trusted.
    ray = np.flatnonzero(tfar > 0)
    vis = np.ones(dist.shape, bool)
    if tracer is None or ray.size == 0:
        return vis
    every = ray.size == dist.size
    if not every:
        origins, dx, dy, dz, dist, tfar = (a[ray] for a in (origins, dx, dy, dz, dist, tfar))
    inv = 1.0 / dist
    dirs = np.empty((dist.size, 3), _F32)
    for k, d in enumerate((dx, dy, dz)):
        np.multiply(d, inv, out=dirs[:, k])
    query = shadow_query(tracer, glass)
    hidden = np.asarray(query(origins, dirs, tfar.astype(_F32, copy=False), trusted=True), bool)
    if every:
        return ~hidden
    vis[ray] = ~hidden
    return vis


def _lifted(p, nrm, epsilon) -> np.ndarray:
    """(m, 3) float32 shadow-ray origins of receivers p (offset epsilon along their normals nrm;
    both structure-of-arrays (m,) float32 triples). Gather its rows with np.take(axis=0): ~3x
    faster than fancy indexing of a 2-D array."""
    out = np.empty((p[0].shape[0], 3), _F32)
    for k in range(3):
        np.add(p[k], nrm[k] * epsilon, out=out[:, k])
    return out


def _mark_partial_all(partial, live, blocked):
    """`_mark_partial` where every sample of receivers `live` (k,) (None: all) was traced:
    blocked (k, samples)."""
    if partial is None:
        return
    hidden = np.count_nonzero(blocked, axis=1)
    mixed = (hidden > 0) & (hidden < blocked.shape[1])
    if live is None:
        partial |= mixed
    else:
        partial[live] |= mixed


def _mark_partial(partial, rows, blocked, m):
    """partial (m,) |= receivers among whose traced samples (rows (k,) receiver of each) some
    were blocked and some not: the ones a penumbra crosses (`penumbra.adaptive_direct`)."""
    if partial is None or rows.size == 0:
        return
    traced = np.bincount(rows, minlength=m)
    hidden = np.bincount(rows[blocked], minlength=m)
    partial |= (hidden > 0) & (hidden < traced)


def _point_chunk(light, p, nrm, tracer, rng, samples, epsilon, partial=None, opened=None):
    if float(light.radius) > 0.0:
        return _radius_chunk(light, p, nrm, tracer, rng, samples, epsilon, partial, opened)
    c = light.position
    wx, wy, wz = c[0] - p[0], c[1] - p[1], c[2] - p[2]  # receiver -> lamp
    d2 = np.maximum(wx * wx + wy * wy + wz * wz, epsilon * epsilon)
    inv_d = 1.0 / np.sqrt(d2)
    cos_r = (wx * nrm[0] + wy * nrm[1] + wz * nrm[2]) * inv_d
    e = (float(light.power) / (4.0 * np.pi)) * np.maximum(cos_r, 0.0) / d2
    if light.directional:
        e *= spot_attenuation(light, -np.stack([wx, wy, wz], axis=1))
    if opened is not None:
        opened.append(e.copy())
    if tracer is None:
        return e
    live = np.nonzero(e != 0)[0]
    if live.size == 0:
        return e
    vis = _shadow_to_targets(tracer, p, nrm, live, _F32(c[0]), _F32(c[1]), _F32(c[2]), epsilon,
                             stopped_by_glass(light))
    e[live] *= vis
    return e


def _cone_varies(light, centre, radius: float, t1, t2, px, py, pz) -> np.ndarray:
    """(k,) bool receivers (px, py, pz (k,)) over whose view of a POINT/SPOT emitter of `radius`
    (t1, t2 (3 x (k, 1)): the frame across the receiver's direction to it) the cone factor
    (`spot_attenuation`) changes: it differs between the emitter's centre and one of four points
    on its rim (the disc facing the receiver, or the sphere's outline) by more than 1e-4."""
    k = px.shape[0]
    rel = np.stack([px, py, pz], axis=1) - np.asarray(centre, _F32)[None, :]  # lamp -> receiver
    base = spot_attenuation(light, rel.astype(_F32))
    varies = np.zeros(k, bool)
    for su, sv in ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)):
        off = np.stack([radius * (su * t1[j][:, 0] + sv * t2[j][:, 0]) for j in range(3)], axis=1)
        varies |= np.abs(spot_attenuation(light, (rel - off).astype(_F32)) - base) > 1e-4
    return varies


def _radius_chunk(light, p, nrm, tracer, rng, samples, epsilon, partial=None, opened=None):
    """POINT/SPOT of radius r > 0 as Cycles 4.x/5.0 emit it (kernel/light/point.h, spot.h): radiance
    L = P / (4 pi^2 r^2) (scene/light.cpp: power over pi times the sphere's area) from

    - a sphere of radius r (`soft_falloff` False: Cycles' `is_sphere`), sampled uniformly in the
      cone it subtends; inside it a receiver sees pi L with no spot cone;
    - a disc of radius r facing the receiver (`soft_falloff` True, Blender's default), sampled
      uniformly in area: pi L r^2 / (d^2 + r^2) on axis, which is the "soft" falloff.

    A SPOT's cone factor is taken per sample along sample point -> receiver, which softens its
    edge by the lamp's angular size. Where the whole emitter is above the receiver's horizon the
    unshadowed irradiance is known in closed form (the emitter's vector irradiance is axial:
    P cos / (4 pi d^2) for the sphere, P cos / (4 pi (d^2 + r^2)) for the disc) and the samples
    only weight cone factor x visibility; elsewhere the samples estimate the clipped integral.
    """
    c = light.position
    radius = float(light.radius)
    r2 = radius * radius
    m = p[0].shape[0]
    s = samples
    # Drawn for every receiver so the rng stream does not depend on which ones face the lamp.
    u, v = stratified_uv(rng, m, s)
    e = np.zeros(m, _F32)
    wx, wy, wz = (c[k] - p[k] for k in range(3))  # receiver -> lamp
    d2 = np.maximum(wx * wx + wy * wy + wz * wz, epsilon * epsilon)
    d = np.sqrt(d2)
    cos_r = (wx * nrm[0] + wy * nrm[1] + wz * nrm[2]) / d
    sphere = not bool(light.soft_falloff)
    # sin of the emitter's angular radius seen from the receiver; nothing reaches a receiver
    # whose horizon the whole emitter is below.
    sin_a = np.sqrt(r2 / np.maximum(d2, r2)) if sphere else radius / np.sqrt(d2 + r2)
    inside = (d2 <= r2) if sphere else np.zeros(m, bool)
    live = np.flatnonzero((cos_r > -sin_a) | inside)
    if live.size == 0:
        if opened is not None:
            opened.append(e.copy())
        return e
    k = live.size
    ax, ay, az = (w[live] / d[live] for w in (wx, wy, wz))  # unit receiver -> lamp
    into = inside[live]
    if into.any():
        # Inside a sphere the lamp is all around: sample the hemisphere above the receiver.
        ax, ay, az = (np.where(into, q[live], w) for q, w in zip(nrm, (ax, ay, az), strict=True))
    t1, t2 = _onb(ax[:, None], ay[:, None], az[:, None])
    a, b = concentric_disk(u[live], v[live])
    px, py, pz = (q[live][:, None] for q in p)
    nx, ny, nz = (q[live][:, None] for q in nrm)
    dl = d[live][:, None]
    power = float(light.power)
    if sphere:
        # Uniform cone towards the sphere (Cycles' sample_uniform_cone); the law of cosines puts
        # the sample on the sphere's near side.
        s2 = np.minimum(r2 / d2[live], 1.0)[:, None]
        omc = s2 / (1.0 + np.sqrt(1.0 - s2))
        q2 = a * a + b * b
        cos_t = 1.0 - q2 * omc
        scale = np.sqrt(np.maximum(omc * (2.0 - q2 * omc), 0.0))
        a *= scale
        b *= scale
        dx, dy, dz = (a * t1[j] + b * t2[j] + cos_t * w[:, None] for j, w in enumerate((ax, ay, az)))
        # Outside, the near root of |p + t dir - c| = r; inside, the only positive one.
        bc = dx * wx[live][:, None] + dy * wy[live][:, None] + dz * wz[live][:, None]
        root = np.sqrt(np.maximum(r2 - dl * dl + bc * bc, 0.0))
        t = bc + np.where(inside[live][:, None], root, -root)
        tx, ty, tz = px + dx * t, py + dy * t, pz + dz * t
        # L x solid angle / s per sample, times its cosine: P / (4 pi^2 r^2) x 2 pi omc.
        f = (power / (2.0 * np.pi * r2)) * omc * np.maximum(dx * nx + dy * ny + dz * nz, 0.0) / s
        full = (power / (4.0 * np.pi)) * cos_r[live] / np.maximum(d2[live], r2)
        # Inside the sphere every direction above the horizon sees it: pi L, no cone factor (the
        # samples, uniform in that hemisphere, only weight visibility by their cosine).
        full[into] = power / (4.0 * np.pi * r2)
    else:
        a *= radius
        b *= radius
        # Disc point relative to the lamp centre, in the plane facing the receiver.
        ox, oy, oz = (a * t1[j] + b * t2[j] for j in range(3))
        tx, ty, tz = c[0] + ox, c[1] + oy, c[2] + oz
        dx, dy, dz = tx - px, ty - py, tz - pz
        t2s = np.maximum(dx * dx + dy * dy + dz * dz, epsilon * epsilon)
        inv_t = 1.0 / np.sqrt(t2s)
        # cos at the disc: its normal is the axis lamp -> receiver; the sample's distance along it.
        cos_l = dl * inv_t
        cos_rs = np.maximum(dx * nx + dy * ny + dz * nz, 0.0) * inv_t
        # L x disc area / s per sample, times cos_r cos_l / t^2.
        f = (power / (4.0 * np.pi * s)) * cos_rs * cos_l / t2s
        full = (power / (4.0 * np.pi)) * cos_r[live] / (d2[live] + r2)
        dx, dy, dz = dx * inv_t, dy * inv_t, dz * inv_t
    f = f.astype(_F32)
    if light.directional:
        att = spot_attenuation(light, -np.stack([dx.ravel(), dy.ravel(), dz.ravel()], axis=1)).reshape(k, s)
        att[into] = 1.0
        fa = f * att
    else:
        fa = f
    # The unshadowed light in closed form, the emitter clipped by the horizon where it cuts it
    # (`clipped_cone_irradiance`), x the samples' weighted cone factor and visibility.
    above = (cos_r[live] >= sin_a[live]) | into
    clipped = ~above
    if clipped.any():
        sin2 = (sin_a[live][clipped] ** 2).astype(np.float64)
        full = np.asarray(full, np.float64).copy()
        full[clipped] = (power / (4.0 * np.pi * np.pi * r2)) * clipped_cone_irradiance(
            cos_r[live][clipped].astype(np.float64), sin2)
    sum_f = f.sum(axis=1)
    ratio = np.where(sum_f > 0, full / np.where(sum_f > 0, sum_f, 1.0), 1.0).astype(_F32)
    varied = np.zeros(k, bool)
    if light.directional:
        varied |= att.min(axis=1) != att.max(axis=1)
        # Where the cone factor varies over the emitter (a spot's blend or edge, an IES profile),
        # the ratio to the closed form, a mean of it weighted by f over the same few samples, is
        # biased at few samples (-6 to -10% at 2 samples near a soft spot's edge); there the plain
        # estimate is kept, unbiased at any count. Which receivers is decided from the emitter's
        # rim (`_cone_varies`), not from the samples: choosing by them biased the mix in turn.
        # (Inside the sphere the factor is 1, `att[into]`: the ratio stays.)
        ratio[_cone_varies(light, c, radius, t1, t2, px[:, 0], py[:, 0], pz[:, 0]) & ~into] = 1.0
    if partial is not None:
        # Where the samples' weights differ for reasons other than shadows (the spot's cone edge
        # crosses the emitter), they are noisy as in a penumbra: same count.
        partial[live[varied]] = True
    w = (fa * ratio[:, None]).ravel()
    lit = np.flatnonzero(w > 0)
    rows = lit // s
    w = w[lit]
    if opened is not None or tracer is None:
        # Summed as the shadowed total below, so an unblocking tracer changes no bit.
        e[live] = np.bincount(rows, weights=w, minlength=k).astype(_F32)
        if opened is not None:
            opened.append(e.copy())
    if tracer is None or lit.size == 0:
        return e
    tx, ty, tz = (q.ravel()[lit].astype(_F32) for q in (tx, ty, tz))
    vis = _shadow_to_targets(tracer, p, nrm, live[rows], tx, ty, tz, epsilon, stopped_by_glass(light))
    e[live] = np.bincount(rows, weights=w * vis, minlength=k).astype(_F32)
    _mark_partial(partial, live[rows], ~vis, m)
    return e


def clipped_cone_irradiance(cos_theta: np.ndarray, sin2_sigma: np.ndarray) -> np.ndarray:
    """Irradiance per unit radiance from a uniform emitter that subtends a cone of half-angle
    sigma (a sphere, or a disc facing the receiver) whose axis is theta from the receiver's
    normal, the part below the receiver's horizon clipped off: pi sin^2 sigma cos theta where the
    whole cone is above it, else Snyder's closed form (1996; Lagarde & de Rousiers 2014, eq. 27).

    Why: a point or spot lamp with a radius near a surface (a ceiling lamp over a wall, radius
    1 m over a sofa) straddles the horizon of many receivers; their light was left to the shadow
    samples, which re-sampled every such pixel as a penumbra."""
    c = np.clip(np.asarray(cos_theta, np.float64), -1.0, 1.0)
    s2 = np.clip(np.asarray(sin2_sigma, np.float64), 1e-12, 1.0)
    sin_t = np.sqrt(np.maximum(1.0 - c * c, 1e-24))
    whole = c * c > s2
    x = np.sqrt(np.maximum(1.0 / s2 - 1.0, 0.0))
    y = np.clip(-x * c / sin_t, -1.0, 1.0)
    sy = sin_t * np.sqrt(np.maximum(1.0 - y * y, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        cut = (c * np.arccos(y) - x * sy) * s2 + np.arctan2(sy, x)
    out = np.where(whole, np.pi * s2 * np.maximum(c, 0.0), cut)
    return np.maximum(out, 0.0)


def _sun_axis(light, pts, nrm, tracer, epsilon, opened=None):
    """(n,) irradiance of a sun traced along its axis (one shadow ray per receiver facing it).

    Same expected irradiance as the disc (the cone's mean cosine is cos(n, axis) times the factor
    the disc path divides out), hard shadows. pts, nrm : (n, 3) float32 row-major.
    """
    to_sun = (-light.direction).astype(_F32)
    # Column by column: numpy broadcasts a (3,) operand over (n, 3) rows (einsum "ij,j") 2x slower.
    cos_r = nrm[:, 0] * to_sun[0]
    cos_r += nrm[:, 1] * to_sun[1]
    cos_r += nrm[:, 2] * to_sun[2]
    live = np.flatnonzero(cos_r > 0)
    e = np.zeros(pts.shape[0], _F32)
    if opened is not None:
        opened.append(np.maximum(cos_r, _F32(0.0)) * _F32(light.power))
    if live.size == 0:
        return e
    if tracer is not None:
        origins = nrm[live]
        origins *= _F32(epsilon)
        origins += pts[live]
        # Finite receivers (checked by the caller) and one unit direction: rays need no checks.
        live = live[~np.asarray(shadow_query(tracer, True)(origins, to_sun[None], np.inf, trusted=True), bool)]
    e[live] = cos_r[live] * _F32(light.power)
    return e


def _beam(light, shape, p, nrm, tracer, epsilon, opened=None):
    """(m,) irradiance of an AREA lamp of Spread 0: a collimated beam along its normal (Cycles'
    spread attenuation is pi within 0.05 degrees of the normal, 0 elsewhere): P / A x cos at
    receivers whose projection along the normal falls on the lamp's front, one shadow ray each.
    p, nrm : (x, y, z) triples of (m,) float32."""
    pts = np.stack(p, axis=1).astype(np.float64)
    n = np.stack(nrm, axis=1).astype(np.float64)
    ex, ey, ez = shape.frame
    d = pts - shape.centre.astype(np.float64)
    height = d @ ez  # > 0: in front of the lamp
    a = (d @ ex) * (2.0 / max(shape.len_u, 1e-300))
    b = (d @ ey) * (2.0 / max(shape.len_v, 1e-300))
    on = (a * a + b * b <= 1.0) if shape.round else ((np.abs(a) <= 1.0) & (np.abs(b) <= 1.0))
    cos_r = np.maximum(-(n @ ez), 0.0)
    e = np.where(on & (height > 0), cos_r * (float(light.power) / shape.area), 0.0).astype(_F32)
    if opened is not None:
        opened.append(e.copy())
    live = np.flatnonzero(e > 0)
    if tracer is not None and live.size:
        origins = (pts[live] + n[live] * epsilon).astype(_F32)
        tfar = np.maximum(height[live] - epsilon, 0.0).astype(_F32)
        blocked = np.asarray(shadow_query(tracer)(origins, (-ez)[None].astype(_F32), tfar, trusted=True), bool)
        e[live[blocked]] = 0.0
    return e


def uniform_cone(axis, half_angle: float, u: np.ndarray, v: np.ndarray):
    """Directions uniform in the cone of `half_angle` (radians) around the unit `axis` (3,), from
    sample coordinates u, v in [0, 1): the concentric map, as Cycles' sample_uniform_cone_concentric.
    Returns ((dx, dy, dz) arrays shaped as u, in u's dtype, and 1 - cos(half_angle))."""
    # A Python float: NumPy 2 keeps u's float32 against it (an np.float64 scalar would promote).
    one_minus_cos = float(2.0 * np.sin(0.5 * half_angle) ** 2)
    a, b = concentric_disk(u, v)
    r2 = a * a + b * b
    cos_t = 1.0 - r2 * one_minus_cos
    # Scale the disc point (radius sqrt(r2)) to the cone's sine: sin_t / sqrt(r2).
    scale = np.sqrt(np.maximum(one_minus_cos * (2.0 - r2 * one_minus_cos), 0.0))
    ax = np.asarray(axis, u.dtype)
    t1, t2 = _onb(ax[0:1], ax[1:2], ax[2:3])
    a *= scale
    b *= scale
    return tuple(a * t1[k] + b * t2[k] + cos_t * ax[k] for k in range(3)), one_minus_cos


def _rows_into(values: np.ndarray, rows: np.ndarray, m: int) -> np.ndarray:
    """(m, s) zeros with values (k, s) at rows (k,)."""
    out = np.zeros((m, values.shape[1]), values.dtype)
    out[rows] = values
    return out


def _sun_chunk(light, p, nrm, tracer, rng, samples, epsilon, partial=None, opened=None,
               ratio_samples=RATIO_MIN_SAMPLES):
    """A sun with a disc (angle > 0), sampled; `_sun_axis` shades suns traced along their axis.
    With at least ratio_samples samples, a receiver that sees the whole disc above its horizon
    takes the ratio estimator (`polygon_light`): the exact light, strength x cos(axis), times the
    share of its samples' light that reached the sun (one direction's cosine differs from the
    disc's mean by ~tan(theta) x angle / 2: 1.7% noise over a floor under a 2 degree sun)."""
    m = p[0].shape[0]
    u, v = stratified_uv(rng, m, samples)
    axis = (-light.direction).astype(_F32)
    half = 0.5 * float(light.angle)
    # Receivers facing away from the whole cone (half of the atrium's pixels; a margin far beyond
    # float32 rounding) get 0 from every sample: their directions are not made.
    facing = nrm[0] * axis[0] + nrm[1] * axis[1] + nrm[2] * axis[2] >= -np.sin(half) - 1e-4
    some = None if facing.all() else np.flatnonzero(facing)
    q = nrm if some is None else tuple(c[some] for c in nrm)
    if some is not None:
        u, v = u[some], v[some]
    (dx, dy, dz), one_minus_cos = uniform_cone(axis, half, u, v)
    cos_r = np.maximum(dx * q[0][:, None] + dy * q[1][:, None] + dz * q[2][:, None], 0.0)
    if some is not None:
        cos_r = _rows_into(cos_r, some, m)
        dx, dy, dz = (_rows_into(c, some, m) for c in (dx, dy, dz))
    # Strength is the irradiance on a facing surface: the cone's mean cosine is divided out.
    weight = float(light.power) / ((1.0 - 0.5 * one_minus_cos) * samples)
    contrib = cos_r.astype(_F32) * _F32(weight)
    open_sum = contrib.sum(axis=1)
    whole = None
    if samples >= ratio_samples:
        cos_axis = nrm[0] * axis[0] + nrm[1] * axis[1] + nrm[2] * axis[2]
        whole = (cos_axis >= np.sin(half)) & (open_sum > 0)
        exact = (_F32(light.power) * cos_axis).astype(_F32)
    if opened is not None:
        opened.append(open_sum if whole is None else np.where(whole, exact, open_sum).astype(_F32))
    if tracer is not None:
        lit = np.flatnonzero(cos_r > 0)  # flat indices: (rows, cols) fancy indexing costs ~2x
        if lit.size:
            rows = lit // samples
            origins = np.take(_lifted(p, nrm, epsilon), rows, axis=0)
            dirs = np.stack([dx.ravel()[lit], dy.ravel()[lit], dz.ravel()[lit]], axis=1)
            # Finite receivers (checked by the caller) and unit cone directions: no ray checks.
            blocked = np.asarray(shadow_query(tracer, True)(origins, dirs, np.inf, trusted=True), bool)
            contrib.ravel()[lit[blocked]] = 0.0
            _mark_partial(partial, rows, blocked, m)
    total = contrib.sum(axis=1)
    if whole is not None:
        total = np.where(whole, exact * (total / np.where(whole, open_sum, _F32(1.0))), total).astype(_F32)
    return total


def _area_chunk(light, shape, p, nrm, tracer, rng, samples, epsilon, partial=None, solid_angle=True, opened=None,
                known=None, ratio_samples=RATIO_MIN_SAMPLES):
    """known : optional (m,) float64 in/out, the lamp's exact unshadowed irradiance at the
    receivers (NaN where not yet computed; `direct_irradiance`'s exact). ratio_samples : fewest
    samples for the ratio estimator (`direct_irradiance`)."""
    m = p[0].shape[0]
    # Drawn for every receiver so the rng stream does not depend on which ones face the lamp.
    u, v = stratified_uv(rng, m, samples)
    e = np.zeros(m, _F32)
    radiance = float(light.power) / (np.pi * shape.area)
    if not shape.rectangular or not solid_angle:
        return _area_chunk_by_area(shape, radiance, p, nrm, tracer, u, v, samples, epsilon, partial, opened, light)
    # Receiver-relative coordinates of the lamp's bounding rectangle in its frame (x, y, normal).
    # float64 per receiver: the solid angle is a small difference of angles that sum to ~2 pi;
    # the per-sample work below is float32 (`_sample_spherical_rectangle`).
    ex, ey, ez = shape.frame
    corner = shape.corner
    d = [corner[k] - p[k].astype(np.float64) for k in range(3)]
    z0 = d[0] * ez[0] + d[1] * ez[1] + d[2] * ez[2]
    # One-sided: only receivers strictly on the emitting side (z0 < 0 in Urena's convention),
    # and not those that see the whole lamp below their horizon (no sample can light them: half
    # of bunny_npm's pixels), with a margin far beyond the samples' float32 rounding, so that
    # what is skipped is the 0 the samples would have given.
    live = np.flatnonzero((z0 < -1e-9 * shape.extent) & _above_horizon(shape, d, nrm))
    if live.size == 0:
        if opened is not None:
            opened.append(e.copy())
        return e
    every = live.size == m
    if not every:
        z0 = z0[live]
        d = [c[live] for c in d]
        u, v = u[live], v[live]
    x0 = d[0] * ex[0] + d[1] * ex[1] + d[2] * ex[2]
    y0 = d[0] * ey[0] + d[1] * ey[1] + d[2] * ey[2]
    sx0, sy0, len_u, len_v = x0, y0, shape.len_u, shape.len_v
    reach = spread_reach(light, z0)
    if reach is not None:
        # Sample only the part of the lamp that can light the receiver (`spread_reach`).
        sx0, sy0 = np.maximum(x0, -reach), np.maximum(y0, -reach)
        len_u = np.minimum(x0 + shape.len_u, reach) - sx0
        len_v = np.minimum(y0 + shape.len_v, reach) - sy0
        seen = np.flatnonzero((len_u > 1e-9 * shape.extent) & (len_v > 1e-9 * shape.extent))
        if seen.size < live.size:
            if seen.size == 0:
                if opened is not None:
                    opened.append(e.copy())
                return e
            live = live[seen]
            every = False
            z0, x0, y0, sx0, sy0, len_u, len_v, u, v = (a[seen] for a in (z0, x0, y0, sx0, sy0, len_u, len_v, u, v))
            d = [c[seen] for c in d]
    xu, yv, inside, solid_angle = _sample_spherical_rectangle(sx0, sy0, z0, len_u, len_v, u, v)
    # World vector receiver -> sample from its local coordinates (float32: a relative vector).
    z32 = z0.astype(_F32)[:, None]
    ex32, ey32, ez32 = (np.asarray(a, _F32) for a in (ex, ey, ez))
    nx, ny, nz = ((q if every else q[live])[:, None] for q in nrm)
    wx = xu * ex32[0] + yv * ey32[0] + z32 * ez32[0]
    wy = xu * ex32[1] + yv * ey32[1] + z32 * ez32[1]
    wz = xu * ex32[2] + yv * ey32[2] + z32 * ez32[2]
    cos_r = wx * nx
    cos_r += wy * ny
    cos_r += wz * nz
    cos_r /= np.sqrt(wx * wx + wy * wy + wz * wz)
    f = np.maximum(cos_r, _F32(0.0))
    f *= inside
    if shape.round:
        # Bounding-rectangle samples outside the ellipse carry no light: still unbiased.
        a = (xu - x0.astype(_F32)[:, None]) * _F32(2.0 / shape.len_u) - _F32(1.0)
        b = (yv - y0.astype(_F32)[:, None]) * _F32(2.0 / shape.len_v) - _F32(1.0)
        f *= a * a + b * b <= 1.0
    # Spread: the radiance per sample direction (z0 < 0 on the emitting side); the closed-form
    # unshadowed light is that of a Lambertian lamp, so the plain estimate stays.
    away = -z0.astype(_F32)[:, None]
    cone = spread_attenuation(light, away / np.sqrt(xu * xu + yv * yv + away * away), np.sqrt(xu * xu + yv * yv) / away)
    if cone is not None:
        f *= cone
    open_sum = f.sum(axis=1)
    unshadowed = open_sum if samples >= ratio_samples and cone is None else None
    scale = (solid_angle * (radiance / samples)).astype(_F32)
    if tracer is not None:
        lit = np.flatnonzero(f > 0)
        if lit.size:
            eps = _F32(epsilon)
            # Every sample lit (most chunks of a lamp above every receiver's horizon): whole
            # arrays instead of gathers, the same values.
            full = lit.size == f.size
            rows = None if full else lit // samples
            # Origin p + n eps, target p + w: the ray is w - n eps, its length less eps the reach.
            if full:
                sx, sy, sz = ((w - c * eps).ravel() for w, c in ((wx, nx), (wy, ny), (wz, nz)))
            else:
                sx, sy, sz = (w.ravel()[lit] - c[rows, 0] * eps for w, c in ((wx, nx), (wy, ny), (wz, nz)))
            dist = np.sqrt(sx * sx + sy * sy + sz * sz)
            tfar = dist - eps
            # A ray of no length (receiver within epsilon of the lamp) cannot be blocked.
            ray = np.flatnonzero(tfar > 0)
            if 0 < ray.size < lit.size:
                full, rows = False, lit // samples if rows is None else rows
                lit, rows, sx, sy, sz, dist, tfar = (a[ray] for a in (lit, rows, sx, sy, sz, dist, tfar))
            if ray.size:
                inv = _F32(1.0) / dist
                dirs = np.empty((lit.size, 3), _F32)
                for k, s in enumerate((sx, sy, sz)):
                    np.multiply(s, inv, out=dirs[:, k])
                # Origins per receiver, then one gather (or repeat) per ray, not two gathers and a
                # multiply-add.
                lifted = _lifted(p, nrm, eps)
                if full:
                    origins = np.repeat(lifted if every else np.take(lifted, live, axis=0), samples, axis=0)
                else:
                    src = live[rows] if not every else rows
                    origins = np.take(lifted, src, axis=0)
                # Finite receivers (checked by the caller), unit directions, positive reach.
                blocked = np.asarray(shadow_query(tracer)(origins, dirs, tfar, trusted=True), bool)
                if full:
                    f.ravel()[blocked] = 0.0
                    _mark_partial_all(partial, live if not every else None, blocked.reshape(-1, samples))
                else:
                    f.ravel()[lit[blocked]] = 0.0
                    _mark_partial(partial, src, blocked, m)
    # Solid-angle sampling: each sample estimates L * S * cos_r, bounded by 2 pi L.
    shadowed_sum = f.sum(axis=1)
    total = shadowed_sum * scale
    open_total = open_sum * scale if opened is not None else None
    if unshadowed is not None:
        # The exact light only where it is used: times the visibility ratio where some sample
        # reached the lamp (a wholly shadowed receiver's 0 stays 0), and as the unshadowed light.
        need = shadowed_sum > 0 if opened is None else unshadowed > 0
        exact = _exact_at(shape, radiance, p, nrm, live, every, need, known)
        total = _times_visibility(exact, total, shadowed_sum, unshadowed)
        if open_total is not None:
            open_total = np.where(unshadowed > 0, exact, open_total).astype(_F32)
    if opened is not None:
        if every:
            opened.append(open_total)
        else:
            o = np.zeros(m, _F32)
            o[live] = open_total
            opened.append(o)
    if every:
        return total
    e[live] = total
    return e


def _above_horizon(shape, d, nrm) -> np.ndarray:
    """(m,) bool: receivers (normals nrm, (m,) float32 triple) with some corner of the lamp's
    rectangle (d : the (m,) float64 components of receiver -> `shape.corner`) above their tangent
    plane by more than 1e-4 of its distance (plus the lamp's size): False where every sample of
    the rectangle (the corners' convex hull) lies below it, whatever float32 rounding does."""
    height = d[0] * nrm[0] + d[1] * nrm[1] + d[2] * nrm[2]
    ex, ey = shape.frame[0], shape.frame[1]
    for edge in (np.asarray(ex, np.float64) * shape.len_u, np.asarray(ey, np.float64) * shape.len_v):
        height += np.maximum(edge[0] * nrm[0] + edge[1] * nrm[1] + edge[2] * nrm[2], 0.0)
    reach = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) + 2.0 * shape.extent
    return height > -1e-4 * reach


def _exact_at(shape, radiance, p, nrm, live, every, need, known):
    """(k,) float64 at the k live receivers: the lamp's exact unshadowed irradiance where need
    (k,) holds, 0 elsewhere. known : None or the chunk's (m,) float64 column of values already
    computed (NaN where not), read where present and written where computed here: the penumbra
    pass's receivers were all shaded by the first pass (`penumbra.adaptive_direct`)."""
    exact = np.zeros(need.shape[0])
    rows = np.flatnonzero(need)
    if rows.size == 0:
        return exact
    chunk_rows = rows if every else live[rows]
    if known is None:
        exact[rows] = _analytic(shape, radiance, p, nrm, chunk_rows, False)
        return exact
    have = known[chunk_rows]
    todo = np.isnan(have)
    if todo.any():
        have[todo] = _analytic(shape, radiance, p, nrm, chunk_rows[todo], False)
        known[chunk_rows[todo]] = have[todo]
    exact[rows] = have
    return exact


def _analytic(shape, radiance, p, nrm, live, every):
    """The lamp's exact unshadowed irradiance at the live receivers (Lambert's polygon formula)."""
    rows = live if not every else slice(None)
    points = np.stack([q[rows] for q in p], axis=1)
    normals = np.stack([q[rows] for q in nrm], axis=1)
    polygon = polygon_light.lamp_polygon(shape.centre, shape.half_u, shape.half_v, shape.round)
    return polygon_light.cosine_solid_angle(polygon, points, normals) * radiance


def _times_visibility(exact, estimate, shadowed, unshadowed):
    """The ratio estimator of `polygon_light` (Heitz et al. 2018): the lamp's exact unshadowed
    irradiance times the share of the samples' unshadowed contribution that reached it. Where
    no sample saw the lamp unshadowed (all behind the horizon or outside an ellipse) the plain
    estimate stays."""
    seen = unshadowed > 0
    ratio = np.divide(shadowed, unshadowed, out=np.zeros_like(shadowed), where=seen)
    return np.where(seen, exact * ratio, estimate).astype(_F32)


def _sample_spherical_rectangle(x0, y0, z0, len_x, len_y, u, v):
    """Urena, Fajardo & King 2013: directions uniform in the solid angle of a rectangle.

    The rectangle spans [x0, x0 + len_x] x [y0, y0 + len_y] in the plane z = z0 < 0 of a frame
    centred on the receiver. x0, y0, z0 : (m,) float64; u, v : (m, s) float in [0, 1).

    The receiver's terms (edge planes, solid angle) are float64: the solid angle is a small
    difference of angles that sum to ~2 pi. The samples' are float32, with cos and sin of the
    sample angle k + u S by angle addition (float32 cos / sin of u S are vectorised, float64 ones
    are not and cost ~15 ns each): their ~1e-7 error only moves a sample by that much on the lamp.

    Returns xu, yv : (m, s) float32 local coordinates of the samples on the rectangle,
    valid : (m, s) bool (false where a degenerate receiver gave no finite sample) and
    S : (m,) float64 solid angle, the inverse of the (uniform) pdf.
    """
    x1, y1 = x0 + len_x, y0 + len_y
    z0sq = z0 * z0
    # z components of the unit normals of the four planes through the receiver and each edge.
    n0z = -y0 / np.sqrt(z0sq + y0 * y0)
    n1z = x1 / np.sqrt(z0sq + x1 * x1)
    n2z = y1 / np.sqrt(z0sq + y1 * y1)
    n3z = -x0 / np.sqrt(z0sq + x0 * x0)
    g0 = np.arccos(np.clip(-n0z * n1z, -1.0, 1.0))
    g1 = np.arccos(np.clip(-n1z * n2z, -1.0, 1.0))
    a2 = np.clip(-n2z * n3z, -1.0, 1.0)
    a3 = np.clip(-n3z * n0z, -1.0, 1.0)
    g2 = np.arccos(a2)
    g3 = np.arccos(a3)
    k = 2.0 * np.pi - g2 - g3
    solid_angle = np.maximum(g0 + g1 - k, 0.0)
    col = lambda a: a.astype(_F32)[:, None]  # noqa: E731  (per receiver -> a float32 column)
    b0, b1 = col(n0z), col(n2z)
    # cos k = cos(g2 + g3), sin k = -sin(g2 + g3) from the cosines a2, a3 (sines >= 0 on
    # [0, pi]): square roots instead of float64 cos / sin.
    s2 = np.sqrt(np.maximum(1.0 - a2 * a2, 0.0))
    s3 = np.sqrt(np.maximum(1.0 - a3 * a3, 0.0))
    ck, sk = col(a2 * a3 - s2 * s3), col(-(s2 * a3 + a2 * s3))
    f32 = np.asarray(u, _F32)
    t = f32 * col(solid_angle)
    ct, st = np.cos(t), np.sin(t)
    cos_au = ck * ct
    cos_au -= sk * st
    sin_au = sk * ct
    sin_au += ck * st
    z = col(z0)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        fu = cos_au * b0
        fu -= b1
        fu /= sin_au
        cu = np.copysign(_F32(1.0), fu) / np.sqrt(fu * fu + b0 * b0)
        np.clip(cu, -1.0, 1.0, out=cu)
        xu = -(cu * z) / np.sqrt(_F32(1.0) - cu * cu)
        xa, xb = col(x0), col(x1)
        np.clip(xu, xa, xb, out=xu)
        dist2 = xu * xu + z * z
        ya, yb = col(y0), col(y1)
        h0 = ya / np.sqrt(dist2 + ya * ya)
        h1 = yb / np.sqrt(dist2 + yb * yb)
        hv = h1 - h0
        hv *= np.asarray(v, _F32)
        hv += h0
        hv2 = hv * hv
        yv = np.where(hv2 < _F32(1.0 - 1e-7), hv * np.sqrt(dist2 / np.maximum(_F32(1.0) - hv2, _F32(1e-30))), yb)
    valid = np.isfinite(xu) & np.isfinite(yv)
    if not valid.all():
        xu = np.where(valid, xu, xa)
        yv = np.where(valid, yv, ya)
    return xu, yv, valid, solid_angle


def _area_chunk_by_area(shape, radiance, p, nrm, tracer, u, v, samples, epsilon, partial=None, opened=None,
                        light=None):
    """Uniform area sampling, for sheared (non-rectangular) lamps that Urena's method cannot take."""
    qx, qy, qz = _area_points(shape, u, v)
    wx, wy, wz = qx - p[0][:, None], qy - p[1][:, None], qz - p[2][:, None]  # receiver -> sample
    d_min2 = max(AREA_MIN_DISTANCE_FRACTION**2 * shape.area / samples, epsilon * epsilon)
    d2 = np.maximum(wx * wx + wy * wy + wz * wz, _F32(d_min2))
    inv_d = 1.0 / np.sqrt(d2)
    cos_r = (wx * nrm[0][:, None] + wy * nrm[1][:, None] + wz * nrm[2][:, None]) * inv_d
    ln = shape.normal
    cos_l = -(wx * ln[0] + wy * ln[1] + wz * ln[2]) * inv_d
    g = np.maximum(cos_r, 0.0) * np.maximum(cos_l, 0.0) / d2
    cone = None if light is None else spread_attenuation(
        light, cos_l, np.sqrt(np.maximum(1.0 - cos_l * cos_l, 0.0)) / np.maximum(cos_l, _F32(1e-30)))
    if cone is not None:
        g *= cone
    if opened is not None:
        opened.append(g.sum(axis=1) * _F32(radiance * shape.area / samples))
    if tracer is not None:
        rows, cols = np.nonzero(g > 0)
        if rows.size:
            vis = _shadow_to_targets(tracer, p, nrm, rows, qx[rows, cols], qy[rows, cols], qz[rows, cols], epsilon)
            g[rows[~vis], cols[~vis]] = 0.0
            _mark_partial(partial, rows, ~vis, g.shape[0])
    return g.sum(axis=1) * _F32(radiance * shape.area / samples)


# --------------------------------------------------------------------------------------------
# Public entry point
# --------------------------------------------------------------------------------------------


def one_sample_exact(light: Light) -> bool:
    """Whether one sample of `light` with `direct_irradiance(ratio_samples=1)` gives its exact
    unshadowed irradiance times that sample's visibility (or 0 where the sample missed it): point
    and spot lamps (hard, or a sphere or disc in closed form), suns whose disc is at most
    ONE_SAMPLE_SUN_ANGLE wide (one direction's cosine is the disc's mean within ~1%), rectangular
    and round area lamps of full spread (the ratio estimator). Not sheared area lamps (area
    sampling, no closed form) nor spread ones (the cone factor varies over the lamp)."""
    if light.kind in ("POINT", "SPOT"):
        return True
    if light.kind == "SUN":
        return float(light.angle) <= ONE_SAMPLE_SUN_ANGLE
    if light.kind == "AREA":
        shape = _area_shape(light)
        return shape.area > 0.0 and shape.rectangular and float(light.spread) >= np.pi
    return False


def one_sample_exact_lamps(lights: list[Light]) -> np.ndarray:
    """(len(lights),) bool: `one_sample_exact` of each lamp (`penumbra.adaptive_direct`'s exact_lamps)."""
    return np.array([one_sample_exact(light) for light in lights], bool)


def _rough_light(light: Light, pts: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """(n,) float32 a rough unshadowed irradiance of `light` at receivers (pts, nrm (n, 3)): the
    pick weight of `_pick_lamps`. The inverse square of the distance to the lamp's centre (kept
    finite by its size), the receiver's cosine (with a margin: a large lamp reaches receivers that
    face away from its centre), an area lamp's own cosine, a spot's cone; no shadows.

    Never 0 where the lamp can light the receiver: the cosine's margin is at least the sine of
    the lamp's angular radius (`_reach_margin`), so `glossy_noise`'s weak lamps, drawn by this
    weight, are not dropped where some of the lamp rises above the receiver's horizon. (A 10 cm
    area lamp 6 cm from a dragon's scales lit them with its edge: 0 here had dropped a quarter of
    the image's Glossy Direct where a sun lit it too.)"""
    scale = float(light.power) * float(np.mean(light.color))
    if light.kind == "SUN":
        margin = _F32(np.sin(min(0.5 * float(light.angle), 0.5 * np.pi)))
        return (scale * np.clip(nrm @ light.matrix[:3, 2].astype(_F32) + margin, 0.0, None)).astype(_F32)
    v = light.matrix[:3, 3].astype(_F32) - pts
    d2 = np.einsum("ij,ij->i", v, v)
    d = np.sqrt(np.maximum(d2, _F32(1e-30)))
    margin = np.maximum(_F32(0.1), _reach_margin(light, d))
    cos_r = np.clip(np.einsum("ij,ij->i", nrm, v) / d + margin, 0.0, 1.0)
    axis = -light.matrix[:3, 2].astype(_F32)  # spots' and area lamps' emitting direction
    if light.kind == "AREA":
        size2 = float(light.size) * float(light.size if light.shape in ("SQUARE", "DISK") else light.size_y)
        cos_l = np.clip(-(v @ axis) / d + _F32(0.1), 0.0, 1.0)
        return (scale / np.pi * cos_r * cos_l / (d2 + _F32(size2))).astype(_F32)
    e = scale / (4.0 * np.pi) * cos_r / (d2 + _F32(float(light.radius) ** 2 + 1e-8))
    if light.kind == "SPOT":
        inside = -(v @ axis) / d >= _F32(np.cos(min(float(light.spot_size) * 0.5 + 0.1, np.pi)))
        e = np.where(inside, e, _F32(0.0))
    elif light.directional:  # an IES profile
        e = e * spot_attenuation(light, -v.astype(_F32))
    return e.astype(_F32)


def _reach_margin(light: Light, d: np.ndarray) -> np.ndarray:
    """(n,) float32 the sine of the angle a lamp's bounding sphere subtends at distances d (n,)
    from its centre (1 within it): a receiver reaches some of the lamp while its cosine to the
    centre is above minus this. Area lamps: their longer half-diagonal (`_area_shape`: scale and
    shear included); point and spot lamps: their radius."""
    if light.kind == "AREA":
        shape = _area_shape(light)  # its bounding radius: the longer half-diagonal (sheared too)
        reach = float(max(np.linalg.norm(shape.half_u + shape.half_v), np.linalg.norm(shape.half_u - shape.half_v)))
    else:
        reach = float(light.radius)
    if not np.isfinite(reach) or reach <= 0.0:
        return np.zeros_like(d, dtype=_F32)
    return np.minimum(_F32(reach) / np.maximum(d, _F32(1e-30)), _F32(1.0)).astype(_F32)


def rough_lights(lights: list[Light], pts: np.ndarray, nrm: np.ndarray) -> np.ndarray:
    """(n, L) float32 each lamp's rough unshadowed irradiance at receivers (pts, nrm (n, 3)),
    `_rough_light`: what `penumbra.adaptive_direct` weighs the lamps' shadow rays by."""
    pts = np.asarray(pts, _F32).reshape(-1, 3)
    nrm = np.asarray(nrm, _F32).reshape(-1, 3)
    out = np.empty((pts.shape[0], len(lights)), _F32)
    for j, lt in enumerate(lights):
        out[:, j] = _rough_light(lt, pts, nrm)
    return out


def _with_floor(p: np.ndarray, allowed: np.ndarray | None = None) -> np.ndarray:
    """p (n, L) rough lights, in place: plus PICK_FLOOR of each row's sum spread over its lamps
    (and 1e-30), so that every lamp may be drawn (`_pick_lamps`, `_roulette_lamps`); with
    `allowed` (n, L) bool, over the lamps each row allows only (the others stay 0)."""
    if allowed is None:
        p += _F32(PICK_FLOOR / p.shape[1]) * p.sum(axis=1, keepdims=True) + _F32(1e-30)
        return p
    count = np.maximum(allowed.sum(axis=1, keepdims=True), 1).astype(_F32)
    p += (_F32(PICK_FLOOR) * p.sum(axis=1, keepdims=True) / count + _F32(1e-30)) * allowed
    return p


def _pick_lamps(lights: list[Light], pts: np.ndarray, nrm: np.ndarray, budget: int,
                rng: np.random.Generator, allowed: np.ndarray | None = None) -> np.ndarray:
    """(n, L) float32 weights of the lamps each receiver is shaded by: `budget` systematic draws
    (one uniform per receiver, shifted by 1 / budget per draw: a lamp whose probability is at
    least 1 / budget is always drawn) from p_j, its rough light's share of the total (at least
    PICK_FLOOR of it spread over the lamps, so every lamp can be drawn); lamp j weighted by
    (draws of j) / (budget p_j), 0 where not drawn: the weighted sum is unbiased. allowed :
    optional (n, L) bool, the lamps each receiver draws from (the sum estimated is theirs; a row
    that allows none gets no weight)."""
    n, count = pts.shape[0], len(lights)
    p = rough_lights(lights, pts, nrm)
    if allowed is not None:
        p *= allowed
    p = _with_floor(p, allowed)
    none = None
    if allowed is not None:
        none = ~allowed.any(axis=1)
        p[none] = _F32(1.0)  # drawn from, then weighed 0
    p /= p.sum(axis=1, keepdims=True)
    chosen = draw_lamps(p, budget, rng)
    draws = np.zeros((n, count), _F32)
    rows = np.arange(n)
    for k in range(budget):  # each row once per draw: plain fancy += is exact
        draws[rows, chosen[:, k]] += _F32(1.0)
    if allowed is None:
        draws /= _F32(budget) * p
    else:  # a lamp a row does not allow was never drawn: 0, not 0 / 0
        np.divide(draws, _F32(budget) * p, out=draws, where=draws > 0)
        draws[none] = _F32(0.0)
    return draws


def draw_lamps(p: np.ndarray, budget: int, rng: np.random.Generator) -> np.ndarray:
    """(n, budget) lamp indices: `budget` systematic draws per row from the probabilities p (n, L)
    float32 (rows summing to 1): one uniform per row, shifted by 1 / budget per draw; draw k takes
    the first lamp whose cdf reaches u_k (a lamp whose p is 0 only where rounding leaves u past
    the cdf's end or u is 0: callers that allow zeros check)."""
    n, count = p.shape
    cdf = np.cumsum(p, axis=1)
    u = (rng.random((n, 1), dtype=_F32) + np.arange(budget, dtype=_F32)[None, :]) / _F32(budget)
    return np.minimum(np.count_nonzero(cdf[:, None, :] < u[:, :, None], axis=2), count - 1)


def _roulette_lamps(lights: list[Light], pts: np.ndarray, nrm: np.ndarray, budget: int,
                    rng: np.random.Generator) -> np.ndarray | None:
    """(n, L) float32 weights of the lamps each receiver is shaded by, for budget >= L lamps:
    lamp j with probability q_j = min(1, budget p_j) (p_j as `_pick_lamps`' draws: its rough
    light's share, with PICK_FLOOR) and weight 1 / q_j, else 0: unbiased, and exact for every
    lamp of a share of at least 1 / budget; None when that is every lamp at every receiver (no
    draws: all are shaded). Why: a strong lamp beside dim ones traced a shadow ray per hit to
    each dim one (morse_apartment's hits: 5 rays where one lamp gives ~99% of the light)."""
    n, count = pts.shape[0], len(lights)
    p = _with_floor(np.nan_to_num(rough_lights(lights, pts, nrm), nan=0.0, posinf=np.float32(1e30), neginf=0.0))
    q = np.minimum(_F32(budget) * p / p.sum(axis=1, keepdims=True), _F32(1.0))
    if (q >= 1.0).all():
        return None
    u = rng.random((n, count), dtype=_F32)
    return np.where(u < q, _F32(1.0) / q, _F32(0.0)).astype(_F32)


def _lamp_chunk(light: Light, shape, p, q, tracer, rng, samples: int, epsilon: float, solid_angle: bool,
                mark=None, opened=None, known=None, bumped=None,
                ratio_samples: int = RATIO_MIN_SAMPLES) -> np.ndarray | None:
    """(m,) irradiance of one sampled (not axial) lamp at a chunk's receivers (p, q: x, y, z
    tuples of (m,)), by its kind: `_point_chunk`, `_sun_chunk`, `_beam` (Spread 0) or
    `_area_chunk`; None for an area lamp without a shape (zero area). mark, opened, known: their
    per-lamp outputs and the exact light to reuse. bumped : (points, normals, smooth normals)
    (m, 3) for the bump shadowing term (`_bump_weight`, applied to `opened` too), or None."""
    if light.kind in ("POINT", "SPOT"):
        e = _point_chunk(light, p, q, tracer, rng, samples, epsilon, mark, opened)
    elif light.kind == "SUN":
        e = _sun_chunk(light, p, q, tracer, rng, samples, epsilon, mark, opened, ratio_samples)
    elif shape is None:
        return None
    elif float(light.spread) <= 0.0:
        e = _beam(light, shape, p, q, tracer, epsilon, opened)
    else:
        e = _area_chunk(light, shape, p, q, tracer, rng, samples, epsilon, mark, solid_angle, opened, known,
                        ratio_samples)
    if bumped is not None:
        bump = _bump_weight(light, *bumped)
        e = e * bump
        if opened:
            opened[0] = opened[0] * bump
    return e


def _shade_picked(light: Light, shape, weight: np.ndarray, p, q, tracer, rng, samples: int, epsilon: float,
                  solid_angle: bool, acc: np.ndarray, bumped=None) -> None:
    """acc (m, 3) += weight x the light of `light` at the receivers of the chunk (p, q: x, y, z
    tuples) that picked it (weight > 0; `_pick_lamps`). bumped : (normals, smooth normals) of the
    chunk's receivers for the bump shadowing term (`_bump_weight`), or None."""
    rows = np.flatnonzero(weight > 0)
    if rows.size == 0:
        return
    ps = tuple(np.ascontiguousarray(c[rows]) for c in p)
    qs = tuple(np.ascontiguousarray(c[rows]) for c in q)
    bumped = None if bumped is None else (np.stack(ps, axis=1), bumped[0][rows], bumped[1][rows])
    e = _lamp_chunk(light, shape, ps, qs, tracer, rng, samples, epsilon, solid_angle, bumped=bumped)
    if e is not None:
        acc[rows] += (e * weight[rows])[:, None] * light.color[None, :]


def _bump_weight(light: Light, pts: np.ndarray, nrm: np.ndarray, smooth: np.ndarray | None):
    """(m,) float32 bump shadowing weight of a lamp's light at receivers (1 without `smooth`)."""
    if smooth is None:
        return np.ones(pts.shape[0], _F32)
    from .bump import shadowing_term  # noqa: PLC0415  (bump imports nothing from here)

    if light.kind == "SUN":
        wi = np.broadcast_to(-light.direction.astype(_F32), pts.shape)
    else:
        wi = light.position[None, :] - pts
        wi = wi / np.maximum(np.linalg.norm(wi, axis=1, keepdims=True), _F32(1e-30))
    return shadowing_term(smooth, nrm, np.ascontiguousarray(wi, _F32))


def direct_irradiance(
    lights: list[Light],
    points: np.ndarray,
    normals: np.ndarray,
    tracer: Tracer | None,
    rng: np.random.Generator,
    samples: int = 1,
    epsilon: float = 1e-4,
    sun_disc: bool = True,
    partial: np.ndarray | None = None,
    solid_angle: bool = True,
    unshadowed: np.ndarray | None = None,
    exact: np.ndarray | None = None,
    per_lamp: np.ndarray | None = None,
    lamp_budget: int | None = None,
    smooth: np.ndarray | None = None,
    ratio_samples: int = RATIO_MIN_SAMPLES,
) -> np.ndarray:
    """Irradiance from the lamps at one-sided Lambertian receivers, with shadow rays.

    Lamps only: the world and emissive meshes live in the irradiance cache.

    Parameters
    ----------
    lights : the scene's lamps.
    points : (n, 3) float32 world-space receiver positions.
    normals : (n, 3) float32 unit normals; light from below (n . l <= 0) contributes nothing.
    tracer : `occluded` is called for shadow rays; None traces no shadows.
    rng : source of the sample patterns; results are deterministic given its state, and the
        stream consumed does not depend on the tracer or on which receivers face a lamp.
    samples : samples per receiver for area lights, sun discs (angle > 0) and soft point/spot
        shadows (radius > 0); hard lamps always use one ray.
    epsilon : metres; shadow rays start this far along the normal and stop this short of the lamp.
    sun_disc : sample the sun's angular disc (soft shadows); False traces one ray along its axis,
        enough where the result is averaged anyway (probe-ray hits of the low-frequency cache).
    partial : optional (n,) bool output: set True at receivers where some of a sampled lamp's
        shadow rays were blocked and some were not (a penumbra; hard lamps never set it); or
        (n, len(lights)): column i for lights[i] alone (`penumbra.adaptive_direct` re-samples
        only the lamps whose penumbra crosses a pixel).
    solid_angle : sample rectangular area lamps uniformly in their solid angle (Urena et al.:
        quiet near a large lamp, ~3 us of float64 set-up per receiver); False samples them
        uniformly over their area (~5x cheaper per receiver, noisier close to the lamp), enough
        for ray hits whose light is averaged anyway (probe rays into the cache, pixel rays).
    unshadowed : optional (n, 3) float32 output: the same samples' light without shadows (the
        exact unshadowed irradiance where the ratio estimator applies), at no extra sampling:
        a penumbra's visibility is the ratio of the two (`penumbra.filter_penumbra`).
    exact : optional (n, len(lights)) float64 in/out: the rectangular area lamps' exact
        unshadowed irradiance per receiver (column i for lights[i]; NaN where not computed),
        read where present, written where computed: a second pass over the same receivers
        (`penumbra.adaptive_direct`'s penumbra pass) reuses the first pass's (~1 us per receiver
        and lamp) and gets the same result. Computed only where the ratio estimator uses it.
    smooth : optional (n, 3) float32 smooth surface normals under receivers whose `normals` a
        normal map bent (`bump.smooth_normals`): each lamp's light is weighed by Cycles' bump
        shadowing term towards the lamp's centre (`bump.shadowing_term`; exact for suns and
        point lamps, the centre's direction for area lamps and the sun's disc).
    ratio_samples : fewest samples per receiver at which rectangular and round area lamps take
        the ratio estimator (RATIO_MIN_SAMPLES); 1 makes a lamp of `one_sample_exact` give its
        exact unshadowed light times one ray's visibility, or 0 where the sample missed the lamp
        (outside a round lamp, below the horizon): what `penumbra`'s probes check pixels with.

    Returns
    -------
    (n, 3) float32 irradiance in W/m^2 times each lamp's colour. Receivers with non-finite
    position or normal get 0.
    """
    if samples < 1:
        raise ValueError(f"samples must be >= 1, got {samples}")
    pts = np.asarray(points, _F32).reshape(-1, 3)
    nrm = np.asarray(normals, _F32).reshape(-1, 3)
    if pts.shape != nrm.shape:
        raise ValueError(f"points {pts.shape} and normals {nrm.shape} differ in shape")
    n = pts.shape[0]
    out = np.zeros((n, 3), _F32)
    if partial is not None:
        partial[:] = False
    if unshadowed is not None:
        unshadowed[:] = 0.0
    if per_lamp is not None:
        per_lamp[:] = 0.0
    column = [i for i, lt in enumerate(lights) if float(lt.power) != 0.0 and np.any(lt.color != 0)]
    active = [lights[i] for i in column]
    if n == 0 or not active:
        return out
    shapes = {}
    for i, lt in enumerate(active):
        if lt.kind == "AREA":
            shape = _area_shape(lt)
            if shape.area > 0.0:
                shapes[i] = shape
            else:
                log.debug("area light %r has zero area; skipped", lt.name)

    sel = None
    # Whole-array test first: the per-row reduction over 3 columns is slow and rarely needed.
    if not (np.isfinite(pts).all() and np.isfinite(nrm).all()):
        sel = np.nonzero(np.isfinite(pts).all(axis=1) & np.isfinite(nrm).all(axis=1))[0]
    if smooth is not None:
        smooth = np.asarray(smooth, _F32).reshape(-1, 3)
    if sel is not None:
        pts, nrm = pts[sel], nrm[sel]
        smooth = None if smooth is None else smooth[sel]
    known = exact if exact is None or sel is None else exact[sel]
    acc = np.zeros((pts.shape[0], 3), _F32)
    found = np.zeros((pts.shape[0],) + partial.shape[1:], bool) if partial is not None else None
    shares = np.zeros((pts.shape[0], len(lights), 3), _F32) if per_lamp is not None else None
    acc_open = np.zeros((pts.shape[0], 3), _F32) if unshadowed is not None else None
    # Suns traced along their axis need no sample patterns: whole arrays at once, row-major.
    axial = [lt.kind == "SUN" and (not sun_disc or float(lt.angle) <= 0.0) for lt in active]
    for i, (lt, ax) in enumerate(zip(active, axial, strict=True)):
        if ax:
            opened = [] if acc_open is not None else None
            bump = _bump_weight(lt, pts, nrm, smooth)
            e = (_sun_axis(lt, pts, nrm, tracer if lt.cast_shadow else None, epsilon, opened) * bump)[:, None]
            e = e * lt.color[None, :]
            acc += e
            if shares is not None:
                shares[:, column[i]] = e
            if opened:
                acc_open += (opened[0] * bump)[:, None] * lt.color[None, :]
    sampled = [(i, lt) for i, (lt, ax) in enumerate(zip(active, axial, strict=True)) if not ax]
    picked = None
    if lamp_budget is not None and len(sampled) > lamp_budget:
        if any(o is not None for o in (partial, unshadowed, exact, per_lamp)):
            raise ValueError("lamp_budget shades some lamps per receiver: no per-lamp outputs")
        picked = _pick_lamps([lt for _, lt in sampled], pts, nrm, lamp_budget, rng)
    elif (lamp_budget is not None and len(sampled) >= ROULETTE_MIN_LAMPS
          and all(o is None for o in (partial, unshadowed, exact, per_lamp))):
        picked = _roulette_lamps([lt for _, lt in sampled], pts, nrm, lamp_budget, rng)
    step = max(1, CHUNK_RAYS // samples)
    for start in range(0, pts.shape[0] if sampled else 0, step):
        stop = min(start + step, pts.shape[0])
        p = tuple(np.ascontiguousarray(pts[start:stop, k]) for k in range(3))
        q = tuple(np.ascontiguousarray(nrm[start:stop, k]) for k in range(3))
        for slot, (i, lt) in enumerate(sampled):
            tr = tracer if lt.cast_shadow else None  # the lamp's Shadow checkbox off: no shadow rays
            if picked is not None:
                _shade_picked(lt, shapes.get(i), picked[start:stop, slot], p, q, tr, rng, samples, epsilon,
                              solid_angle, acc[start:stop],
                              None if smooth is None else (nrm[start:stop], smooth[start:stop]))
                continue
            mark = None if found is None else found[start:stop] if found.ndim == 1 else found[start:stop, column[i]]
            opened = [] if acc_open is not None else None
            e = _lamp_chunk(lt, shapes.get(i), p, q, tr, rng, samples, epsilon, solid_angle, mark, opened,
                            None if known is None else known[start:stop, column[i]],
                            None if smooth is None else (pts[start:stop], nrm[start:stop], smooth[start:stop]),
                            ratio_samples)
            if e is None:
                continue
            e = e[:, None] * lt.color[None, :]
            acc[start:stop] += e
            if shares is not None:
                shares[start:stop, column[i]] = e
            if opened:
                acc_open[start:stop] += opened[0][:, None] * lt.color[None, :]
    if partial is not None:
        partial[slice(None) if sel is None else sel] = found
    if unshadowed is not None:
        unshadowed[slice(None) if sel is None else sel] = acc_open
    if per_lamp is not None:
        per_lamp[slice(None) if sel is None else sel] = shares
    if known is not None and sel is not None:
        exact[sel] = known
    if sel is None:
        return acc
    out[sel] = acc
    return out
