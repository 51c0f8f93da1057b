"""Lamp light through thin translucent surfaces (a Translucent BSDF: leaves, paper, lampshades).

Cycles counts a Translucent BSDF as a diffuse closure: its colour is in Diffuse Color, and the
light it diffuses from the other side of the surface is in Diffuse Direct / Indirect. A mix of a
Diffuse and a Translucent BSDF reflects per channel (1 - t) of its diffuse colour's light from
the front and t from behind, t = the translucent part's share of that colour
(`snapshot.Material.translucent`; `surface_mix.mix` weighs it). So a receiver's lamp irradiance is
(1 - t) E(n) + t E(-n): the lamps are sampled again on the back of the surface, the normal
flipped, only at receivers with t > 0. A sunlit leaf seen from below glows (it was black:
Diffuse Direct 0 against Cycles' 0.96 on a back-lit Translucent plane).

The light of the cache and the pixel rays (sky, bounces) is read on the front only: a thin leaf
in foliage sees similar diffuse light on both sides, the sun's is what differs. Probe and pixel
ray hits on such a surface take its whole diffuse colour under the light of the side they hit.

numpy only (no bpy, no gpu).
"""

from __future__ import annotations

import numpy as np

#: Added to the frame number of the back side's lamp samples: a stream of their own.
BACK_SEED_OFFSET = 1 << 22


def share_table(materials) -> np.ndarray | None:
    """(m, 3) float32 each material's translucent share per channel (`Material.translucent`, 0
    where none), or None when no material has one (nothing to do)."""
    shares = [getattr(m, "translucent", None) for m in materials]
    if all(s is None for s in shares):
        return None
    table = np.zeros((len(shares), 3), np.float32)
    for i, s in enumerate(shares):
        if s is not None:
            table[i] = s
    return table


def pixel_shares(table: np.ndarray | None, material: np.ndarray) -> np.ndarray | None:
    """(n, 3) float32 the translucent share at pixels of G-buffer material texels `material` (n,)
    (index + 1, 0 = background; a fraction carries a metallic texel), or None without any."""
    if table is None:
        return None
    rows = np.floor(np.asarray(material, np.float32).reshape(-1)).astype(np.int64) - 1
    known = (rows >= 0) & (rows < table.shape[0])
    out = np.zeros((rows.shape[0], 3), np.float32)
    out[known] = table[rows[known]]
    return out if out.any() else None


def lit_from_behind(shares: np.ndarray | None) -> np.ndarray:
    """(k,) the receivers of shares (n, 3) (None: none) with some translucent share."""
    if shares is None:
        return np.zeros(0, np.intp)
    return np.flatnonzero(shares.max(axis=1) > 0)


def blend(front: np.ndarray, back: np.ndarray, share: np.ndarray) -> np.ndarray:
    """(1 - t) front + t back, float32 (t broadcast over the light's trailing axes)."""
    return ((1.0 - share) * front + share * np.asarray(back, np.float32)).astype(np.float32)


def mix_back(front: np.ndarray, shares: np.ndarray | None, back_light) -> np.ndarray:
    """(n, 3) the lamp irradiance (1 - t) front + t back at n receivers of shares t (n, 3) (None:
    `front` as it is). back_light(rows) -> (k, 3) the lamps' light on the back of the receivers
    `rows` (k,) (their normals flipped), called only for those with some t > 0."""
    rows = lit_from_behind(shares)
    if rows.size == 0:
        return front
    out = np.array(front, np.float32, copy=True)
    out[rows] = blend(out[rows], back_light(rows), shares[rows])
    return out
