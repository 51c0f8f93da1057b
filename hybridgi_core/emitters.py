"""Emissive triangles as lights: next-event estimation of the direct light they give receivers.

Why: a room lit by an emissive panel (a light fixture, a screen, neon) reaches the pixels only
through rays that happen to hit the emitter (pixel rays, the cache's probe rays): a 0.6 m panel
in a closed room, 640x360 against Cycles, gave Combined 0.27 at the cheapest rung and 0.13 at
the richest (12 s), blotchy walls and almost no contact shadows, where Cycles + OIDN reached
0.13 in 3.6 s: Cycles samples emissive triangles as lights. Here each receiver draws `samples`
points on the emitters, triangles chosen in proportion to their power (radiance luminance x
area) and points uniform on each, and traces a shadow ray to each point.

Emission is two-sided, as the rays read it (`shading.SurfaceTable.emission_of` on any hit), except
where an object's emissive triangles close a volume: their inner side is never seen (`_sides`).

Textured emission (a screen, a sign, a glTF emissive map: `SurfaceTable.glowing`) is sampled as
well: a triangle is chosen by its mean radiance (`radiance`, the texture averaged over the
triangle) and each sample reads the texture at its own point (`texture`). Left to the rays, a
checkered neon sign lit its wall and floor 28% dim (Diffuse Direct against Cycles; the rays' rare
bright hits are what the residual's filter spreads thinnest).

Where it is used (final renders with pixel rays): the frame's full-res direct light adds it at
every pixel (`FramePipeline._centre_direct`; subframes at the pixels that see another surface),
and the pixel rays leaving those pixels no longer count what they find of these triangles
(`SurfaceTable.diffuse_emission`; their control variate, the cache's direct band, still holds the
emitters, so the residual removes the cache's share: the pixel's emitter light is the samples'
alone). Everything else is as before: the cache's probe rays, the hits' further bounces and
their lamp light read from the image (`ScreenLight`, built before the emitters are added), the
glossy lobes and the viewport see emitters through rays.

numpy only (no bpy).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from . import polygon_light
from .environment import LUMA as ENV_LUMA
from .lights import AREA_MIN_DISTANCE_FRACTION, _onb, shadow_query

_F32 = np.float32
#: Rec. 709 luminance (the environment's weights, as float32): the power that chooses a triangle.
LUMA = ENV_LUMA.astype(_F32)
#: Receivers per block of work: bounds the (receivers x samples) arrays.
BLOCK = 1 << 14
#: Emitter samples per pixel of a frame's direct light, as a share of its lamps' shadow samples
#: in penumbrae (at least MIN_PIXEL_SAMPLES): every pixel takes them, lamps' full count only
#: where a penumbra crosses.
PIXEL_SHARE = 1.0 / 3.0
MIN_PIXEL_SAMPLES = 4


#: Pixels sample the emitters when these give at least this share of the scene's light (their
#: flux against the lamps'): a small glowing screen in a lamp-lit room is left to the rays, whose
#: cost it does not change, rather than paying every pixel's samples for a few % of the light
#: (spheres' glowing ball: 4%; the McGuire box's ceiling panel beside its lamp: 4%).
MIN_LIGHT_SHARE = 0.1


def emitter_samples(shadow_samples: int) -> int:
    """Emitter samples per pixel of a frame whose lamps take `shadow_samples` in penumbrae."""
    return max(MIN_PIXEL_SAMPLES, int(round(shadow_samples * PIXEL_SHARE)))


def worth_sampling(emitters: MeshLights | None, lights) -> bool:
    """Whether the pixels should sample `emitters` (see MIN_LIGHT_SHARE): their flux (both sides,
    luminance) against the lamps' power x colour luminance; a sun's flux is unbounded (no)."""
    if emitters is None:
        return False
    flux = 2.0 * np.pi * float((emitters.radiance @ LUMA).astype(np.float64) @ emitters.area)
    lamps = 0.0
    for light in lights:
        if light.kind == "SUN" and float(light.power) > 0:
            return False
        lamps += max(float(light.power), 0.0) * float(np.asarray(light.color, np.float32) @ LUMA)
    return bool(np.isfinite(flux)) and flux >= MIN_LIGHT_SHARE * (flux + lamps)


@dataclass(frozen=True)
class MeshLights:
    """The emissive triangles of a scene, ready to sample.

    prims : (k,) the triangles' indices in the traced geometry
    v0, e1, e2 : (k, 3) float32 a corner and the two edges from it
    normal : (k, 3) float32 unit geometric normals
    area : (k,) float64
    radiance : (k, 3) float32 emitted radiance (both sides)
    choose : (k,) float64 the probability of choosing each triangle (power share)
    cdf : (k,) float64 its running sum (last = 1)
    centre, radius : (k, 3), (k,) float32 each triangle's bounding sphere
    group : (k,) int64 the compact emitter (`COMPACT_FILL`) each triangle belongs to, -1 for none
    spheres : (G, 4) float64 each compact emitter's bounding sphere (centre, radius)
    group_share : (G,) float64 each compact emitter's share of the power (its triangles' choose)
    side : (k,) int8 the side a triangle's light leaves by: +1 its normal's, -1 the other, 0 both
        (`_sides`); None: both
    glows : (k,) bool the triangles whose radiance varies over them (an emission texture), or None:
        `radiance` is their mean, and a sample reads `texture`
    texture : texture(prims (c,), u (c,), v (c,)) -> (c, 3) float32 the radiance of triangles
        `prims` (indices in the traced geometry) at barycentrics u, v (`shading.SurfaceTable`)
    closed : (k,) int the closed emitter (one object's triangles with a `side`) each triangle
        bounds, -1 for none; None: none (`exact`: a receiver inside one sees its inner sides)
    clusters : `Clusters` of the triangles sampled by power (more than EXACT_TRIANGLES, at most
        MAX_CLUSTERS clusters), or None: triangles chosen by their power share alone
    """

    prims: np.ndarray
    v0: np.ndarray
    e1: np.ndarray
    e2: np.ndarray
    normal: np.ndarray
    area: np.ndarray
    radiance: np.ndarray
    choose: np.ndarray
    cdf: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    group: np.ndarray
    spheres: np.ndarray
    group_share: np.ndarray
    side: np.ndarray | None = None
    glows: np.ndarray | None = None
    texture: Callable | None = None
    closed: np.ndarray | None = None
    clusters: Clusters | None = None

    @classmethod
    def from_triangles(cls, positions: np.ndarray, triangles: np.ndarray, emission: np.ndarray,
                       skip: np.ndarray | None = None, objects: np.ndarray | None = None,
                       glows: np.ndarray | None = None, texture: Callable | None = None) -> MeshLights | None:
        """From a geometry's (V, 3) positions, (T, 3) triangles and (T, 3) per-triangle emitted
        radiance; skip : (T,) bool triangles left to the rays; objects : (T,)
        each triangle's object (None: one object each), which `COMPACT_FILL` judges; glows,
        texture as `from_packed`. None when nothing emits."""
        p = np.asarray(positions, np.float32)[np.asarray(triangles)]
        return cls.from_packed(np.concatenate([p[:, 0], p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]], axis=1), emission, skip,
                               objects, glows, texture)

    @classmethod
    def from_packed(cls, packed: np.ndarray, emission: np.ndarray, skip: np.ndarray | None = None,
                    objects: np.ndarray | None = None, glows: np.ndarray | None = None,
                    texture: Callable | None = None) -> MeshLights | None:
        """From `shading.SurfaceTable`'s (T, 9) packed corners (v0, v1 - v0, v2 - v0) and (T, 3)
        emission (a textured triangle's mean); skip, objects as `from_triangles`; glows : (T,) bool
        the textured triangles, whose samples read `texture` (both or neither)."""
        emission = np.asarray(emission, np.float32).reshape(-1, 3)
        lum = emission @ LUMA
        lit = (lum > 0) & np.isfinite(lum)
        if skip is not None:
            lit &= ~np.asarray(skip, bool)
        prims = np.flatnonzero(lit)
        if prims.size == 0:
            return None
        p = np.asarray(packed, np.float32)[prims]
        owner = prims if objects is None else np.asarray(objects).reshape(-1)[prims]
        built = cls._build(prims, p[:, 0:3], p[:, 3:6], p[:, 6:9], emission, lum, owner)
        if built is None or glows is None or texture is None or not np.asarray(glows, bool)[built.prims].any():
            return built
        return replace(built, glows=np.asarray(glows, bool)[built.prims], texture=texture)

    @classmethod
    def _build(cls, prims, v0, e1, e2, emission, lum, owner=None) -> MeshLights | None:
        cross = np.cross(e1.astype(np.float64), e2.astype(np.float64))
        twice = np.linalg.norm(cross, axis=1)
        keep = twice > 0
        if not keep.any():
            return None
        prims, v0, e1, e2, cross, twice = prims[keep], v0[keep], e1[keep], e2[keep], cross[keep], twice[keep]
        owner = prims if owner is None else np.asarray(owner)[keep]
        area = 0.5 * twice
        power = lum[prims].astype(np.float64) * area
        choose = power / power.sum()
        cdf = np.cumsum(choose)
        cdf[-1] = 1.0
        v0, e1, e2 = (np.ascontiguousarray(a, _F32) for a in (v0, e1, e2))
        centre = v0 + (e1 + e2) / _F32(3.0)
        radius = np.max([np.linalg.norm(v0 + e - centre, axis=1) for e in (0.0, e1, e2)], axis=0)
        group, spheres, share = _compact_groups(owner, v0, e1, e2, area, choose)
        side, closed = _sides(owner, v0, e1, e2) if prims.size <= EXACT_TRIANGLES else (None, None)
        clusters = None if prims.size <= EXACT_TRIANGLES else Clusters.build(owner, centre, radius, power, group)
        return cls(prims, v0, e1, e2, (cross / twice[:, None]).astype(_F32), area, emission[prims], choose, cdf,
                   centre, radius.astype(_F32), group, spheres, share, side, closed=closed, clusters=clusters)

    @property
    def ratio(self) -> bool:
        """Whether receivers take the closed form and a shadowed share (`_ratio_block`): few triangles."""
        return self.prims.size <= EXACT_TRIANGLES

    def radiance_at(self, tri: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(c, 3) float32 the radiance of rows `tri` (c,) at barycentrics u, v (c,): a textured
        triangle's texel there, the others' own."""
        out = self.radiance[tri]
        if self.glows is None:
            return out
        g = np.flatnonzero(self.glows[tri])
        if g.size:
            out[g] = self.texture(self.prims[tri[g]], np.asarray(u, _F32)[g], np.asarray(v, _F32)[g])
        return out

    def irradiance(self, points: np.ndarray, normals: np.ndarray, tracer, rng: np.random.Generator,
                   samples: int, epsilon: float, partial: np.ndarray | None = None,
                   unshadowed: np.ndarray | None = None, cones: np.ndarray | None = None) -> np.ndarray:
        """(n, 3) float32 irradiance the emitters give receivers (points, unit normals (n, 3)),
        `samples` points each with a shadow ray (tracer None: unshadowed). With `ratio`, optional
        outputs as `GISystem.direct`'s for `penumbra.adaptive_direct`: partial (n,) bool, the
        receivers some but not all of whose samples' light was blocked (else untouched);
        unshadowed (n, 3), the light without shadows (exact). Without `ratio` (sampled by power,
        `_block`): unshadowed (n, 3), the light of the samples on triangles without their shadows
        (the same samples' estimate), and cones (n, 3), the part of the returned light that
        compact emitters' cones gave (shadowed by their rays' hits: in both the return and the
        estimate of the light without shadows, which is the rest): `penumbra.filter_emitter_light`
        filters the two apart."""
        pts = np.asarray(points, _F32).reshape(-1, 3)
        nrm = np.asarray(normals, _F32).reshape(-1, 3)
        out = np.zeros((pts.shape[0], 3), _F32)
        for a in range(0, pts.shape[0], BLOCK):
            rows = slice(a, a + BLOCK)
            if self.ratio:
                out[rows] = self._ratio_block(pts[rows], nrm[rows], tracer, rng, samples, epsilon,
                                              None if partial is None else partial[rows],
                                              None if unshadowed is None else unshadowed[rows])
            else:
                out[rows] = self._block(pts[rows], nrm[rows], tracer, rng, samples, epsilon,
                                        None if unshadowed is None else unshadowed[rows],
                                        None if cones is None else cones[rows])
        return out

    def exact(self, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """(n, k) float64 the unshadowed irradiance (luminance-free: Lambert's form factor) each
        triangle gives receivers (points, unit normals (n, 3)), on the sides it emits from."""
        p = np.asarray(points, np.float64).reshape(-1, 3)
        nrm = np.asarray(normals, np.float64).reshape(-1, 3)
        k = self.prims.size
        out = np.zeros((p.shape[0], k))
        corners = [self.v0.astype(np.float64) + e for e in (0.0, self.e1.astype(np.float64), self.e2.astype(np.float64))]
        side = np.zeros(k, np.int8) if self.side is None else self.side
        # Each receiver's height over the faces of closed emitters, on their outer side's sign.
        outer = np.zeros((p.shape[0], k))
        for j in np.flatnonzero(side != 0):
            outer[:, j] = ((p - corners[0][j]) @ self.normal[j].astype(np.float64)) * side[j]
        inside = self._inside(outer, side)
        for j in range(k):
            rows = slice(None)
            if side[j] != 0:  # a closed emitter: only receivers on its outer side see this face,
                # and those inside it (a room whose walls glow: they see every face's inner side)
                rows = np.flatnonzero((outer[:, j] > 0) | inside[:, self.closed[j]])
                if rows.size == 0:
                    continue
            out[rows, j] = polygon_light.cosine_solid_angle(np.stack([c[j] for c in corners]), p[rows], nrm[rows])
        return out

    def _inside(self, outer: np.ndarray, side: np.ndarray) -> np.ndarray:
        """(n, C) bool: the receivers behind every face of each closed emitter (inside a convex
        one), from their heights over the faces on the outer side's sign (outer (n, k));
        C = the closed emitters' count (0 columns without any)."""
        count = 0 if self.closed is None else int(self.closed.max(initial=-1)) + 1
        inside = np.ones((outer.shape[0], count), bool)
        for j in np.flatnonzero(side != 0):
            inside[:, self.closed[j]] &= outer[:, j] <= 0
        return inside

    def _ratio_block(self, p, n, tracer, rng, samples, epsilon, partial=None, unshadowed=None):
        """`irradiance` of a few triangles (EXACT_TRIANGLES at most) as the lamps' ratio estimator
        (`polygon_light`, Heitz et al. 2018): each triangle's exact unshadowed irradiance (`exact`)
        times the share of the samples' light that reaches the receiver. The samples pick a
        triangle in proportion to its exact light at that receiver and a point on it (`_toward`).

        Why: a receiver near a strip or panel drew its samples by the triangles' power, most of
        them on faces it does not see, and a few 1 / d^2-weighted points on the one it does: a room
        lit by a 3 m x 10 cm LED strip read its walls' Diffuse Direct -7% in speckles (rel L1 0.26
        at 160x90 against Cycles). Unshadowed receivers are now exact; penumbrae keep the
        samples' noise, in the share only."""
        # The receivers as the shadow rays leave them, epsilon off their surface: a receiver on an
        # emitter's own face (its pixels, a probe ray's hit on it) lies a rounding error to either
        # side of the face's plane, and behind it Lambert's form sees the face's back (emitters are
        # two-sided) fill its hemisphere: E = pi L at every other pixel of a panel, and a room's
        # bounce light 7-12% high where probe hits sample the emitters.
        exact = self.exact(p + n * _F32(epsilon), n)  # (m, k)
        lum = exact * (self.radiance @ LUMA).astype(np.float64)[None, :]
        total = lum.sum(axis=1)
        light = (exact @ self.radiance.astype(np.float64)).astype(_F32)  # (m, 3) unshadowed
        if unshadowed is not None:
            unshadowed[:] = light
        if (tracer is None and self.glows is None) or samples <= 0:
            return light
        live = np.flatnonzero(total > 0)
        if live.size == 0:
            return light
        cdf = np.cumsum(lum[live], axis=1) / total[live, None]
        u = rng.random((live.size, samples))
        tri = np.minimum((u[:, :, None] > cdf[:, None, :]).sum(axis=2), self.prims.size - 1).reshape(-1)
        u1, u2 = rng.random((2, tri.size), dtype=_F32)
        origin = np.repeat(p[live] + n[live] * _F32(epsilon), samples, axis=0)
        receiver = np.repeat(n[live], samples, axis=0).astype(np.float64)
        # A pass of few samples (the adaptive first pass: it finds the penumbrae, and where none or
        # all of its samples are blocked the estimate is exact whatever their weights) draws its
        # points by area, a third of the solid angle's cost (strip room 640x360: direct 1.9 -> 1.2 s).
        direction, dist, weight, bary = self._toward(tri, origin, u1, u2, epsilon, samples,
                                                     solid=samples >= SOLID_SAMPLES)
        cos_r = np.einsum("ij,ij->i", receiver, direction)
        # Each sample's unshadowed estimate of its triangle's light over the chance of that triangle.
        chance = np.take_along_axis(lum[live], tri.reshape(live.size, samples), axis=1).reshape(-1) / np.repeat(
            total[live], samples)
        open_light = np.where((cos_r > 0) & np.isfinite(weight) & (dist > 0) & (chance > 0),
                              cos_r * weight * (self.radiance[tri] @ LUMA) / np.maximum(chance, 1e-300), 0.0)
        blocked = np.zeros(0, np.int64) if tracer is None else _blocked(tracer, origin, direction, dist,
                                                                         open_light > 0, epsilon)
        if self.glows is not None:
            return self._textured_share(light, live, samples, tri, bary, open_light, blocked, partial)
        seen = open_light.copy()
        seen[blocked] = 0.0
        num = seen.reshape(live.size, samples).sum(axis=1)
        den = open_light.reshape(live.size, samples).sum(axis=1)
        share = np.clip(np.where(den > 0, num / np.maximum(den, 1e-300), 1.0), 0.0, 1.0)
        light[live] *= share.astype(_F32)[:, None]
        if partial is not None:
            partial[live[(share > 0.0) & (share < 1.0)]] = True
        return light

    def _textured_share(self, light, live, samples, tri, bary, open_light, blocked, partial):
        """`_ratio_block`'s shadowed share where some triangles are textured, per channel: the
        samples' light with each one's texel, shadowed, over their light with their triangles'
        mean radiance, unshadowed (whose expectation is the exact `light`): light x share is then
        the textured, shadowed light in expectation, and exact where a receiver's triangles are
        untextured and wholly seen. A receiver is `partial` where some of its samples were blocked
        and some not, not where the texture merely varies: the penumbra pass's rays at every pixel
        lit by a checkered sign read Combined 0.0262 in 2.45 s against 0.0280 in 1.88 s (320x180)."""
        mean = self.radiance[tri] @ LUMA
        scale = np.where(mean > 0, open_light / np.maximum(mean, 1e-30), 0.0)  # cos x weight / chance
        seen = self.radiance_at(tri, *bary).astype(np.float64) * scale[:, None]
        seen[blocked] = 0.0
        den = (self.radiance[tri].astype(np.float64) * scale[:, None]).reshape(live.size, samples, 3).sum(axis=1)
        num = seen.reshape(live.size, samples, 3).sum(axis=1)
        share = np.where(den > 0, num / np.maximum(den, 1e-300), 1.0)
        light[live] *= np.maximum(share, 0.0).astype(_F32)
        if partial is not None:
            lit = (open_light > 0).reshape(live.size, samples)
            hidden = np.zeros(open_light.size, bool)
            hidden[blocked] = True
            hidden = hidden.reshape(live.size, samples)
            partial[live[(hidden & lit).any(axis=1) & (~hidden & lit).any(axis=1)]] = True
        return light

    def _toward(self, tri, origin, u1, u2, epsilon, samples, solid: bool = True):
        """(direction (c, 3), distance (c,), weight (c,), (u, v)) float64 of a point on each triangle
        `tri` seen from `origin` (c, 3), from uniforms u1, u2 (c,); weight: its unshadowed
        irradiance estimate over the radiance, for the triangle alone; u, v (c,) the point's
        barycentrics (where a textured triangle's radiance is read; 0 for untextured ones sampled
        by solid angle).

        Triangles that subtend much of the receiver's sky (near ones) are sampled uniformly in
        their solid angle (Arvo 1995; weight: that solid angle): a point sampled by area right
        next to a receiver gave 1 / d^2 fireflies (a panel 2 cm under a ceiling lights the
        ceiling by its back). A triangle within NEAR_RADII of its bounding radius may subtend
        more than NEAR_SOLID_ANGLE (pi (r / (d - r))^2 bounds it): only those get their solid
        angle. The rest by area (weight: cos_l area / d^2, floored as area lamps sampled by area
        have it)."""
        count = tri.size
        direction = np.zeros((count, 3), np.float64)
        dist = np.zeros(count, np.float64)
        weight = np.zeros(count, np.float64)
        near = np.zeros(count, bool)
        maybe = np.zeros(0, np.int64)
        if solid:
            to_centre = self.centre[tri] - origin
            maybe = np.flatnonzero(np.einsum("ij,ij->i", to_centre, to_centre) < (NEAR_RADII * self.radius[tri]) ** 2)
        omega = np.zeros(count, np.float64)
        bu = np.zeros(count, np.float64)
        bv = np.zeros(count, np.float64)
        if maybe.size:
            corners = [(self.v0[tri[maybe]] + e).astype(np.float64) - origin[maybe]
                       for e in (0.0, self.e1[tri[maybe]], self.e2[tri[maybe]])]
            units = [c / np.maximum(np.linalg.norm(c, axis=1, keepdims=True), 1e-300) for c in corners]
            omega[maybe] = _solid_angle(*units)
            near[maybe] = omega[maybe] > NEAR_SOLID_ANGLE
        far = np.flatnonzero(~near)
        if far.size:
            a, b = u1[far], u2[far]
            fold = a + b > 1
            a, b = np.where(fold, 1 - a, a), np.where(fold, 1 - b, b)
            bu[far], bv[far] = a, b
            t = tri[far]
            w = (self.v0[t] + a[:, None] * self.e1[t] + b[:, None] * self.e2[t] - origin[far]).astype(np.float64)
            d2 = np.einsum("ij,ij->i", w, w)
            dist[far] = np.sqrt(d2)
            direction[far] = w / np.maximum(dist[far], 1e-300)[:, None]
            cos_l = np.abs(np.einsum("ij,ij->i", self.normal[t], direction[far]))
            floor = np.maximum(AREA_MIN_DISTANCE_FRACTION**2 * self.area[t] / samples, epsilon * epsilon)
            weight[far] = cos_l * self.area[t] / np.maximum(d2, floor)
        close = np.flatnonzero(near)
        if close.size:
            pick = near[maybe]
            d = _sample_spherical_triangle(*(u[pick] for u in units), u1[close], u2[close])
            direction[close] = d
            nl = self.normal[tri[close]].astype(np.float64)
            # Distance to the triangle's plane along the sampled direction (inside the triangle).
            along = np.einsum("ij,ij->i", nl, d)
            dist[close] = np.einsum("ij,ij->i", nl, corners[0][pick]) / np.where(np.abs(along) > 1e-12, along, 1e-12)
            weight[close] = omega[close]
            if self.glows is not None:
                bu[close], bv[close] = self._barycentrics(tri[close], origin[close] + d * dist[close, None])
        return direction, dist, weight, (bu, bv)

    def _barycentrics(self, tri: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(u, v) float64 barycentrics of vertices 1 and 2 of the points (c, 3) in the planes of
        triangles `tri` (c,), clipped to the triangle."""
        e1, e2 = self.e1[tri].astype(np.float64), self.e2[tri].astype(np.float64)
        w = points - self.v0[tri].astype(np.float64)
        d00, d01, d11 = (np.einsum("ij,ij->i", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
        d20, d21 = np.einsum("ij,ij->i", w, e1), np.einsum("ij,ij->i", w, e2)
        det = np.maximum(d00 * d11 - d01 * d01, 1e-300)
        u = np.clip((d11 * d20 - d01 * d21) / det, 0.0, 1.0)
        v = np.clip((d00 * d21 - d01 * d20) / det, 0.0, 1.0)
        over = np.maximum(u + v, 1.0)
        return u / over, v / over

    def _block(self, p, n, tracer, rng, samples, epsilon, unshadowed=None, cones=None):
        m = p.shape[0]
        count = m * samples
        if self.clusters is None:
            tri = np.minimum(np.searchsorted(self.cdf, rng.random(count)), self.cdf.size - 1)
            chance, group_chance = self.choose[tri], None
        else:
            tri, chance, group_chance = self.clusters.draw(p, n, samples, rng, self.group, self.spheres.shape[0])
        u1, u2 = rng.random((2, count), dtype=_F32)
        origin = np.repeat(p + n * _F32(epsilon), samples, axis=0)
        receiver = np.repeat(n, samples, axis=0)
        # Samples of compact emitters go through their bounding sphere's cone (`_cone_light`);
        # the rest sample the chosen triangle, as follows.
        cone = self._cone_samples(tri, origin, tracer)
        by_triangle = np.ones(count, bool)
        by_triangle[cone] = False
        direction = np.zeros((count, 3), np.float64)  # cone samples keep 0: no weight below
        dist = np.zeros(count, np.float64)
        weight = np.zeros(count, np.float64)
        picked = np.flatnonzero(by_triangle)
        if picked.size:
            t = tri[picked]
            direction[picked], dist[picked], w, (bu, bv) = self._toward(t, origin[picked], u1[picked], u2[picked],
                                                                        epsilon, samples)
            weight[picked] = w / chance[picked]  # the triangle's chance at this receiver
        cos_r = np.einsum("ij,ij->i", receiver, direction)
        weight = np.where((cos_r > 0) & np.isfinite(weight) & (dist > 0), cos_r * weight, 0.0)
        if self.glows is None or not picked.size:
            radiance = self.radiance[tri]
        else:
            radiance = np.zeros((count, 3), _F32)
            radiance[picked] = self.radiance_at(tri[picked], bu, bv)
        if unshadowed is not None:
            unshadowed[:] = (radiance * weight[:, None].astype(_F32)).reshape(m, samples, 3).mean(axis=1)
        if tracer is not None:
            weight[_blocked(tracer, origin, direction, dist, weight > 0, epsilon)] = 0.0
        e = radiance * weight[:, None].astype(_F32)
        if cone.size:
            share = self.group_share[self.group[tri[cone]]] if group_chance is None else group_chance[cone]
            e[cone] = self._cone_light(tri[cone], origin[cone], receiver[cone], tracer, u1[cone], u2[cone], share)
            if cones is not None:
                part = np.zeros((count, 3), _F32)
                part[cone] = e[cone]
                cones[:] = part.reshape(m, samples, 3).mean(axis=1)
        elif cones is not None:
            cones[:] = 0.0
        return e.reshape(m, samples, 3).mean(axis=1)

    def _cone_samples(self, tri: np.ndarray, origin: np.ndarray, tracer) -> np.ndarray:
        """Indices of the samples (chosen triangles `tri`, ray origins) whose triangle belongs to a
        compact emitter that the origin lies outside of: they sample its bounding sphere's cone."""
        if tracer is None or self.spheres.shape[0] == 0:
            return np.zeros(0, np.int64)
        cand = np.flatnonzero(self.group[tri] >= 0)
        if cand.size == 0:
            return cand
        sphere = self.spheres[self.group[tri[cand]]]
        gap = np.linalg.norm(sphere[:, :3] - origin[cand], axis=1)
        return cand[gap > sphere[:, 3] * (1.0 + CONE_MARGIN)]

    def _cone_light(self, tri, origin, receiver, tracer, u1, u2, share) -> np.ndarray:
        """(c, 3) float32 one-sample estimates of the light the compact emitters of triangles `tri`
        give receivers (origin, unit normal (c, 3)) outside their bounding spheres: a direction
        uniform in the sphere's cone, traced to its first hit; that hit's emission counts if it is
        a triangle of the same emitter. Divided by `share` (c,), the chance that the receiver's
        sample chose any of the emitter's triangles (its power share, or its clusters' chance,
        `Clusters.draw`): the estimate stands for the whole emitter, so a compact emitter's light
        is estimated by cones alone, wherever its triangles were chosen."""
        g = self.group[tri]
        sphere = self.spheres[g]
        axis = sphere[:, :3] - origin.astype(np.float64)
        gap = np.linalg.norm(axis, axis=1)
        axis /= gap[:, None]
        sin2 = np.minimum((sphere[:, 3] / gap) ** 2, 1.0)
        cos_max = np.sqrt(1.0 - sin2)
        one_minus = sin2 / (1.0 + cos_max)  # 1 - cos_max without cancellation
        cos_t = 1.0 - np.asarray(u1, np.float64) * one_minus
        sin_t = np.sqrt(np.maximum(1.0 - cos_t * cos_t, 0.0))
        phi = 2.0 * np.pi * np.asarray(u2, np.float64)
        t1, t2 = _onb(axis[:, 0], axis[:, 1], axis[:, 2])
        a, b = np.cos(phi) * sin_t, np.sin(phi) * sin_t
        d = np.stack([a * t1[k] + b * t2[k] + cos_t * axis[:, k] for k in range(3)], axis=1)
        cos_r = np.einsum("ij,ij->i", receiver.astype(np.float64), d)
        out = np.zeros((tri.shape[0], 3), _F32)
        live = np.flatnonzero(cos_r > 0)
        if live.size == 0:
            return out
        hits = tracer.intersect(origin[live], np.ascontiguousarray(d[live], _F32), _F32(np.inf), trusted=True)
        row = np.minimum(np.searchsorted(self.prims, hits.prim), self.prims.size - 1)
        same = (hits.prim >= 0) & (self.prims[row] == hits.prim) & (self.group[row] == g[live])
        live, row = live[same], row[same]
        weight = cos_r[live] * 2.0 * np.pi * one_minus[live] / share[live]
        out[live] = self.radiance_at(row, hits.u[same], hits.v[same]) * weight[:, None].astype(_F32)
        return out


def _blocked(tracer, origin: np.ndarray, direction: np.ndarray, dist: np.ndarray, live: np.ndarray,
             epsilon: float) -> np.ndarray:
    """Indices of the samples `live` (bool) marks whose shadow ray from `origin` along
    `direction` is blocked before the emitter `dist` away; the rays stop epsilon short of it
    (it must not hide its own point)."""
    reach = dist.astype(_F32) - _F32(epsilon)
    ray = np.flatnonzero(live & (reach > 0))
    if ray.size == 0:
        return ray
    blocked = np.asarray(shadow_query(tracer)(origin[ray], np.ascontiguousarray(direction[ray], _F32), reach[ray],
                                              trusted=True), bool)
    return ray[blocked]


#: An emitter (one object's emissive triangles) is compact when the mean area it shows a receiver,
#: a quarter of its area (Cauchy's formula; its triangles counted once), fills at least this share
#: of its bounding sphere's disc: a ball (1), a cube (0.64), a squat cylinder; not a panel (0.16),
#: a tube or a strip of neon. Outside its sphere a compact emitter is sampled by directions in the
#: sphere's cone (`MeshLights._cone_light`): nearly every ray meets it, where points chosen on
#: its triangles by power fell half on its far side and weighed 1 / d^2 next to it (a glowing ball
#: on a floor lit by nothing else: Diffuse Direct rel L1 0.31 against Cycles at 16 samples).
COMPACT_FILL = 0.3
#: Receivers within this share of a compact emitter's radius beyond its bounding sphere (or inside
#: it) sample its triangles instead: the cone there is nearly a hemisphere.
CONE_MARGIN = 1e-3


def _objects(owner: np.ndarray, least: int = 4):
    """The row indices of each object's emissive triangles (`owner` (k,) their object), for the
    objects of at least `least` triangles: fewer make no compact emitter and no closed one."""
    _keys, inverse = np.unique(owner, return_inverse=True)
    order = np.argsort(inverse, kind="stable")
    for rows in np.split(order, np.flatnonzero(np.diff(inverse[order])) + 1):
        if rows.size >= least:
            yield rows


def _compact_groups(owner, v0, e1, e2, area, choose) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(group (k,) int64, spheres (G, 4) float64, share (G,) float64) of the emissive triangles
    (corners v0, v0 + e1, v0 + e2, areas, choice probabilities) by their object `owner` (k,):
    the compact objects (COMPACT_FILL) of at least 4 triangles, -1 for the rest."""
    k = owner.shape[0]
    group = np.full(k, -1, np.int64)
    spheres, shares = [], []
    for rows in _objects(owner):
        pts = np.concatenate([v0[rows], v0[rows] + e1[rows], v0[rows] + e2[rows]]).astype(np.float64)
        centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
        radius = float(np.sqrt(((pts - centre) ** 2).sum(axis=1).max()))
        if not (radius > 0.0 and np.isfinite(radius)):
            continue
        if 0.25 * float(area[rows].sum()) >= COMPACT_FILL * np.pi * radius * radius:
            group[rows] = len(spheres)
            spheres.append((*centre, radius))
            shares.append(float(choose[rows].sum()))
    return group, np.asarray(spheres, np.float64).reshape(-1, 4), np.asarray(shares, np.float64)


#: Triangles per cluster (`Clusters`): an emitter's triangles split in halves along the longest
#: axis of their centres until a part holds at most this many.
CLUSTER_TRIANGLES = 4
#: Most clusters (each receiver weighs every one); with more, triangles are chosen by power alone.
MAX_CLUSTERS = 64
#: Share of a receiver's samples that choose a cluster by its power alone, whatever its distance
#: (defensive mixture: no cluster that lights the receiver is left to chance near 0).
CLUSTER_POWER_SHARE = 0.2


@dataclass(frozen=True)
class Clusters:
    """Emissive triangles in spatial clusters, each within one object: a receiver chooses a cluster
    by its power over its squared distance (none wholly below the receiver's horizon), then a
    triangle in it by power.

    Why: chosen by their power share alone, a triangle right by a receiver (a wall 5 cm behind a
    sign cut into 98 triangles, a ceiling 2 cm over a subdivided panel) was one chance in many,
    whose rare samples then weighed many times its light: heavy-tailed noise, most receivers
    reading a fraction of their light and a few a multiple of it (a panel's ceiling, mean of 2300
    probe hits: 0.15, 0.52 and 0.42 with 1, 4 and 16 samples).

    order : (k,) the triangles, cluster by cluster; start : (C + 1,) each cluster's first place in
    `order`; centre (C, 3), radius (C,) bounding spheres; power (C,); within : (k,) each
    triangle's share of its cluster's power; group : (C,) each cluster's compact emitter or -1;
    running : (k + 1,) the running sum of `within` in `order` (0 first): a cluster's members'
    cumulative shares, where `draw` finds a triangle."""

    order: np.ndarray
    start: np.ndarray
    centre: np.ndarray
    radius: np.ndarray
    power: np.ndarray
    within: np.ndarray
    group: np.ndarray
    running: np.ndarray

    @classmethod
    def build(cls, owner, centre, radius, power, group) -> Clusters | None:
        """From the triangles' objects, bounding spheres (centre (k, 3), radius (k,)), power (k,)
        and compact emitters; None with more than MAX_CLUSTERS clusters or only one."""
        parts = []
        # Larger clusters for larger emitters: about MAX_CLUSTERS / 2 of them for one object.
        size = max(CLUSTER_TRIANGLES, -(-int(np.asarray(owner).size) // (MAX_CLUSTERS // 2)))
        for rows in _objects(owner, least=1):
            _split(np.asarray(rows), np.asarray(centre, np.float64), parts, size)
            if len(parts) > MAX_CLUSTERS:
                return None
        if len(parts) < 2:
            return None
        order = np.concatenate(parts)
        start = np.cumsum([0] + [p.size for p in parts])
        c = np.asarray(centre, np.float64)
        pw = np.asarray(power, np.float64)
        centres, radii, totals = [], [], []
        for rows in parts:
            mid = 0.5 * (c[rows].min(axis=0) + c[rows].max(axis=0))
            centres.append(mid)
            radii.append(float((np.linalg.norm(c[rows] - mid, axis=1) + radius[rows]).max()))
            totals.append(float(pw[rows].sum()))
        totals = np.asarray(totals)
        within = np.zeros(order.size)
        which = np.repeat(np.arange(len(parts)), np.diff(start))
        within[order] = pw[order] / np.maximum(totals[which], 1e-300)
        return cls(order, start, np.asarray(centres), np.asarray(radii), totals, within,
                   np.asarray([group[p[0]] for p in parts], np.int64),
                   np.concatenate([[0.0], np.cumsum(within[order])]))

    def chances(self, p: np.ndarray, n: np.ndarray) -> np.ndarray:
        """(m, C) float32 each receiver's (points, unit normals (m, 3)) chance of each cluster."""
        # Squared distances and heights as products with the centres (GEMMs, float32 about the
        # clusters' mean centre: no (m, C, 3) array; the importance need only be roughly right,
        # the weights use the chances it gives), in place.
        ref = self.centre.mean(axis=0)
        q = (np.asarray(p, np.float64) - ref).astype(_F32)
        nf = np.asarray(n, _F32)
        c = (self.centre - ref).astype(_F32)
        d2 = q @ c.T
        d2 *= _F32(-2.0)
        d2 += np.einsum("ij,ij->i", q, q)[:, None]
        d2 += np.einsum("ij,ij->i", c, c)[None, :]
        np.maximum(d2, (self.radius**2).astype(_F32)[None, :], out=d2)
        w = np.divide(self.power.astype(_F32)[None, :], d2, out=d2)
        height = nf @ c.T
        height -= np.einsum("ij,ij->i", nf, q)[:, None]
        w *= height > -self.radius.astype(_F32)[None, :]
        total = w.sum(axis=1, keepdims=True)
        by_power = (self.power / self.power.sum()).astype(_F32)
        dark = total[:, 0] <= 0
        w /= np.where(dark[:, None], _F32(1.0), total)
        if dark.any():
            w[dark] = by_power
        w *= _F32(1.0 - CLUSTER_POWER_SHARE)
        w += _F32(CLUSTER_POWER_SHARE) * by_power[None, :]
        return w

    def draw(self, p, n, samples: int, rng, tri_group: np.ndarray, groups: int):
        """`samples` triangles per receiver: (tri (m s,) rows into the emitters' arrays, their
        chance (m s,), the chance of any triangle of their compact emitter (m s,))."""
        chance = self.chances(p, n)  # (m, C)
        m, k = chance.shape
        cdf = np.cumsum(chance, axis=1, dtype=np.float64)
        cdf /= cdf[:, -1:]
        row = np.repeat(np.arange(m), samples)
        # Every row's CDF offset by its index: one sorted array, one searchsorted for all rows.
        cdf += np.arange(m, dtype=np.float64)[:, None]
        flat = cdf.reshape(-1)
        pick = np.searchsorted(flat, rng.random(m * samples) + row, side="right") - row * k
        pick = np.clip(pick, 0, k - 1)
        first, size = self.start[pick], np.diff(self.start)[pick]
        # Within the cluster by power: its members' running shares.
        u = rng.random(m * samples)
        run = self.running[1:]
        base = self.running[first]
        slot = np.searchsorted(run, base + u * (run[first + size - 1] - base), side="right")
        tri = self.order[np.clip(slot, first, first + size - 1)]
        picked = chance[row, pick].astype(np.float64) * self.within[tri]
        group_chance = np.ones(m * samples)
        if groups:
            by_group = np.zeros((m, groups))
            for c in np.flatnonzero(self.group >= 0):
                by_group[:, self.group[c]] += chance[:, c]
            g = tri_group[tri]
            has = g >= 0
            group_chance[has] = by_group[row[has], g[has]]
        return tri, picked, group_chance


def _split(rows: np.ndarray, centre: np.ndarray, parts: list, size: int) -> None:
    """Append to `parts` the triangle rows split in halves along the longest axis of their centres
    until each part holds at most `size`."""
    if rows.size <= size or len(parts) > MAX_CLUSTERS:
        parts.append(rows)
        return
    c = centre[rows]
    axis = int(np.argmax(c.max(axis=0) - c.min(axis=0)))
    order = rows[np.argsort(c[:, axis], kind="stable")]
    half = order.size // 2
    _split(order[:half], centre, parts, size)
    _split(order[half:], centre, parts, size)


#: Most emissive triangles whose light receivers take in closed form (`MeshLights._ratio_block`):
#: each costs Lambert's formula at every receiver. A panel is 2, a strip or box 12; more (an
#: emissive sphere, text, a subdivided panel) keep sampling by power.
EXACT_TRIANGLES = 16
#: Samples per receiver from which `_ratio_block` draws points in near triangles' solid angles
#: (fewer: by area, whose 1 / d^2 weights make a noisier share in penumbrae): above the 8 of
#: `penumbra.adaptive_direct`'s first pass, which only finds the penumbrae (2% of a strip-lit
#: room's pixels).
SOLID_SAMPLES = 12


def _sides(owner: np.ndarray, v0: np.ndarray, e1: np.ndarray, e2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((k,) int8, (k,) int): +1 for the triangles of an object (`owner`) whose emissive triangles
    close a volume they face out of (every edge shared by two of them, in opposite directions, and
    the volume their normals enclose positive), -1 where they face into it, 0 elsewhere (both
    sides); and the number of the closed volume each bounds (0, 1, ...; -1 for none).

    Why: emission is two-sided, and the inner side of a closed emitter (an LED strip, a box) is
    never seen; counted by the closed form (`MeshLights.exact`), it doubled the light its shadow
    rays then had to take back, so no receiver was exact."""
    side = np.zeros(owner.shape[0], np.int8)
    closed = np.full(owner.shape[0], -1, np.int64)
    corners = np.stack([v0, v0 + e1, v0 + e2], axis=1).astype(np.float64)  # (k, 3, 3)
    scale = max(float(np.abs(corners).max()), 1e-30) * 1e-6
    for rows in _objects(owner):
        c = corners[rows]
        _v, vid = np.unique(np.round(c.reshape(-1, 3) / scale).astype(np.int64), axis=0, return_inverse=True)
        vid = vid.reshape(-1, 3)
        directed = np.concatenate([vid[:, [0, 1]], vid[:, [1, 2]], vid[:, [2, 0]]])
        if np.unique(directed, axis=0).shape[0] != directed.shape[0]:
            continue  # an edge twice in one direction: not one consistently wound surface
        _e, count = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
        if not (count == 2).all():
            continue  # open: a panel, a strip without ends
        volume = float(np.einsum("ij,ij->i", c[:, 0], np.cross(c[:, 1], c[:, 2])).sum()) / 6.0
        extent = float(np.ptp(c.reshape(-1, 3), axis=0).max())
        if abs(volume) > 1e-9 * extent**3:
            side[rows] = 1 if volume > 0 else -1
            closed[rows] = closed.max() + 1
    return side, closed


#: Solid angle (sr) above which a triangle is sampled in its solid angle rather than its area:
#: farther, 1 / d^2 varies little over it and area sampling costs a third as much.
NEAR_SOLID_ANGLE = 0.05
#: Bounding radii within which a triangle may subtend NEAR_SOLID_ANGLE: pi / (k - 1)^2 < 0.05.
NEAR_RADII = 9.0


def _solid_angle(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(k,) solid angle of spherical triangles with unit corners a, b, c (k, 3) float64 (Van
    Oosterom & Strackee 1983: no cancellation of near-pi angles for small triangles)."""
    triple = np.abs(np.einsum("ij,ij->i", a, np.cross(b, c)))
    denom = 1.0 + np.einsum("ij,ij->i", a, b) + np.einsum("ij,ij->i", b, c) + np.einsum("ij,ij->i", c, a)
    return 2.0 * np.arctan2(triple, denom)


def _sample_spherical_triangle(a, b, c, u1, u2) -> np.ndarray:
    """(k, 3) unit directions uniform in the solid angle of spherical triangles with unit corners
    a, b, c (k, 3) float64, from uniforms u1, u2 (k,) (Arvo, "Stratified sampling of spherical
    triangles", 1995)."""
    def unit(x):
        return x / np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-300)

    def dot(x, y):
        return np.einsum("ij,ij->i", x, y)

    n_ab, n_ac, n_bc = unit(np.cross(a, b)), unit(np.cross(a, c)), unit(np.cross(b, c))
    alpha = np.arccos(np.clip(dot(n_ab, n_ac), -1.0, 1.0))
    beta = np.arccos(np.clip(dot(-n_ab, n_bc), -1.0, 1.0))
    gamma = np.arccos(np.clip(dot(n_ac, n_bc), -1.0, 1.0))
    area = np.maximum(alpha + beta + gamma - np.pi, 0.0)
    part = np.asarray(u1, np.float64) * area
    s, t = np.sin(part - alpha), np.cos(part - alpha)
    u = t - np.cos(alpha)
    v = s + np.sin(alpha) * dot(a, b)
    denom = (v * s + u * t) * np.sin(alpha)
    q = np.clip(((v * t - u * s) * np.cos(alpha) - v) / np.where(np.abs(denom) > 1e-300, denom, 1e-300), -1.0, 1.0)
    c_hat = q[:, None] * a + np.sqrt(1.0 - q * q)[:, None] * unit(c - dot(c, a)[:, None] * a)
    z = 1.0 - np.asarray(u2, np.float64) * (1.0 - dot(c_hat, b))
    return unit(z[:, None] * b + np.sqrt(np.maximum(1.0 - z * z, 0.0))[:, None] * unit(c_hat - dot(c_hat, b)[:, None] * b))
