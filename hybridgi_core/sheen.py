"""Cycles' Sheen closure as HybridGI renders it: a diffuse colour that grows at grazing views.

Why: Cycles counts its Sheen closure (the Sheen BSDF node, the Principled BSDF's sheen layer:
fabric, velvet, dust) as a diffuse closure. Its weight is the microfiber sheen lobe's directional
albedo A(mu, roughness) at the view cosine mu (Zeltner et al. 2022, Cycles' `bsdf_sheen`), so the
Diffuse Color pass shows colour x A(mu) and the Diffuse Direct / Indirect passes the light it
gathers as a diffuse surface does; the Principled BSDF's layers under its sheen (specular and
diffuse base) are weighted 1 - max(sheen colour) x A(mu) (Cycles' closure_layering_weight).
Checked: a white Sheen BSDF (roughness 0.5) under a uniform world has Diffuse Color 0.019 at
mu = 1, 0.154 at mu = 0.5 and 0.458 at mu = 0.17, and Diffuse Direct the world's 1.0 x its
radiance; a Principled BSDF (base 0.5, sheen 1) 0.5 (1 - A) + A at the same cosines.

HybridGI folds it into the G-buffer's per-material view-dependent weight table (`weight_row`:
red multiplies the diffuse colour, green-blue-alpha add the sheen's colour) and into what a
probe-ray hit reflects (`hit_albedo`, `hit_weight`: the cosine-weighted means over the
hemisphere). The lamps' light on it is the diffuse light (the lobe's shape, brighter towards
grazing lamps, is not followed: exact under uniform light); the specular and metallic lobes
under a Principled BSDF's sheen are weighted as its base is (`layer_factor`,
`glossy.under_sheen`; a probe-ray hit's glossy albedo keeps its full weight). The table is
Cycles' own, measured
by `scripts/measure_sheen_albedo.py` (the Diffuse Color of white Sheen BSDF spheres).

Pure numpy: no bpy.
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

TABLE_FILE = Path(__file__).with_name("sheen_albedo.npz")


@lru_cache(maxsize=1)
def _table() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(albedo (R, M), roughness (R,), mu (M,)) of `TABLE_FILE`."""
    with np.load(TABLE_FILE) as data:
        return (data["albedo"].astype(np.float64), data["roughness"].astype(np.float64),
                data["mu"].astype(np.float64))


def albedo(roughness: float, mu) -> np.ndarray:
    """(...) the sheen lobe's directional albedo at view cosines mu (clipped to 0..1), bilinear in
    the measured table; roughness is clipped to 0..1 as Cycles clips it."""
    table, rough_grid, mu_grid = _table()
    r = float(np.clip(np.nan_to_num(roughness, nan=0.5), 0.0, 1.0))
    i = min(int(np.searchsorted(rough_grid, r, side="right")) - 1, rough_grid.size - 2)
    t = (r - rough_grid[i]) / (rough_grid[i + 1] - rough_grid[i])
    row = (1.0 - t) * table[i] + t * table[i + 1]
    return np.interp(np.clip(np.asarray(mu, np.float64), 0.0, 1.0), mu_grid, row)


def hemispherical_albedo(roughness: float) -> float:
    """Cosine-weighted mean of the albedo over the hemisphere, 2 int A(mu) mu dmu: what a
    probe-ray hit, lit and seen from every direction at once, reflects of the sheen colour."""
    mu = (np.arange(64) + 0.5) / 64
    return float(np.mean(2.0 * albedo(roughness, mu) * mu))


def colour_of(material) -> np.ndarray | None:
    """(3,) a material's sheen colour (`Material.sheen`), or None when it has none."""
    sheen = getattr(material, "sheen", None)
    return None if sheen is None else np.asarray(sheen, np.float64).reshape(3)


def weight_row(material, mu: np.ndarray) -> np.ndarray:
    """(len(mu), 4) the sheen's share of the G-buffer's weight table at cosines mu: red the
    factor on the diffuse colour (1 - max(sheen) A where the sheen is layered over the base, a
    Principled BSDF's; else 1), green-blue-alpha the sheen colour x A added to it."""
    row = np.zeros((len(mu), 4))
    row[:, 0] = 1.0
    sheen = colour_of(material)
    if sheen is None:
        return row
    under = layer_factor(material, mu)
    if under is not None:
        row[:, 0] = under
    row[:, 1:] = albedo(material.sheen_roughness, mu)[:, None] * sheen[None, :]
    return row


def layer_factor(material, mu: np.ndarray) -> np.ndarray | None:
    """(len(mu),) the weight of what lies under a Principled BSDF's sheen (its specular and
    metallic lobes, as its diffuse base: `weight_row`'s red) at view cosines mu, 1 - max(sheen) A;
    None without a layered sheen."""
    sheen = colour_of(material)
    if sheen is None or not getattr(material, "sheen_layered", False):
        return None
    return np.clip(1.0 - sheen.max() * albedo(material.sheen_roughness, mu), 0.0, 1.0)


def hit_weight(material) -> float:
    """The factor on a probe-ray hit's diffuse base under a layered sheen (1 without one)."""
    sheen = colour_of(material)
    if sheen is None or not material.sheen_layered:
        return 1.0
    return float(np.clip(1.0 - sheen.max() * hemispherical_albedo(material.sheen_roughness), 0.0, 1.0))


def hit_albedo(material) -> np.ndarray:
    """(3,) the sheen's albedo a probe-ray hit adds to its diffuse base (zeros without one)."""
    sheen = colour_of(material)
    if sheen is None:
        return np.zeros(3, np.float32)
    return (sheen * hemispherical_albedo(material.sheen_roughness)).astype(np.float32)
