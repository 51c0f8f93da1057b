"""Glossy Direct: the lamps reflected by a Principled BSDF's GGX lobes at image pixels.

Cycles' Glossy Direct is the lamp light its glossy closures reflect towards the camera, divided by
Glossy Color (their albedo at the view angle, `specular.glossy_color`). The lobes are Cycles':
the dielectric specular layer (Fresnel of the adjusted IOR remapped to F0..1, weight
(1 - metallic)(1 - transmission)) and the metallic lobe (Schlick on F0 = base colour, the F82
tint's white default), both GGX with height-correlated Smith masking and, for Multiscatter GGX,
the multiple-scattering factor 1 + Fms (1 - E) / E of `microfacet_ggx_preserve_energy`.

The lamps are sampled as `lights.direct_irradiance` samples them for the diffuse light, with shadow
rays of their own: area lamps uniformly over their area, point and spot lamps over the disc of
their radius facing the receiver, suns over their cone. Surfaces smoother than MIN_ROUGHNESS are
not evaluated: Cycles finds their mirror images of lamps only through BSDF sampling.

The cache's light (`cache_reflection`) is added split-sum: Glossy Color times the incident
radiance averaged over the hemisphere (the cache's irradiance / pi at the pixel, L2 SH blended
over the 8 cells as the diffuse gather blends them), the sky's and emitters' as part of Glossy
Direct (Cycles counts light straight from the world as direct), the bounced light's as Glossy
Indirect. The lobe's direction is not followed: read about the mirror direction, L2 SH leak the
surface's own radiance from below its plane into grazing reflections (10x Cycles' Glossy Indirect
on a floor), so the hemisphere's mean is the better estimate for rough lobes; sharp reflections
of the surroundings are missing.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import sh as shmod
from . import specular as sp
from .evaluate import corner_weights
from .lights import (
    _area_points,
    _area_shape,
    _onb,
    _sample_spherical_rectangle,
    _shadow_to_targets,
    concentric_disk,
    spot_attenuation,
    stratified_uv,
    uniform_cone,
)
from .snapshot import Light

_F32 = np.float32
#: Receivers x samples per block (bounds the temporaries).
CHUNK = 1 << 15
#: Below this roughness a lobe is too sharp to meet a sampled lamp point (Cycles evaluates none).
MIN_ROUGHNESS = 0.02


@dataclass
class GlossyMaterials:
    """Per-material constants of the glossy lobes, indexed by material (row -1 = none).

    rough, alpha2 : (m,) roughness and alpha^2; eta, f0_real : (m,) the layer's IOR and its F0;
    f0 : (m, 3) the layer's tinted F0; weight, metallic : (m,) the lobes' weights; metal_f0 :
    (m, 3); ms : (m,) Multiscatter GGX; fss, fss_metal : (m, 3) average Fresnels; e_avg : (m,).
    """

    rough: np.ndarray
    alpha2: np.ndarray
    eta: np.ndarray
    f0_real: np.ndarray
    f0: np.ndarray
    weight: np.ndarray
    metallic: np.ndarray
    metal_f0: np.ndarray
    ms: np.ndarray
    fss: np.ndarray
    fss_metal: np.ndarray
    e_avg: np.ndarray
    layers: list

    @classmethod
    def from_materials(cls, materials) -> GlossyMaterials:
        layers = [getattr(m, "specular", None) for m in materials]
        n = len(layers)
        out = cls(*(np.zeros(n) for _ in range(4)), np.zeros((n, 3)), np.zeros(n), np.zeros(n), np.zeros((n, 3)),
                  np.zeros(n, bool), np.zeros((n, 3)), np.zeros((n, 3)), np.ones(n), layers)
        _, e_avg_table, _ = sp.tables()
        for i, layer in enumerate(layers):
            if layer is None or layer.roughness < MIN_ROUGHNESS:
                continue
            out.rough[i] = layer.roughness
            out.alpha2[i] = layer.roughness**4
            out.eta[i] = layer.eta if layer.eta >= 1.0 else 1.0 / layer.eta
            out.f0_real[i] = float(sp.f0_from_ior(out.eta[i]))
            out.weight[i] = layer.weight if layer.active else 0.0
            out.f0[i] = layer.f0
            out.metallic[i] = layer.metallic
            out.metal_f0[i] = layer.metal_color
            out.ms[i] = layer.multiscatter
            s_avg = np.clip((sp.fresnel_dielectric_fss(out.eta[i]) - out.f0_real[i]) / max(1.0 - out.f0_real[i], 1e-12), 0, 1)
            out.fss[i] = out.f0[i] + (1.0 - out.f0[i]) * s_avg
            out.fss_metal[i] = out.metal_f0[i] + (1.0 - out.metal_f0[i]) / 21.0
            out.e_avg[i] = float(sp._lerp_table(e_avg_table, [layer.roughness]))
        return out

    @property
    def any(self) -> bool:
        return bool(np.any((self.weight > 0) | (self.metallic > 0)))


def _lobe_terms(mats: GlossyMaterials, rows, n, v, lx, ly, lz):
    """The glossy lobes at m receivers towards s unit directions each, factored so that no
    (m, s, 3) array is needed: BRDF x cos = common (A + B remap + C + D schlick) per channel.

    Returns common (m, s) (D G2 / (4 cos_i), 0 below either horizon), remap (m, s) (the
    dielectric Fresnel remapped to 0..1), schlick (m, s) ((1 - cos(h, i))^5) and k (m, 4, 3):
    A, B the dielectric layer's weight x multiscatter factor x F0 and x (1 - F0); C, D the
    metallic lobe's."""
    a2 = mats.alpha2[rows][:, None].astype(_F32)
    mu_i = np.einsum("ij,ij->i", n, v)[:, None]
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    mu_o = lx * nx + ly * ny + lz * nz
    hx, hy, hz = lx + v[:, 0:1], ly + v[:, 1:2], lz + v[:, 2:3]
    inv = _F32(1.0) / np.maximum(np.sqrt(hx * hx + hy * hy + hz * hz), _F32(1e-12))
    cos_nh = (hx * nx + hy * ny + hz * nz) * inv
    cos_hi = np.clip((hx * v[:, 0:1] + hy * v[:, 1:2] + hz * v[:, 2:3]) * inv, 0.0, 1.0)
    ok = (mu_i > 1e-4) & (mu_o > 0) & (a2 > 0)
    mu_i = np.maximum(mu_i, _F32(1e-4))
    x = cos_nh * cos_nh * (a2 - _F32(1.0)) + _F32(1.0)
    d = a2 / (_F32(np.pi) * x * x)
    g2 = _F32(1.0) / (_F32(1.0) + sp._lambda(a2, mu_i) + sp._lambda(a2, np.where(ok, mu_o, _F32(1.0))))
    common = np.where(ok, d * g2 / (_F32(4.0) * mu_i), _F32(0.0)).astype(_F32)
    f0_real = mats.f0_real[rows][:, None].astype(_F32)
    remap = (sp.fresnel_dielectric(cos_hi, mats.eta[rows][:, None]).astype(_F32) - f0_real) / np.maximum(
        _F32(1.0) - f0_real, _F32(1e-12))
    remap = np.clip(remap, 0.0, 1.0)
    one_minus = _F32(1.0) - cos_hi
    schlick = (one_minus * one_minus) ** 2 * one_minus
    e = sp._lerp_table(sp.tables()[0], [mats.rough[rows], mu_i[:, 0]])[:, None]
    ms, e_avg = mats.ms[rows][:, None], mats.e_avg[rows][:, None]
    scale = np.where(ms, sp.multiscatter_factor(mats.fss[rows], e, e_avg), 1.0) * mats.weight[rows][:, None]
    scale_m = np.where(ms, sp.multiscatter_factor(mats.fss_metal[rows], e, e_avg), 1.0) * mats.metallic[rows][:, None]
    f0, fm0 = mats.f0[rows], mats.metal_f0[rows]
    k = np.stack([scale * f0, scale * (1.0 - f0), scale_m * fm0, scale_m * (1.0 - fm0)], axis=1).astype(_F32)
    return common, remap, schlick, k


