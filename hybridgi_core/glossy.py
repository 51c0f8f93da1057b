"""Glossy Direct: the lamps reflected by the materials' glossy lobes at image pixels.

Cycles' Glossy Direct is the lamp light its glossy closures reflect towards the camera, divided by
Glossy Color (their albedo at the view angle, `specular.glossy_color`). The lobes are Cycles'
(`specular.GlossyLobe`): a Principled BSDF's dielectric specular layer (Fresnel of the adjusted
IOR remapped to F0..1, weight (1 - metallic)(1 - transmission)) and metallic lobe (F82 tint), a
Glossy BSDF's (no Fresnel, its colour), a Metallic BSDF's (F82 tint or a conductor's Fresnel), a
Glass BSDF's reflection (its real Fresnel), each under the weights and view factors of the mixes
above it: GGX or Beckmann with height-correlated Smith masking and, for Multiscatter GGX, the
multiple-scattering factor 1 + Fms (1 - E) / E of `microfacet_ggx_preserve_energy`.

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

from dataclasses import dataclass, replace

import numpy as np

from . import sh as shmod
from . import sheen as sheen_mod
from . import specular as sp
from .environment import LUMA
from .evaluate import corner_weights
from .lights import (
    _area_points,
    _area_shape,
    _onb,
    _sample_spherical_rectangle,
    _shadow_to_targets,
    concentric_disk,
    shadow_query,
    spot_attenuation,
    spread_attenuation,
    stopped_by_glass,
    stratified_uv,
    uniform_cone,
)
from .rows import finite_rows
from .snapshot import Light

_F32 = np.float32
#: Receivers x samples per block (bounds the temporaries; 128k, not 32k: fewer GIL hand-overs,
#: `reflection.CHUNK_RAYS`).
CHUNK = 1 << 17
#: Rec. 709 luminance weights (the `variance` output's luminance).
_LUMA = LUMA.astype(_F32)
#: Below this roughness a lobe is too sharp to meet a sampled lamp point (Cycles evaluates none).
MIN_ROUGHNESS = 0.02


#: View cosines at which `GlossyMaterials.reflects` looks for a Glossy Color above 0.
_REFLECT_COSINES = np.array([0.1, 0.5, 1.0])


#: Metallic values of the variants of a material with a Metallic texture (`Material.metallic_map`):
#: the G-buffer writes each pixel's texel value into the material target's fraction
#: (`raster/gbuffer`), `glossy_image.material_rows` picks the nearest variant's row.
METALLIC_STEPS = 5

#: Roughness values of the variants of a material with a Roughness texture (`Material.roughness_map`):
#: evenly spread over the texture's range (`roughness_range`); the G-buffer writes each pixel's
#: variant (metallic step x roughness step) into the material target's fraction.
ROUGHNESS_STEPS = 6


def roughness_range(material) -> tuple[float, float] | None:
    """(lo, hi) the 2nd and 98th percentiles of a material's roughness texture, over which its
    `ROUGHNESS_STEPS` variants spread; None without variants (no texture, not a lone Principled
    BSDF's layer, or a spread under 0.02: its mean roughness serves)."""
    texels = getattr(material, "roughness_map", None)
    if texels is None or not isinstance(getattr(material, "specular", None), sp.SpecularLayer):
        return None
    stride = max(1, int(np.sqrt(texels.size / 65536)))
    lo, hi = np.percentile(texels[::stride, ::stride], [2.0, 98.0])
    return (float(lo), float(hi)) if hi - lo > 0.02 else None


def is_textured_metal(material) -> bool:
    """Whether a material's metallic lobe may follow a colour texture (`metal_tint_basis`)."""
    return _metal_texels(material) is not None


def _metal_texels(material) -> np.ndarray | None:
    """(h, w, 3) the texture a material's metallic lobe takes its colour from: the colour texture
    of a lone Principled BSDF with a metallic lobe, under a Metallic texture its
    `Material.metal_texture` (the colour texture is then the diffuse base); else None."""
    layer = getattr(material, "specular", None)
    if not isinstance(layer, sp.SpecularLayer) or layer.metallic <= 0.0:
        return None
    if getattr(material, "metallic_map", None) is not None:
        return getattr(material, "metal_texture", None)
    return getattr(material, "texture", None)


def metal_tint_basis(material) -> np.ndarray | None:
    """(3, 3) float32 rows: a textured metal's mean colour texel and its texture's two main axes
    of colour variation (unit; principal components of the texels), or None where its metallic
    lobe takes one colour: no colour texture, or no metallic lobe of a lone Principled BSDF (under
    a Metallic texture the colour is its `Material.metal_texture`). The G-buffer writes each
    pixel's texel coordinates along the axes into the albedo and emission targets' alphas (spare
    there); `metal_tint` rebuilds the texel from them and the metallic lobe's colour (its F0: the
    mean texel) follows it per pixel. Two axes hold a texture's colour variation (brightness, and
    a hue between two colours) nearly whole."""
    source = _metal_texels(material)
    if source is None:
        return None
    texels = source.reshape(-1, 3).astype(np.float64)
    texels = texels[:: max(1, texels.shape[0] // 65536)]
    mean = texels.mean(axis=0)
    if float(mean @ LUMA) <= 1e-4:
        return None
    _, vectors = np.linalg.eigh(np.cov((texels - mean).T) + np.eye(3) * 1e-12)
    return np.stack([mean, vectors[:, 2], vectors[:, 1]]).astype(np.float32)


#: Grey metal colours (F0) at which `metal_albedo_curve` tabulates a metallic lobe's Glossy Color.
METAL_CURVE_SIZE = 17


#: View cosines at which `metal_albedo_curve` tabulates it.
METAL_CURVE_COSINES = np.linspace(0.1, 1.0, 10)


def metal_albedo_curve(layer) -> np.ndarray:
    """(METAL_CURVE_SIZE, len(METAL_CURVE_COSINES)) the Glossy Color of a `SpecularLayer`'s
    metallic lobe alone (its dielectric share off) for a grey metal colour F0 = 0, 1/16, ..., 1
    at view cosines METAL_CURVE_COSINES. Why: a rough metal's albedo is not linear in F0
    (multiple scattering gives back more of a bright metal's light: roughness 0.9 at normal
    incidence, F0 0.34 -> 0.188, F0 0.9 -> 0.810, 4.3 x for 2.65 x the F0; 3.7 x at cosine 0.5),
    so a textured metal's texel is weighed by this curve (`metal_tint_scale`), not by its ratio
    to the mean colour."""
    f0s = np.linspace(0.0, 1.0, METAL_CURVE_SIZE)
    metal = replace(layer, weight=0.0, transmission=0.0)
    return np.stack([np.asarray(sp.glossy_color(replace(metal, metal_color=np.full(3, f, np.float32)),
                                                METAL_CURVE_COSINES)).reshape(-1, 3)[:, 0] for f in f0s])


def metal_tint_scale(mats, rows: np.ndarray, ratio: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(k, 3) float32 the factor on the metallic lobe's light of k receivers of glossy `rows`
    seen at cosines mu (k,) whose texel is `ratio` (k, 3) times their lobe's colour
    (`metal_tint`): its albedo at the texel's F0 over its albedo at the lobe's
    (`metal_albedo_curve`, bilinear); the ratio itself where that albedo is 0."""
    f0 = mats.metal_f0[rows]
    curve = mats.metal_curve[rows]  # (k, F, C)
    texel = np.clip(f0 * ratio, 0.0, 1.0)
    cosines = METAL_CURVE_COSINES
    x = np.clip((np.asarray(mu, np.float64) - cosines[0]) / (cosines[-1] - cosines[0]), 0.0, 1.0) * (cosines.size - 1)
    j0 = np.minimum(np.floor(x).astype(np.int64), cosines.size - 2)
    wj = (x - j0)[:, None]
    k = np.arange(rows.shape[0])[:, None]
    at_view = curve[k, :, j0[:, None]][:, 0] * (1.0 - wj) + curve[k, :, j0[:, None] + 1][:, 0] * wj  # (k, F)

    def along(f):
        y = f * (METAL_CURVE_SIZE - 1)
        i0 = np.clip(np.floor(y).astype(np.int64), 0, METAL_CURVE_SIZE - 2)
        w = y - i0
        lo = np.take_along_axis(at_view, i0, axis=1)
        hi = np.take_along_axis(at_view, i0 + 1, axis=1)
        return lo + w * (hi - lo)

    base = along(f0)
    scale = np.divide(along(texel), base, out=np.asarray(ratio, np.float64).copy(), where=base > 1e-6)
    return scale.astype(np.float32)


def metal_tint(basis: np.ndarray, s: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(n, 3) the texel over the mean colour, per channel, from coordinates s, t (n,) along the
    axes of `metal_tint_basis` (clipped to 0..8; 1 where the mean's channel is 0)."""
    mean = basis[0].astype(np.float64)
    texel = mean[None, :] + s[:, None] * basis[1][None, :] + t[:, None] * basis[2][None, :]
    ratio = np.divide(texel, mean[None, :], out=np.ones_like(texel), where=mean[None, :] > 1e-6)
    return np.clip(ratio, 0.0, 8.0).astype(np.float32)


#: View cosines of each material's tabulated Glossy Color (`GlossyMaterials.color_table`).
COLOR_TABLE_SIZE = 1025


@dataclass
class GlossyMaterials:
    """Per-material constants of the glossy lobes (`specular.GlossyLobe`), indexed by material
    and by lobe slot: arrays (L, m, ...) for the scene's most lobes per material L (unused slots
    weigh 0).

    rough : (m,) the material's smoothest lobe's roughness, mirror-like ones included (what the
    reflection rays trace: `reflection.py`; 1 without lobes); alpha2, e_avg : (L, m);
    beckmann, ms : (L, m) the Beckmann distribution, Multiscatter GGX; eta, f0_real : (L, m) the
    dielectric Fresnel's IOR (above 1) and its F0; k : (L, m, 4, 3) the weight times the
    Fresnel's coefficients (`GlossyLobe.coefficients`); fss : (L, m, 3); view : (L, m, V) the
    view factor over `specular.view_grid` (ones without one); layers : each material's `specular`;
    reflects : (m,) whether a material's glossy lobes reflect anything at all (a Glossy Color
    above 0 at some view angle, mirror-like lobes included): a scene without is skipped whole.
    Rows past the materials' are the variants of each material with a Metallic texture (its
    layer at metallic 0, 0.25, ... 1: `METALLIC_STEPS`) and / or a Roughness texture
    (`ROUGHNESS_STEPS` roughness values over `roughness_range`), metallic-major; variants :
    (materials,) int64 the first variant row of each material, -1 for the rest; variant_steps :
    (materials, 2) int64 its metallic and roughness step counts (1 for the one it lacks).
    """

    rough: np.ndarray
    lobe_rough: np.ndarray
    alpha2: np.ndarray
    beckmann: np.ndarray
    ms: np.ndarray
    eta: np.ndarray
    f0_real: np.ndarray
    k: np.ndarray
    fss: np.ndarray
    e_avg: np.ndarray
    view: np.ndarray
    layers: list
    reflects: np.ndarray | None = None
    #: (m, COLOR_TABLE_SIZE, 3) float32 each material's Glossy Color over the view cosine on a
    #: uniform grid of [0, 1] (`glossy_color` interpolates it); `from_materials` fills it.
    color_table: np.ndarray | None = None
    variants: np.ndarray | None = None
    variant_steps: np.ndarray | None = None
    #: (m,) the metallic lobe's share of each row's Glossy Color at normal incidence (a lone
    #: Principled BSDF's; 0 for the rest): what a pixel's metal tint scales (`metal_tint_basis`)
    metal_share: np.ndarray | None = None
    #: (n, 3) the metallic lobe's colour (F0) of the rows of materials with a tint basis, and
    #: (n, METAL_CURVE_SIZE, cosines) its albedo against a grey F0 and the view cosine
    #: (`metal_albedo_curve`); zeros elsewhere.
    metal_f0: np.ndarray | None = None
    metal_curve: np.ndarray | None = None
    #: material index -> `metal_tint_basis` of the textured metals
    tint_bases: dict | None = None

    @classmethod
    def from_materials(cls, materials) -> GlossyMaterials:
        layers = [getattr(m, "specular", None) for m in materials]
        owner = list(range(len(layers)))  # the material of each row (variants: their material's)
        variants = np.full(len(layers), -1, np.int64)
        variant_steps = np.ones((len(layers), 2), np.int64)
        for i, material in enumerate(materials):
            layer = layers[i]
            if not isinstance(layer, sp.SpecularLayer):
                continue
            metals = np.linspace(0.0, 1.0, METALLIC_STEPS) if getattr(material, "metallic_map", None) is not None \
                else None
            span = roughness_range(material)
            roughs = np.linspace(span[0], span[1], ROUGHNESS_STEPS) if span is not None else None
            if metals is None and roughs is None:
                continue
            variants[i] = len(layers)
            variant_steps[i] = (1 if metals is None else metals.size, 1 if roughs is None else roughs.size)
            for q in (None,) if metals is None else metals:
                metal = layer if q is None else replace(layer, metallic=float(q),
                                                        weight=(1.0 - q) * (1.0 - layer.transmission))
                added = [metal if r is None else replace(metal, roughness=float(r))
                         for r in ((None,) if roughs is None else roughs)]
                layers = layers + added
                owner += [i] * len(added)
        every = [under_sheen(materials[m], layer) for m, layer in zip(owner, layers, strict=True)]
        per = [[lobe for lobe in lobes if lobe.roughness >= MIN_ROUGHNESS] for lobes in every]
        n, slots = len(layers), max((len(p) for p in per), default=0)
        out = cls(np.ones(n), np.zeros((slots, n)), np.zeros((slots, n)), np.zeros((slots, n), bool),
                  np.zeros((slots, n), bool), np.full((slots, n), 1.5), np.zeros((slots, n)), np.zeros((slots, n, 4, 3)),
                  np.ones((slots, n, 3)), np.ones((slots, n)), np.ones((slots, n, sp.VIEW_SAMPLES)), layers)
        _, e_avg_table, _ = sp.tables()
        for i, lobes in enumerate(per):
            if every[i]:
                out.rough[i] = min(lobe.roughness for lobe in every[i])
            for j, lobe in enumerate(lobes):
                out.lobe_rough[j, i] = lobe.roughness
                out.alpha2[j, i] = lobe.roughness**4
                out.beckmann[j, i] = lobe.distribution == "BECKMANN"
                out.ms[j, i] = lobe.distribution == "MULTI_GGX"
                out.eta[j, i] = lobe.eta
                out.f0_real[j, i] = float(sp.f0_from_ior(lobe.eta))
                out.k[j, i] = lobe.weight[None, :] * lobe.coefficients()
                out.fss[j, i] = lobe.average_fresnel()
                out.e_avg[j, i] = float(sp._lerp_table(e_avg_table, [lobe.roughness]))
                if lobe.view is not None:
                    out.view[j, i] = sp.sample_view(lobe.view, sp.view_grid())
        out.reflects = np.array([layer is not None and float(np.max(sp.lobes_color(lobes, _REFLECT_COSINES))) > 0
                                 for layer, lobes in zip(layers, every, strict=True)], bool)
        grid = np.linspace(0.0, 1.0, COLOR_TABLE_SIZE)
        out.color_table = np.zeros((n, COLOR_TABLE_SIZE, 3), _F32)
        for i, layer in enumerate(layers):
            if layer is not None:
                out.color_table[i] = sp.lobes_color(every[i], grid)
        out.variants = variants
        out.variant_steps = variant_steps
        out.tint_bases = {i: b for i, b in enumerate(metal_tint_basis(m) for m in materials) if b is not None}
        out.metal_share = np.zeros(n)
        out.metal_f0 = np.zeros((n, 3))
        out.metal_curve = np.zeros((n, METAL_CURVE_SIZE, METAL_CURVE_COSINES.size))
        for i, layer in enumerate(layers):
            if isinstance(layer, sp.SpecularLayer) and layer.metallic > 0.0:
                total = float(np.asarray(sp.glossy_color(layer, 1.0)).reshape(-1, 3)[0] @ LUMA)
                metal = float(np.asarray(sp.glossy_color(replace(layer, weight=0.0), 1.0)).reshape(-1, 3)[0] @ LUMA)
                out.metal_share[i] = float(np.clip(metal / total, 0.0, 1.0)) if total > 0 else 0.0
                if owner[i] in out.tint_bases:  # (its values are never None)
                    out.metal_f0[i] = np.asarray(layer.metal_color, np.float64).reshape(3)
                    out.metal_curve[i] = metal_albedo_curve(layer)
        return out

    @property
    def live(self) -> np.ndarray:
        """(m,) whether a material has a lobe to evaluate."""
        return np.abs(self.k).sum(axis=(0, 2, 3)) > 0

    @property
    def any(self) -> bool:
        return bool(self.live.any())


def _lobe_terms(mats: GlossyMaterials, rows, n, v, lx, ly, lz, widen=None):
    """The glossy lobes at m receivers towards s unit directions each, factored so that no
    (m, s, 3) array is needed: BRDF x cos = sum over slots of common (k0 + k1 remap + k2 s5 +
    k3 c s6) per channel.

    Returns a list over the lobe slots in use of (common (m, s): D G2 / (4 cos_i), 0 below
    either horizon; terms, 3 x (m, s) or None where the slot's coefficient of it is 0: remap (the
    dielectric Fresnel mapped to 0..1), (1 - c)^5 and c (1 - c)^6 of c = cos(h, i); k (m, 4, 3):
    the slot's coefficients times its multiscatter factor and view factor at the receiver's view
    angle). widen : (m,) alpha^2 each receiver's lobes gain (`specular_aa.footprint_alpha2`) or None."""
    mu_i = np.einsum("ij,ij->i", n, v)[:, None]
    nx, ny, nz = n[:, 0:1], n[:, 1:2], n[:, 2:3]
    mu_o = lx * nx + ly * ny + lz * nz
    hx, hy, hz = lx + v[:, 0:1], ly + v[:, 1:2], lz + v[:, 2:3]
    inv = _F32(1.0) / np.maximum(np.sqrt(hx * hx + hy * hy + hz * hz), _F32(1e-12))
    cos_nh = (hx * nx + hy * ny + hz * nz) * inv
    cos_hi = np.clip((hx * v[:, 0:1] + hy * v[:, 1:2] + hz * v[:, 2:3]) * inv, 0.0, 1.0)
    facing = (mu_i > 1e-4) & (mu_o > 0)
    mu_i = np.maximum(mu_i, _F32(1e-4))
    one_minus = _F32(1.0) - cos_hi
    s5 = (one_minus * one_minus) ** 2 * one_minus
    s6c = s5 * one_minus * cos_hi
    mu_view = np.clip(mu_i[:, 0], 0.0, 1.0)
    out = []
    for slot in range(mats.alpha2.shape[0]):
        k = mats.k[slot, rows]
        if not np.any(k):
            continue
        a2 = mats.alpha2[slot, rows][:, None].astype(_F32)
        ok = facing & (a2 > 0)
        if widen is not None:
            a2 = np.where(a2 > 0, np.minimum(a2 + widen[:, None], _F32(1.0)), a2).astype(_F32)
        mu_o_ok = np.where(ok, mu_o, _F32(1.0))
        x = cos_nh * cos_nh * (a2 - _F32(1.0)) + _F32(1.0)
        d = a2 / (_F32(np.pi) * x * x)
        g2 = _F32(1.0) / (_F32(1.0) + sp._lambda(a2, mu_i) + sp._lambda(a2, mu_o_ok))
        beck = mats.beckmann[slot, rows]
        if beck.any():
            d = np.where(beck[:, None], _beckmann_d(a2, cos_nh), d)
            g2 = np.where(beck[:, None], _F32(1.0) / (_F32(1.0) + _beckmann_lambda(a2, mu_i)
                                                      + _beckmann_lambda(a2, mu_o_ok)), g2)
        common = np.where(ok, d * g2 / (_F32(4.0) * mu_i), _F32(0.0)).astype(_F32)
        terms = [None, s5 if np.any(k[:, 2]) else None, s6c if np.any(k[:, 3]) else None]
        if np.any(k[:, 1]):
            f0_real = mats.f0_real[slot, rows][:, None].astype(_F32)
            terms[0] = _remapped_dielectric(cos_hi, mats.eta[slot, rows], f0_real[:, 0])
        out.append((common, terms, slot_coefficients(mats, slot, rows, mu_i[:, 0], mu_view)[0]))
    return out


def slot_coefficients(mats: GlossyMaterials, slot: int, rows, mu, mu_view=None) -> tuple[np.ndarray, np.ndarray]:
    """(k (m, 4, 3) float32, e (m,)) of lobe `slot` at m receivers of materials `rows` seen at
    cosines mu (> 0): the Fresnel terms' coefficients (`GlossyMaterials.k`) times the lobe's
    multiple-scattering and view factors, and its single-scattering albedo E (F = 1). The lobe's
    BRDF x cos is D G2 / (4 cos_i) x sum_j k_j term_j (`_lobe_terms`), which integrates to E."""
    mu_view = np.clip(mu, 0.0, 1.0) if mu_view is None else mu_view
    k = mats.k[slot, rows]
    rough = mats.lobe_rough[slot, rows]
    e = sp._lerp_table(sp.tables()[0], [rough, mu])
    e_avg = mats.e_avg[slot, rows][:, None]
    scale = np.where(mats.ms[slot, rows][:, None], sp.multiscatter_factor(mats.fss[slot, rows], e[:, None], e_avg),
                     1.0)
    view = _view_factor(mats.view[slot, rows], mu_view)
    return (k * (scale * view[:, None])[:, None, :]).astype(_F32), e


def traced_fresnel(mats: GlossyMaterials, rows, mu, cos_hi) -> np.ndarray:
    """(m, s) float32 the Fresnel (luminance, with each lobe's multiple-scattering and view factors)
    of the lobes as rough as each receiver's traced one (`GlossyMaterials.rough`: a Principled
    BSDF's specular and metallic lobes) at the half-vector cosines cos_hi (m, s) of its reflection
    samples; rows (m,) material rows, mu (m,) view cosines. 1 where no lobe matches.

    Why: Cycles' Glossy Direct and Indirect are the lobes' light over their albedo, Fresnel
    included in both; at grazing views a dielectric's Fresnel rises steeply towards the mirror
    direction, and a sample weight without it (G2 / G1) leans the mean towards the lobe's tail.
    A floor reflecting a map bright on one side only, seen at 20 degrees: Glossy Direct +45%."""
    rows = np.asarray(rows)
    c = np.clip(np.asarray(cos_hi, _F32), 0.0, 1.0)
    out = np.zeros(c.shape, _F32)
    if rows.size == 0:
        return out
    unique, inverse = np.unique(rows, return_inverse=True)
    step = np.rint(np.clip(np.asarray(mu, np.float64), 0.0, 1.0) * (FRESNEL_MU_STEPS - 1)).astype(np.int64)
    traced = mats.rough[unique]
    for slot in range(mats.alpha2.shape[0]):
        mine_u = (np.abs(mats.lobe_rough[slot, unique] - traced) < 1e-6) & mats.k[slot, unique].any(axis=(1, 2))
        if not mine_u.any():
            continue
        table = _coefficient_table(mats, slot, unique)
        at = np.flatnonzero(mine_u[inverse])
        k = table[inverse[at], step[at]]
        cc = c[at]
        f = k[:, 0:1] + np.zeros_like(cc)
        if np.any(k[:, 2:4]):
            one_minus = _F32(1.0) - cc
            s5 = (one_minus * one_minus) ** 2 * one_minus
            f += k[:, 2:3] * s5 + k[:, 3:4] * s5 * one_minus * cc
        if np.any(k[:, 1]):
            f += k[:, 1:2] * _remapped_dielectric(cc, mats.eta[slot, rows[at]], mats.f0_real[slot, rows[at]])
        out[at] += f
    out[~np.any(out > 0, axis=1)] = 1.0
    return out


#: View cosines at which `traced_fresnel` tabulates each material's lobe coefficients (their
#: multiple-scattering and view factors vary slowly with it; per receiver they cost 0.2 s of
#: 1.6 M reflection samples' 0.25 s).
FRESNEL_MU_STEPS = 33


def _coefficient_table(mats: GlossyMaterials, slot: int, rows: np.ndarray) -> np.ndarray:
    """(len(rows), FRESNEL_MU_STEPS, 4) float32 the luminance of `slot_coefficients` of lobe
    `slot` for material rows `rows` at FRESNEL_MU_STEPS view cosines over (0, 1]."""
    grid = np.linspace(1e-4, 1.0, FRESNEL_MU_STEPS)
    k = slot_coefficients(mats, slot, np.repeat(rows, FRESNEL_MU_STEPS), np.tile(grid, rows.size))[0]
    return (k @ np.asarray(LUMA, _F32)).astype(_F32).reshape(rows.size, FRESNEL_MU_STEPS, 4)


def _remapped_dielectric(c: np.ndarray, eta: np.ndarray, f0: np.ndarray) -> np.ndarray:
    """(m, s) float32 Cycles' fresnel_dielectric_cos at cosines c (m, s) in [0, 1] for IORs eta
    (m,), mapped from [f0, 1] to [0, 1]: `_fresnel_remap` in float32 and without its NaN guards
    (both denominators are kept from 0; a cosine of 0 is taken as 1e-6, where total internal
    reflection and the grazing limit both give 1). Six times faster than the float64 form on the
    lobes' (m, s) samples (`_lobe_terms`: 0.1 s of bunny_npm's frame)."""
    eta = np.asarray(eta, _F32)[:, None]
    f0 = np.asarray(f0, _F32)[:, None]
    c = np.maximum(c, _F32(1e-6))
    g = np.sqrt(np.maximum(eta * eta - _F32(1.0) + c * c, _F32(0.0)))
    a = (g - c) / np.maximum(g + c, _F32(1e-12))
    b = (c * (g + c) - _F32(1.0)) / np.maximum(c * (g - c) + _F32(1.0), _F32(1e-12))
    fresnel = _F32(0.5) * a * a * (_F32(1.0) + b * b)
    return np.clip((fresnel - f0) / np.maximum(_F32(1.0) - f0, _F32(1e-12)), 0.0, 1.0)


def fresnel_terms(mats: GlossyMaterials, slot: int, rows, cos_hi) -> np.ndarray:
    """(m, 4) the terms the coefficients of `slot_coefficients` weigh at cos(h, i) = cos_hi (m,):
    1, the dielectric Fresnel remapped to 0..1, (1 - c)^5 and c (1 - c)^6 (`_lobe_terms`)."""
    c = np.clip(np.asarray(cos_hi, np.float64), 0.0, 1.0)
    remap = _fresnel_remap(c, mats.eta[slot, rows], mats.f0_real[slot, rows])
    s5 = (1.0 - c) ** 5
    return np.stack([np.ones_like(c), remap, s5, s5 * (1.0 - c) * c], axis=1)


def _fresnel_remap(cos_hi, eta, f0):
    """The dielectric Fresnel at cos(h, i) = cos_hi for IOR eta, mapped from [f0, 1] to [0, 1]
    (`GlossyLobe.coefficients`' remap term), in cos_hi's precision."""
    fresnel = sp.fresnel_dielectric(cos_hi, eta).astype(cos_hi.dtype)
    return np.clip((fresnel - f0) / np.maximum(cos_hi.dtype.type(1.0) - f0, cos_hi.dtype.type(1e-12)), 0.0, 1.0)


def glows(light) -> bool:
    """Whether the glossy lobes see `light` (its `for_glossy` view) at all: a power and colour above 0."""
    return float(light.power) != 0.0 and bool(np.any(light.color != 0))


def under_sheen(material, layer) -> list:
    """The glossy lobes of `layer` (`specular.surface_lobes`), those under a Principled BSDF's
    sheen weighted by 1 - max(sheen colour) x the sheen's albedo at the view angle
    (`sheen.layer_factor`), as Cycles layers its sheen over the specular and metallic lobes (the
    coat lies above the sheen and keeps its weight). Why: a velvet's highlight at grazing views
    was as bright as without its sheen."""
    lobes = sp.surface_lobes(layer)
    factor = sheen_mod.layer_factor(material, sp.view_grid()) if isinstance(layer, sp.SpecularLayer) else None
    if factor is None or not lobes:
        return lobes
    coat = lobes[-1] if layer.coated else None
    return [lobe if lobe is coat else
            replace(lobe, view=factor if lobe.view is None else sp.sample_view(lobe.view, sp.view_grid()) * factor)
            for lobe in lobes]


def _view_factor(tables, mu) -> np.ndarray:
    """(m,) each receiver's view factor: its row of (m, V) tables over `specular.view_grid`
    linearly interpolated at its view cosine."""
    if np.all(tables == 1.0):
        return np.ones(tables.shape[0])
    x = np.clip(mu, 0.0, 1.0) * (tables.shape[1] - 1)
    i0 = np.minimum(np.floor(x).astype(np.int64), tables.shape[1] - 2)
    frac = x - i0
    at = np.arange(tables.shape[0])
    return tables[at, i0] * (1.0 - frac) + tables[at, i0 + 1] * frac


def _beckmann_d(a2, cos_nh):
    """Beckmann's normal distribution (Cycles' bsdf_D<BECKMANN>)."""
    c2 = np.clip(cos_nh * cos_nh, 1e-12, 1.0)
    with np.errstate(over="ignore"):
        return _F32(1.0) / (np.exp((_F32(1.0) - c2) / (c2 * a2)) * _F32(np.pi) * a2 * c2 * c2)


def _beckmann_lambda(a2, cos_n):
    """Smith Lambda of Beckmann, the rational approximation Cycles uses."""
    cos2 = np.maximum(cos_n * cos_n, 1e-30)
    t = a2 * np.maximum(1.0 / cos2 - 1.0, 0.0)
    a = 1.0 / np.sqrt(np.maximum(t, 1e-30))
    lam = ((0.396 * a - 1.259) * a + 1.0) / ((2.181 * a + 3.535) * a)
    return np.where(t < 0.39, 0.0, lam).astype(_F32)


def lobes(mats: GlossyMaterials, rows, n, v, lx, ly, lz) -> np.ndarray:
    """(m, s, 3) BRDF x cos(n, l) of the glossy lobes at m receivers towards s unit directions each.

    rows : (m,) material index; n, v : (m, 3) unit normal and direction to the eye; lx, ly, lz :
    (m, s) unit directions to the light. 0 where either direction is below the surface."""
    rows = np.asarray(rows)
    out = np.zeros((*np.shape(lx), 3), _F32)
    for common, terms, k in _lobe_terms(mats, rows, *(np.asarray(a, _F32) for a in (n, v, lx, ly, lz))):
        k = k[:, None]
        f = np.broadcast_to(k[..., 0, :], out.shape).copy()
        for j, term in enumerate(terms):
            if term is not None:
                f += k[..., j + 1, :] * term[..., None]
        out += common[..., None] * f
    return out


def glossy_color(mats: GlossyMaterials, rows, mu) -> np.ndarray:
    """(n, 3) float32 Glossy Color at receivers of materials `rows` (-1: none) seen at cosines
    `mu`, interpolated in the materials' `color_table`: within 4e-4 of `specular.glossy_color`
    (itself linear in its albedo tables' coarser grid), whose float64 table look-ups per pixel
    cost bunny_npm's 640x360 frame 124 ms."""
    rows = np.asarray(rows)
    x = np.clip(np.asarray(mu, _F32), 0.0, 1.0) * _F32(COLOR_TABLE_SIZE - 1)
    i0 = np.minimum(x.astype(np.intp), COLOR_TABLE_SIZE - 2)
    frac = (x - i0)[:, None]
    live = np.flatnonzero(rows >= 0)
    out = np.zeros((rows.shape[0], 3), _F32)
    if live.size:
        flat = np.take(rows, live) * COLOR_TABLE_SIZE + np.take(i0, live)
        rows_of = mats.color_table.reshape(-1, 3)
        f = np.take(frac, live, axis=0)
        lo = np.take(rows_of, flat, axis=0)
        hi = np.take(rows_of, flat + 1, axis=0)
        hi -= lo
        hi *= f
        hi += lo
        out[live] = hi
    return out


def _lamp_samples(light: Light, p, rng, samples):
    """(dirs (m, s, 3) unit receiver -> lamp, weight (m, s) radiance-to-radiance factor per sample
    without the BRDF (L x dw / s, lamp colour aside), targets (m, s, 3) or None for a sun)."""
    m = p.shape[0]
    if light.kind == "AREA":
        shape = _area_shape(light)
        if shape.area <= 0:
            return None
        if float(light.spread) <= 0.0:
            # A collimated beam (`lights._beam`): one direction, P / A where the receiver's
            # projection along the normal falls on the lamp.
            ex, ey, ez = shape.frame
            rel = p - shape.centre.astype(np.float64)
            height = rel @ ez
            a, b = (rel @ ex) * (2.0 / shape.len_u), (rel @ ey) * (2.0 / shape.len_v)
            on = (a * a + b * b <= 1.0) if shape.round else ((np.abs(a) <= 1.0) & (np.abs(b) <= 1.0))
            weight = np.where(on & (height > 0), float(light.power) / shape.area, 0.0)[:, None]
            targets = (p - height[:, None] * ez[None, :])[:, None, :]
            return np.broadcast_to(-ez, (m, 1, 3)).copy(), weight, targets
        u, v = stratified_uv(rng, m, samples)
        if shape.rectangular:
            dirs, weight, targets = _rectangle_samples(shape, float(light.power) / (np.pi * shape.area), p, u, v,
                                                       samples)
        else:
            qx, qy, qz = _area_points(shape, u, v)
            w = np.stack([qx - p[:, 0:1], qy - p[:, 1:2], qz - p[:, 2:3]], axis=-1)
            d2 = np.maximum((w * w).sum(-1), 1e-8)
            dirs = w / np.sqrt(d2)[..., None]
            cos_l = -(dirs @ shape.normal.astype(np.float64))
            radiance = float(light.power) / (np.pi * shape.area)
            weight = radiance * np.maximum(cos_l, 0.0) * shape.area / (d2 * samples)
            targets = np.stack([qx, qy, qz], axis=-1)
        if float(light.spread) < np.pi:  # Spread: the radiance towards each sample's direction
            cos_l = -(dirs @ shape.normal.astype(dirs.dtype))
            sin_l = np.sqrt(np.maximum(1.0 - cos_l * cos_l, 0.0))
            weight = weight * spread_attenuation(light, cos_l, sin_l / np.maximum(cos_l, 1e-30))
        return dirs, weight, targets
    if light.kind in ("POINT", "SPOT"):
        return _round_lamp_samples(light, p, rng, samples)
    to_sun = -light.direction.astype(np.float64)
    half = 0.5 * float(light.angle)
    if half <= 0:
        return np.broadcast_to(to_sun, (m, 1, 3)).copy(), np.full((m, 1), float(light.power)), None
    u, v = stratified_uv(rng, m, samples)
    components, one_minus_cos = uniform_cone(to_sun, half, u.astype(np.float64), v.astype(np.float64))
    dirs = np.stack(components, axis=-1)
    weight = np.full((m, samples), float(light.power) / ((1.0 - 0.5 * one_minus_cos) * samples))
    return dirs, weight, None


def _round_lamp_samples(light: Light, p, rng, samples):
    """`_lamp_samples` of a POINT/SPOT: its centre (radius 0), else the emitters of
    `lights._radius_chunk` (L = P / (4 pi^2 r^2) on a disc facing the receiver with Soft Falloff,
    on a sphere without), a SPOT's cone factor taken per sample as Cycles does."""
    m = p.shape[0]
    c = light.position.astype(np.float64)
    to = c[None, :] - p
    dist = np.maximum(np.linalg.norm(to, axis=1), 1e-6)
    radius = float(light.radius)
    power = float(light.power)
    if radius <= 0:
        q = np.broadcast_to(c, (m, 1, 3)).copy()
        w = q - p[:, None, :]
        d2 = np.maximum((w * w).sum(-1), 1e-8)
        dirs = w / np.sqrt((w * w).sum(-1).clip(1e-16))[..., None]
        weight = (power / (4.0 * np.pi)) / d2
        if light.directional:
            weight = weight * spot_attenuation(light, -to.astype(_F32))[:, None]
        return dirs, weight, q
    axis = to / dist[:, None]  # receiver -> lamp
    u, v = stratified_uv(rng, m, samples)
    a, b = concentric_disk(u.astype(np.float64), v.astype(np.float64))
    t1, t2 = _onb(axis[:, 0:1], axis[:, 1:2], axis[:, 2:3])
    r2 = radius * radius
    if light.soft_falloff:
        q = np.stack([c[k] + radius * (a * t1[k] + b * t2[k]) for k in range(3)], axis=-1)
        w = q - p[:, None, :]
        t2s = np.maximum((w * w).sum(-1), 1e-8)
        dirs = w / np.sqrt(t2s)[..., None]
        # L x disc area x cos_l / t^2 / s, cos_l = distance along the disc's axis / t.
        weight = (power / (4.0 * np.pi * samples)) * dist[:, None] / (t2s * np.sqrt(t2s))
    else:
        inside = dist <= radius
        s2 = np.where(inside, 1.0, r2 / np.maximum(dist, radius) ** 2)[:, None]
        # Outside, the cone the sphere subtends; inside, the whole sphere of directions.
        omc = np.where(inside[:, None], 2.0, s2 / (1.0 + np.sqrt(1.0 - s2)))
        q2 = a * a + b * b
        cos_t = 1.0 - q2 * omc
        scale = np.sqrt(np.maximum(omc * (2.0 - q2 * omc), 0.0))
        dirs = np.stack([scale * (a * t1[k] + b * t2[k]) + cos_t * axis[:, k:k + 1] for k in range(3)], axis=-1)
        bc = (dirs * to[:, None, :]).sum(-1)
        root = np.sqrt(np.maximum(r2 - dist[:, None] ** 2 + bc * bc, 0.0))
        t = bc + np.where(inside[:, None], root, -root)
        q = p[:, None, :] + dirs * t[..., None]
        # Uniform in the cone: one weight per receiver, the same for each of its samples.
        weight = np.broadcast_to((power / (2.0 * np.pi * r2 * samples)) * omc, (m, samples)).copy()
    if light.directional:
        cone = spot_attenuation(light, -dirs.reshape(-1, 3).astype(_F32)).reshape(m, samples)
        if not light.soft_falloff:
            cone[dist <= radius] = 1.0
        weight = weight * cone
    return dirs, weight, q


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
                  epsilon: float = 1e-4, variance: np.ndarray | None = None, widen: np.ndarray | None = None
                  ) -> np.ndarray:
    """(n, 3) float32 lamp radiance the glossy lobes reflect towards the eye (Cycles' Glossy Direct
    times Glossy Color), with shadow rays.

    points, normals, to_eye : (n, 3) float32 receivers, unit normals facing the eye and unit
    directions to the eye; rows : (n,) int32 material index (-1: none). variance : optional (n,)
    float32 output, the estimated variance of each receiver's result's luminance (Rec. 709), from
    the spread of its samples' luminances as if they were independent (the stratified samples
    spread less: it errs high), summed over the lamps: where the highlight is noisy (`glossy_noise`).
    widen : optional (n,) alpha^2 the receivers' lobes gain (`specular_aa.footprint_alpha2`)."""
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    nrm = np.asarray(normals, np.float64).reshape(-1, 3)
    eye = np.asarray(to_eye, np.float64).reshape(-1, 3)
    rows = np.asarray(rows, np.int64).reshape(-1)
    out = np.zeros((pts.shape[0], 3), _F32)
    if variance is not None:
        variance[:] = 0.0
    # The lamps as glossy lobes see them (Specular factor, glossy ray visibility).
    active = [g for g in (lt.for_glossy() for lt in lights) if glows(g)]
    if not active or not mats.any or pts.shape[0] == 0:
        return out
    valid = (rows >= 0) & finite_rows(pts) & finite_rows(nrm) & finite_rows(eye)
    valid[valid] &= mats.live[rows[valid]]
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
            slots = _lobe_terms(mats, r, n32, v32, d32[..., 0], d32[..., 1], d32[..., 2],
                                None if widen is None else np.asarray(widen, _F32).reshape(-1)[idx])
            if not slots:
                continue
            w32 = weight.astype(_F32)
            lit = np.zeros(w32.shape, bool)
            for common, _, _ in slots:
                lit |= (common * w32) > 0
            if tracer is not None and light.cast_shadow:
                ri, si = np.nonzero(lit)
                if ri.size:
                    if targets is not None:
                        t = targets[ri, si].astype(_F32)
                        vis = _shadow_to_targets(tracer, p32, ncols, ri, t[:, 0], t[:, 1], t[:, 2], epsilon,
                                                 stopped_by_glass(light))
                    else:
                        origins = (p[ri] + n[ri] * epsilon).astype(_F32)
                        vis = ~np.asarray(shadow_query(tracer, stopped_by_glass(light))(
                            origins, d32[ri, si], np.inf, trusted=True), bool)
                    w32 = w32.copy()
                    w32[ri[~vis], si[~vis]] = 0.0
            lum = np.zeros(w32.shape, _F32) if variance is not None else None
            luma = _LUMA * light.color.astype(_F32)
            for common, terms, k in slots:
                # Per channel: sum_s c (k0 + k1 remap + k2 s5 + k3 c s6), without an (m, s, 3) array.
                c = common * w32
                total = k[:, 0] * c.sum(axis=1)[:, None]
                if lum is not None:
                    lum += c * (k[:, 0] @ luma)[:, None]
                for j, term in enumerate(terms):
                    if term is not None:
                        ct = c * term
                        total += k[:, j + 1] * ct.sum(axis=1)[:, None]
                        if lum is not None:
                            lum += ct * (k[:, j + 1] @ luma)[:, None]
                acc += total * light.color
            if lum is not None and lum.shape[1] > 1:
                # The estimate is the sum of s samples: s x their sample variance.
                s = lum.shape[1]
                var_idx = lum.var(axis=1) * _F32(s * s / (s - 1))
                variance[idx] += var_idx
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
