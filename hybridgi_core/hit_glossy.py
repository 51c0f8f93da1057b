"""The glossy lobes of a pixel ray's hit, seen from the ray: their view angle and the direction
they reflect, read from the cache.

Why: a hit reflects its lobes' share of the cache's light as if it were diffuse (the lobes'
hemispherical albedo x irradiance / pi, `shading.SurfaceTable.set_materials`), the same towards
every ray. A Principled floor seen at a grazing angle from a ball on it reflects several times its
mean (the dielectric's Fresnel), and what it reflects is the bright sky above the horizon in the
mirror direction, not the mean over its hemisphere. A ball and a torus on a roughness-0.6
floor under courtyard.exr had Diffuse Indirect 8% low against Cycles (2% with the floor matte).

The correction scales that diffuse share per hit by (Glossy Color at the ray's view cosine over
its cosine-weighted mean) x (the cache's radiance through a lobe about the lobe's dominant
direction over its irradiance / pi at the normal). Both factors are 1 on average over a uniform
sky, so a hit's glossy energy only moves between view angles and directions. The lobe is Cycles'
after a diffuse bounce: Filter Glossy blurs it to roughness >= 0.64 by default
(`specular.hit_blur_roughness`); its L2 SH band factors are a Phong lobe's of the same width
(Ramamoorthi and Hanrahan 2001: exp(-l^2 / 2s), s = 2 / alpha^2 - 2), its dominant direction
Frostbite's (Lagarde and de Rousiers 2014: the mirror direction pulled towards the normal as
the lobe widens). numpy only.
"""

from __future__ import annotations

import functools

import numpy as np

from .environment import LUMA as ENV_LUMA
from .evaluate import monomials
from .glossy import glossy_color
from .specular import hit_blur_roughness

_F32 = np.float32
LUMA = ENV_LUMA.astype(_F32)
#: Largest factor a hit's glossy share is scaled by (a dark cache cell's irradiance beside a
#: bright direction must not blow it up).
MAX_RATIO = 8.0
#: Irradiance below which a hit's ratio is taken as 1 (nothing to redistribute).
MIN_IRRADIANCE = 1e-6


def color_mean(mats) -> np.ndarray:
    """(m,) float32 each material's Glossy Color luminance averaged over the view, cosine-weighted
    (2 int c(mu) mu dmu over `color_table`'s grid, by the trapezoid rule), cached on mats."""
    mean = getattr(mats, "_color_mean", None)
    if mean is None:
        lum = mats.color_table @ LUMA  # (m, size)
        mu = np.linspace(0.0, 1.0, lum.shape[1], dtype=_F32)
        f = 2.0 * lum * mu[None, :]
        mean = ((f[:, 1:] + f[:, :-1]).sum(axis=1) * (0.5 * float(mu[1] - mu[0]))).astype(_F32)
        mats._color_mean = mean
    return mean


@functools.lru_cache(maxsize=8)
def _blur_roughness(filter_glossy: float) -> float:
    """The mean roughness Filter Glossy blurs a hit's lobes to (`specular.hit_blur_roughness`)."""
    blur, weight = hit_blur_roughness(filter_glossy)
    return float(blur @ weight)


def lobe_factors(mats, filter_glossy: float) -> np.ndarray:
    """(m, 3) float32 per material: the pull of its blurred lobe's dominant direction from the
    normal towards the mirror direction, and its L1 and L2 band factors over the cosine's (see
    the module docstring); cached on mats."""
    cached = getattr(mats, "_lobe_factors", None)
    if cached is not None and cached[0] == filter_glossy:
        return cached[1]
    rough = np.maximum(np.asarray(mats.rough, np.float64), _blur_roughness(filter_glossy))
    alpha = np.clip(rough * rough, 1e-3, 1.0)
    s = np.maximum(2.0 / (alpha * alpha) - 2.0, 1e-3)
    out = np.stack([(1.0 - alpha) * (np.sqrt(1.0 - alpha) + alpha), np.exp(-1.0 / (2.0 * s)) / (2.0 / 3.0),
                    np.exp(-4.0 / (2.0 * s)) / 0.25], axis=1).astype(_F32)
    mats._lobe_factors = (filter_glossy, out)
    return out