def lobes(mats: GlossyMaterials, rows, n, v, lx, ly, lz) -> np.ndarray:
    """(m, s, 3) BRDF x cos(n, l) of the glossy lobes at m receivers towards s unit directions each.

    rows : (m,) material index; n, v : (m, 3) unit normal and direction to the eye; lx, ly, lz :
    (m, s) unit directions to the light. 0 where either direction is below the surface."""
    common, remap, schlick, k = _lobe_terms(mats, rows, *(np.asarray(a, _F32) for a in (n, v, lx, ly, lz)))
    k = k[:, None]
    return common[..., None] * (k[..., 0, :] + k[..., 1, :] * remap[..., None] + k[..., 2, :]
                                + k[..., 3, :] * schlick[..., None])


def glossy_color(mats: GlossyMaterials, rows, mu) -> np.ndarray:
    """(n, 3) float32 Glossy Color at receivers of materials `rows` seen at cosines `mu`."""
    rows = np.asarray(rows)
    out = np.zeros((rows.shape[0], 3))
    for m, layer in enumerate(mats.layers):
        sel = np.flatnonzero(rows == m)
        if sel.size and layer is not None:
            out[sel] = sp.glossy_color(layer, mu[sel])
    return out.astype(_F32)


def _lamp_samples(light: Light, p, rng, samples):
    """(dirs (m, s, 3) unit receiver -> lamp, weight (m, s) radiance-to-radiance factor per sample
    without the BRDF (L x dw / s, lamp colour aside), targets (m, s, 3) or None for a sun)."""
    m = p.shape[0]
    if light.kind == "AREA":
        shape = _area_shape(light)
        if shape.area <= 0:
            return None
        u, v = stratified_uv(rng, m, samples)
        if shape.rectangular:
            return _rectangle_samples(shape, float(light.power) / (np.pi * shape.area), p, u, v, samples)
        qx, qy, qz = _area_points(shape, u, v)
        w = np.stack([qx - p[:, 0:1], qy - p[:, 1:2], qz - p[:, 2:3]], axis=-1)
        d2 = np.maximum((w * w).sum(-1), 1e-8)
        dirs = w / np.sqrt(d2)[..., None]
        cos_l = -(dirs @ shape.normal.astype(np.float64))
        radiance = float(light.power) / (np.pi * shape.area)
        weight = radiance * np.maximum(cos_l, 0.0) * shape.area / (d2 * samples)
        return dirs, weight, np.stack([qx, qy, qz], axis=-1)
    if light.kind in ("POINT", "SPOT"):
        c = light.position.astype(np.float64)
        to = c[None, :] - p
        dist = np.maximum(np.linalg.norm(to, axis=1), 1e-6)
        axis = -to / dist[:, None]
        radius = float(light.radius)
        s = samples if radius > 0 else 1
        if radius > 0:
            u, v = stratified_uv(rng, m, s)
            a, b = concentric_disk(u, v)
            t1, t2 = _onb(axis[:, 0:1], axis[:, 1:2], axis[:, 2:3])
            q = np.stack([c[k] + radius * (a * t1[k] + b * t2[k]) for k in range(3)], axis=-1)
        else:
            q = np.broadcast_to(c, (m, 1, 3)).copy()
        w = q - p[:, None, :]
        d2 = np.maximum((w * w).sum(-1), max(radius * radius, 1e-8))
        dirs = w / np.sqrt((w * w).sum(-1).clip(1e-16))[..., None]
        weight = (float(light.power) / (4.0 * np.pi)) / (d2 * s)
        if light.kind == "SPOT":
            weight = weight * spot_attenuation(light, -to.astype(_F32))[:, None]
        return dirs, weight, q
    to_sun = -light.direction.astype(np.float64)
    half = 0.5 * float(light.angle)
    if half <= 0:
        return np.broadcast_to(to_sun, (m, 1, 3)).copy(), np.full((m, 1), float(light.power)), None
    u, v = stratified_uv(rng, m, samples)
    components, one_minus_cos = uniform_cone(to_sun, half, u.astype(np.float64), v.astype(np.float64))
    dirs = np.stack(components, axis=-1)
    weight = np.full((m, samples), float(light.power) / ((1.0 - 0.5 * one_minus_cos) * samples))
    return dirs, weight, None


