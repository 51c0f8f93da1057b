"""Metal at a ray's hit: the lamps in its highlight, not spread as diffuse light.

Why: a cache of irradiance cannot hold a lobe's direction, so a hit reflects its glossy lobes'
light as if it were diffuse (`shading.SurfaceTable.set_materials`): right for the light of the
surroundings, which a rough lobe averages anyway, wrong for a lamp, which a lobe shows only in
its highlight. On a dielectric's few percent that matters little; on metal it is all of the hit's
lamp light. Cycles' light sampling at the hit finds the lamp through the lobe towards where the
ray came from; so the hits whose glossy share of the brdf is most of it (metals) take their
lamps' light that way (`highlights`, a few lamp samples with shadow rays), in place of the
glossy share of their lamp irradiance: a reflection ray's hit (`reflection.traced_reflection`)
and a final-gather ray's (`pixel_gather.hit_radiance`). Not a probe ray's: the cache's further
bounces read a shiny hit's light as diffuse light again (a metal floor's highlight on a metal
wall lit the floor's reflection of the wall: Combined 0.068 -> 0.116 with the highlights in the
cache, 0.063 with none of the metal's lamp light; half a floor of metal 0.038 -> 0.038 / 0.059),
and the cache's first batch took 60% longer on those scenes.

Measured (bench/artist_scenes.py, 128x96 against Cycles 1024 spp): a sunlit floor of metal
beside a ball and a cube, Diffuse Indirect bias -27% -> +3% (the floor's highlight lights the
ball from below); half a floor of metal, +27% -> -6% (with each hit's texel's glossy albedo,
`shading._metal_glossy`).

numpy only (no bpy).
"""

from __future__ import annotations

import numpy as np

from .environment import LUMA as ENV_LUMA
from .glossy import glossy_direct
from .lights import GLOSSY_LAMP_BUDGET, _pick_lamps

#: Hits whose brdf's luminance is more than this share glossy are shiny (metals).
SHINY_SHARE = 0.5
#: Lamp samples per shiny hit and lamp.
SHINY_SAMPLES = 2

_LUMA = ENV_LUMA.astype(np.float32)


def shiny_hits(surfaces, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
               brdf: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """(indices, their (k, 3) glossy brdf (`SurfaceTable.glossy_brdf`)) of the shiny hits among
    hits (prim (m,) >= 0 at barycentrics u, v, their brdf (m, 3)), or None where there are none.
    Only materials that can be shiny (`SurfaceTable.may_shine`) are looked at per hit: a scene
    without metals pays one check."""
    maybe = surfaces.may_shine
    if not maybe.any() or prim.size == 0:
        return None
    cand = np.flatnonzero(np.take(maybe, np.take(surfaces.material_index, prim)))
    if cand.size == 0:
        return None
    glossy_part = surfaces.glossy_brdf(np.take(prim, cand), np.take(u, cand), np.take(v, cand))
    keep = shiny_share(glossy_part, np.take(brdf, cand, axis=0))
    return (cand[keep], glossy_part[keep]) if keep.any() else None


def may_shine(glossy: np.ndarray, albedo: np.ndarray, textured: list[int], metal_glossy: dict) -> np.ndarray:
    """(M,) bool the materials (hit glossy albedo (M, 3), diffuse albedo (M, 3), the textured ones'
    indices, `shading._metal_glossy`'s ends by index) some of whose hits may be shiny: a
    texture's darkest diffuse counted as none, a Metallic texture's metal texel as its glossy."""
    glossy_lum = glossy @ _LUMA
    diffuse_lum = albedo @ _LUMA
    if textured:
        diffuse_lum[textured] = 0.0
    for m, (_lo, hi) in metal_glossy.items():
        glossy_lum[m] = max(float(glossy_lum[m]), float(hi @ _LUMA))
    return glossy_lum > np.float32(SHINY_SHARE) * (glossy_lum + diffuse_lum)


def shiny_share(glossy_part: np.ndarray, brdf: np.ndarray) -> np.ndarray:
    """(m,) bool: hits whose glossy brdf (m, 3) is more than SHINY_SHARE of their brdf's luminance."""
    return glossy_part @ _LUMA > np.float32(SHINY_SHARE) * (brdf @ _LUMA)


def highlights(lights, glossy_materials, tracer, material_index: np.ndarray, prim: np.ndarray,
               position: np.ndarray, normal: np.ndarray, dirs: np.ndarray, rng) -> np.ndarray:
    """(m, 3) the lamps' light the glossy lobes of hits (prim, position, normal (m, 3)) reflect
    back along the rays `dirs` (m, 3) that met them: `glossy.glossy_direct` towards the rays'
    origins, SHINY_SAMPLES per lamp, with shadow rays."""
    out = np.zeros((prim.shape[0], 3), np.float32)
    if not lights or prim.size == 0:
        return out
    rows = np.take(material_index, prim).astype(np.int64)
    to_origin = -np.asarray(dirs, np.float32)
    n = np.where((np.einsum("ij,ij->i", normal, to_origin) < 0)[:, None], -normal, normal)  # the ray's side
    eps = float(tracer.epsilon)
    if len(lights) <= GLOSSY_LAMP_BUDGET:
        out[:] = glossy_direct(lights, position, n, to_origin, rows, glossy_materials, tracer, rng, SHINY_SAMPLES, eps)
        return out
    # Many lamps: GLOSSY_LAMP_BUDGET of them per hit, drawn by their rough light and weighed by one
    # over their probability, as the glossy lamp light draws them (`GISystem._glossy_picked`): a
    # metal floor under 50 point lamps took 100 lamp samples per metal hit (320x180: 6 s of CPU).
    weights = _pick_lamps(lights, position, n, GLOSSY_LAMP_BUDGET, rng)
    for j, light in enumerate(lights):
        sel = np.flatnonzero(weights[:, j] > 0)
        if sel.size:
            out[sel] += weights[sel, j, None] * glossy_direct([light], position[sel], n[sel], to_origin[sel], rows[sel],
                                                             glossy_materials, tracer, rng, SHINY_SAMPLES, eps)
    return out