def lobe_monomials(normals: np.ndarray, to_eye: np.ndarray, factors: np.ndarray, terms: int) -> np.ndarray:
    """(terms, n) float32 `evaluate.monomials` that turn an irradiance row into pi x the radiance
    through a lobe about its dominant direction (factors (n, 3): `lobe_factors`' rows): the bands
    of the dominant direction's monomials scaled by the lobe's band factors over the cosine's."""
    cos = np.einsum("ij,ij->i", normals, to_eye)
    d = (2.0 * cos)[:, None] * normals
    d -= to_eye
    d -= normals
    d *= factors[:, 0:1]
    d += normals
    d /= np.sqrt(np.maximum(np.einsum("ij,ij->i", d, d), _F32(1e-24)))[:, None]
    mono = monomials(d, terms)
    mono[1:4] *= factors[:, 1]
    if terms == 9:
        # z^2 carries 1/3 of band 0 (the table folds SH's -1 into the constant): keep it unscaled.
        mono[6] -= _F32(1.0 / 3.0)
        mono[4:9] *= factors[:, 2]
        mono[6] += _F32(1.0 / 3.0)
    return mono


def view_ratio(system, lookup, prim: np.ndarray, position: np.ndarray, normal: np.ndarray,
               hit_dirs: np.ndarray, cells: np.ndarray | None = None,
               irradiance: np.ndarray | None = None) -> np.ndarray:
    """(m, 3) float32 the factor by which hits (prim (m,) >= 0 at position, normal, reached along
    hit_dirs (m, 3)) reflect the cache's light through their glossy lobes, against the diffuse
    stand-in (see the module docstring); 1 where their material has no lobe. cells : (m,) the
    cache cells the hits read (`HitLookup.cells`) and irradiance (m, 3) their light there at the
    normal, if the caller has them (lookup a `HitLookup` then)."""
    mats = system.glossy_materials
    surfaces = system.updater.scene.surfaces
    material = np.take(surfaces.material_index, prim)
    out = np.ones((prim.shape[0], 3), _F32)
    live = np.flatnonzero(np.take(mats.reflects, material))
    if live.size == 0:
        return out
    rows = np.take(material, live)
    nrm = np.take(normal, live, axis=0)
    to_eye = -np.take(hit_dirs, live, axis=0)
    # The Glossy Color at the ray's view over its cosine-weighted mean (1 where that is 0).
    mean = np.take(color_mean(mats), rows)
    view = np.where(mean > 1e-8, (glossy_color(mats, rows, np.einsum("ij,ij->i", nrm, to_eye)) @ LUMA)
                    / np.maximum(mean, _F32(1e-8)), _F32(1.0))
    factors = np.take(lobe_factors(mats, float(surfaces.filter_glossy)), rows, axis=0)
    if cells is None:
        # A multi-level lookup (`levels.LevelLookup`): its coarsest level's light, smooth enough
        # for a ratio of directions.
        lookup = getattr(lookup, "lookups", (lookup,))[0]
        cells = lookup.cells(np.take(position, live, axis=0), nrm)
    else:
        cells = np.take(cells, live)
    lobe = lookup.evaluate(cells, lobe_monomials(nrm, to_eye, factors, lookup.terms)).T
    irradiance = lookup.evaluate(cells, monomials(nrm, lookup.terms)).T if irradiance is None else \
        np.take(irradiance, live, axis=0)
    ratio = np.where(irradiance > MIN_IRRADIANCE, lobe / np.maximum(irradiance, MIN_IRRADIANCE), 1.0)
    out[live] = np.clip(ratio * view[:, None], 0.0, MAX_RATIO)
    return out