def _rectangle_samples(shape, radiance, p, u, v, samples):
    """`_lamp_samples` of a rectangular (or round, in its bounding rectangle) area lamp drawn
    uniformly in its solid angle (Urena et al. 2013, as the diffuse light samples it): every
    sample weighs radiance x solid angle / samples, so receivers near a large lamp stay quiet."""
    m = p.shape[0]
    ex, ey, ez = shape.frame
    d = shape.corner[None, :] - p
    z0 = d @ ez
    live = z0 < -1e-9 * shape.extent  # the emitting side only
    z0 = np.where(live, z0, -1.0)
    x0, y0 = d @ ex, d @ ey
    xu, yv, inside, solid_angle = _sample_spherical_rectangle(x0, y0, z0, shape.len_u, shape.len_v, u, v)
    # Receiver-relative sample vectors per component in float32 (a relative vector, as the
    # diffuse light computes them): (m, s, 3) float64 temporaries were most of the cost.
    z32 = z0.astype(_F32)[:, None]
    w = [xu * _F32(ex[k]) + yv * _F32(ey[k]) + z32 * _F32(ez[k]) for k in range(3)]
    inv = _F32(1.0) / np.maximum(np.sqrt(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]), _F32(1e-12))
    dirs = np.stack([c * inv for c in w], axis=-1)
    weight = np.where(live, radiance * solid_angle / samples, 0.0).astype(_F32)[:, None] * inside
    if shape.round:
        a = (xu - x0.astype(_F32)[:, None]) * _F32(2.0 / shape.len_u) - _F32(1.0)
        b = (yv - y0.astype(_F32)[:, None]) * _F32(2.0 / shape.len_v) - _F32(1.0)
        weight = weight * (a * a + b * b <= 1.0)
    targets = np.stack([p[:, k].astype(_F32)[:, None] + w[k] for k in range(3)], axis=-1)
    return dirs, np.broadcast_to(weight, (m, samples)).copy(), targets


def glossy_direct(lights, points, normals, to_eye, rows, mats: GlossyMaterials, tracer, rng, samples: int = 4,
                  epsilon: float = 1e-4) -> np.ndarray:
    """(n, 3) float32 lamp radiance the glossy lobes reflect towards the eye (Cycles' Glossy Direct
    times Glossy Color), with shadow rays.

    points, normals, to_eye : (n, 3) float32 receivers, unit normals facing the eye and unit
    directions to the eye; rows : (n,) int32 material index (-1: none)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    eye = np.asarray(to_eye, np.float64).reshape(-1, 3)
    rows = np.asarray(rows, np.int64).reshape(-1)
    out = np.zeros((pts.shape[0], 3), _F32)
    active = [lt for lt in lights if float(lt.power) != 0.0 and np.any(lt.color != 0)]
    if not active or not mats.any or pts.shape[0] == 0:
        return out
    valid = (rows >= 0) & np.isfinite(pts).all(1) & np.isfinite(nrm).all(1) & np.isfinite(eye).all(1)
    valid[valid] &= (mats.weight[rows[valid]] > 0) | (mats.metallic[rows[valid]] > 0)
    sel = np.flatnonzero(valid)
    step = max(1, CHUNK // max(samples, 1))
    for start in range(0, sel.size, step):
        idx = sel[start:start + step]
        p, n, v, r = pts[idx], nrm[idx], eye[idx], rows[idx]
        n32, v32 = n.astype(_F32), v.astype(_F32)
        p32 = tuple(np.ascontiguousarray(p[:, k], _F32) for k in range(3))
        ncols = tuple(np.ascontiguousarray(n[:, k], _F32) for k in range(3))
        acc = np.zeros((idx.size, 3))
        for light in active:
            drawn = _lamp_samples(light, p, rng, samples)
            if drawn is None:
                continue
            dirs, weight, targets = drawn
            d32 = dirs.astype(_F32)
            common, remap, schlick, k = _lobe_terms(mats, r, n32, v32, d32[..., 0], d32[..., 1], d32[..., 2])
            c = common * weight.astype(_F32)
            if tracer is not None:
                ri, si = np.nonzero(c > 0)
                if ri.size:
                    if targets is not None:
                        t = targets[ri, si].astype(_F32)
                        vis = _shadow_to_targets(tracer, p32, ncols, ri, t[:, 0], t[:, 1], t[:, 2], epsilon)
                    else:
                        origins = (p[ri] + n[ri] * epsilon).astype(_F32)
                        vis = ~np.asarray(tracer.occluded(origins, d32[ri, si], np.inf, trusted=True), bool)
                    c[ri[~vis], si[~vis]] = 0.0
            # Per channel: sum_s c (A + B remap + C + D schlick), without an (m, s, 3) array.
            s0, s1, s2 = c.sum(axis=1), (c * remap).sum(axis=1), (c * schlick).sum(axis=1)
            acc += ((k[:, 0] + k[:, 2]) * s0[:, None] + k[:, 1] * s1[:, None] + k[:, 3] * s2[:, None]) * light.color
        out[idx] = acc
    return out


def cache_reflection(cache, points, normals, to_eye, rough):
    """((n, 3), (n, 3)) float32 the cache's incident radiance reflected by a lobe of roughness
    `rough` (n,) about the normals: from the sky and emitters (part of Cycles' Glossy Direct) and
    from other surfaces (its Glossy Indirect), each before its Glossy Color.

    points, normals, to_eye : (n, 3) float32 receivers, unit normals facing the eye and unit
    directions to the eye (the lobe's direction is not used yet: see the module docstring)."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    nrm = np.asarray(normals, np.float32).reshape(-1, 3)
    if pts.shape[0] == 0:
        return np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)
    flats, w = corner_weights(cache, pts, nrm, visibility=True)
    out = []
    for band in (cache.sh_direct, cache.sh_indirect):
        coeffs = np.einsum("nc,nckl->nkl", w, band[flats])
        out.append((np.maximum(shmod.irradiance(coeffs, nrm), 0.0) / np.pi).astype(np.float32))
    return out[0], out[1]
