"""Linearly transformed cosines (Heitz, Dupuy, Hill and Neubelt, SIGGRAPH 2016): the GGX lobe's
light from a polygonal lamp in closed form.

Why: an area lamp's glossy highlight was estimated with lamp samples and shadow rays per pixel
(`glossy.glossy_direct`: 4 everywhere, 32 where noisy), most of a glossy scene's frame (bunny_npm
and dragon_npm at 640x360: ~1.5 s of a core). An LTC is a clamped cosine distribution seen through
a 3x3 matrix M; its integral over a polygon is the form factor of the polygon mapped by M^-1, which
Lambert's formula gives exactly (`polygon_light`). Fitted to the lobe (`scripts/fit_ltc.py`, the
shipped TABLE_FILE), the lamp's unshadowed glossy light is one formula per pixel, lamp and lobe,
noise-free; the lamp light's shadows come from the diffuse light's visibility (the ratio estimator
of `polygon_light`: Heitz et al. 2018), so no glossy shadow ray is traced either.

The table holds, per roughness and view angle, M^-1 = [[a, 0, b], [0, 1, 0], [c, 0, d]] in the
frame whose z is the normal and whose x-z plane holds the view. The lobe's magnitude is not in it:
the caller scales by the lobe's albedo (multiple scattering and view factor) with its Fresnel taken
at the half vector of the direction the light arrives from on average (`polygon_integral`'s
cos_hv): a dielectric's Fresnel grows several-fold towards grazing half vectors, so its lobe-wide
mean (Glossy Color) overstated a lamp in the mirror direction by ~20% at roughness 0.5.

numpy only (no bpy).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from . import polygon_light
from . import specular as sp

#: Roughness and view-angle samples of the table (uniform in roughness and in the view's angle).
TABLE_SIZE = 32
#: The shipped fit (`scripts/fit_ltc.py`).
TABLE_FILE = Path(__file__).with_name("ltc_ggx.npz")
#: The fit's smoothest roughness: its first column stands for every smoother lobe.
MIN_FIT_ROUGHNESS = 0.05
#: Smallest view cosine the fit and the look-up use (grazing views are clamped to it).
MIN_MU = 1e-3
#: Largest correction of the fit at the light's mean direction (`polygon_integral`).
MAX_CORRECTION = 4.0


def grid(size: int = TABLE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """(roughness (size,), view cosine (size,)) of the table's cells."""
    t = np.arange(size) / (size - 1)
    return t, np.maximum(np.cos(t * (0.5 * np.pi)), MIN_MU)


def ggx_lobe(alpha2: np.ndarray, mu: np.ndarray, wi: np.ndarray) -> np.ndarray:
    """(N,) D G2 / (4 cos_i) of the GGX lobe (F = 1; height-correlated Smith) towards unit
    directions wi (N, 3) in the frame whose z is the normal and whose view is (sqrt(1 - mu^2), 0,
    mu); alpha2, mu (N,). 0 below the horizon. What `glossy._lobe_terms` weighs by the Fresnel."""
    sin = np.sqrt(np.maximum(1.0 - mu * mu, 0.0))
    hx, hy, hz = wi[:, 0] + sin, wi[:, 1], wi[:, 2] + mu
    cos2 = hz * hz / np.maximum(hx * hx + hy * hy + hz * hz, 1e-300)
    x = cos2 * (alpha2 - 1.0) + 1.0
    d = alpha2 / (np.pi * x * x)
    g2 = 1.0 / (1.0 + sp._lambda(alpha2, mu) + sp._lambda(alpha2, np.maximum(wi[:, 2], 1e-12)))
    return np.where(wi[:, 2] > 0, d * g2 / (4.0 * mu), 0.0)


def density(params: np.ndarray, wi: np.ndarray) -> np.ndarray:
    """(N,) the LTC of M^-1 = [[a, 0, b], [0, 1, 0], [c, 0, d]] at unit directions wi (N, 3);
    params (4,) one (a, b, c, d) for all, or (N, 4) one per direction: the clamped cosine / pi at
    M^-1 wi / |M^-1 wi| times the Jacobian |det M^-1| / |M^-1 wi|^3."""
    a, b, c, d = np.moveaxis(np.asarray(params, np.float64), -1, 0)
    lo = np.stack([a * wi[:, 0] + b * wi[:, 2], wi[:, 1], c * wi[:, 0] + d * wi[:, 2]], axis=1)
    length = np.maximum(np.linalg.norm(lo, axis=1), 1e-30)
    return np.maximum(lo[:, 2] / length, 0.0) / np.pi * np.abs(a * d - b * c) / length**3


@lru_cache(maxsize=1)
def table() -> np.ndarray:
    """(TABLE_SIZE, TABLE_SIZE, 4) float64 (a, b, c, d) per (roughness, view angle) cell."""
    with np.load(TABLE_FILE) as data:
        return np.asarray(data["m_inv"], np.float64)


def lookup(rough: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """(n, 4) (a, b, c, d) of M^-1 at roughness `rough` and view cosine `mu` (n,): bilinear in
    the table, whose entries are smooth in both."""
    t = table()
    size = t.shape[0]
    x = np.clip(np.asarray(rough, np.float64), 0.0, 1.0) * (size - 1)
    theta = np.arccos(np.clip(np.asarray(mu, np.float64), MIN_MU, 1.0))
    y = np.clip(theta / (0.5 * np.pi), 0.0, 1.0) * (size - 1)
    i0 = np.minimum(x.astype(np.int64), size - 2)
    j0 = np.minimum(y.astype(np.int64), size - 2)
    fx = (x - i0)[:, None]
    fy = (y - j0)[:, None]
    top = t[i0, j0] * (1.0 - fy) + t[i0, j0 + 1] * fy
    bottom = t[i0 + 1, j0] * (1.0 - fy) + t[i0 + 1, j0 + 1] * fy
    return top * (1.0 - fx) + bottom * fx


def view_frame(normals: np.ndarray, to_eye: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, y, mu): unit tangent x (n, 3) towards the view, y = n x x, and the view cosine (n,).
    A view along the normal takes any tangent (the lobe is then round)."""
    mu = np.einsum("ij,ij->i", normals, to_eye)
    x = to_eye - normals * mu[:, None]
    length = np.linalg.norm(x, axis=1)
    flat = length < 1e-7
    if flat.any():
        # Any perpendicular: the axis least aligned with the normal, projected out.
        axis = np.eye(3)[np.argmin(np.abs(normals[flat]), axis=1)]
        x[flat] = axis - normals[flat] * np.einsum("ij,ij->i", axis, normals[flat])[:, None]
        length[flat] = np.linalg.norm(x[flat], axis=1)
    x /= np.maximum(length, 1e-30)[:, None]
    y = np.cross(normals, x)
    return x, y, mu


def polygon_integral(polygon: np.ndarray, points: np.ndarray, normals: np.ndarray, to_eye: np.ndarray,
                     rough: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(integral (n,), cos_hv (n,)) float64: the integral of the fitted lobe (normalised: 1 over
    the sphere) over the convex polygon (k, 3) seen from each receiver (points, unit normals, unit
    directions to the eye, (n, 3) each; rough (n,) the lobe's roughness), clipped to the surface's
    horizon and to the cosine's (tilted from it: between the two the lobe is 0 and the fit is
    not, or the other way round); and the cosine between the view and the half vector of the direction
    the lobe's light arrives from on average (the polygon's vector form factor in the cosine's
    space, mapped back by M): where the caller takes the lobe's Fresnel. The integral is
    corrected towards the lobe's own value there (`_correction`). The lamp's glossy radiance is
    its radiance x the lobe's albedo there x the integral."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    v = np.asarray(to_eye, np.float64).reshape(-1, 3)
    if p.shape[0] == 0:
        return np.zeros(0), np.ones(0)
    x, y, mu = view_frame(n, v)
    m = lookup(rough, mu)
    rel = [polygon[None, :, c] - p[:, c, None] for c in range(3)]  # (n, k) planes
    lx = rel[0] * x[:, 0:1] + rel[1] * x[:, 1:2] + rel[2] * x[:, 2:3]
    ly = rel[0] * y[:, 0:1] + rel[1] * y[:, 1:2] + rel[2] * y[:, 2:3]
    lz = rel[0] * n[:, 0:1] + rel[1] * n[:, 1:2] + rel[2] * n[:, 2:3]
    a, b, c, d = (m[:, i : i + 1] for i in range(4))
    f = _form_factor_above(lx, ly, lz, a, b, c, d)
    # Back through M: the x-z block of M^-1 inverted, y unchanged.
    a, b, c, d = m.T
    det = a * d - b * c
    det = np.where(np.abs(det) > 1e-12, det, 1e-12)
    w = np.stack([(d * f[:, 0] - b * f[:, 2]) / det, f[:, 1], (a * f[:, 2] - c * f[:, 0]) / det], axis=1)
    length = np.linalg.norm(w, axis=1)
    seen = length > 0
    w[seen] /= length[seen, None]
    w[~seen] = (0.0, 0.0, 1.0)
    mu = np.clip(mu, MIN_MU, 1.0)
    sin = np.sqrt(1.0 - mu * mu)
    # h = l + v in the local frame (v = (sin, 0, mu)); cos(h, v) = sqrt((1 + l . v) / 2).
    cos_hv = np.sqrt(np.clip(0.5 * (1.0 + w[:, 0] * sin + w[:, 2] * mu), 0.0, 1.0))
    integral = f[:, 2] / np.pi
    return integral * _correction(m, np.asarray(rough, np.float64), mu, w, integral), cos_hv


def _form_factor_above(lx, ly, lz, a, b, c, d) -> np.ndarray:
    """(n, 3) the vector form factor, in the cosine's space, of the polygons (local-frame vertex
    planes lx, ly, lz (n, k)) mapped by M^-1 (its entries a, b, c, d (n, 1)): of their part above
    the surface's horizon (lz >= 0), which `vector_form_factor` then clips to the cosine's."""
    out = np.zeros((lx.shape[0], 3))
    cut = (lz < 0.0).any(axis=1)
    for rows, clip in ((np.flatnonzero(~cut), False), (np.flatnonzero(cut), True)):
        if rows.size == 0:
            continue
        x, y, z = lx[rows], ly[rows], lz[rows]
        if clip:
            (x, y, z), count = polygon_light.clip_below([x, y, z], z)
            rows, x, y, z = rows[count >= 3], x[count >= 3], y[count >= 3], z[count >= 3]
        ar, br, cr, dr = a[rows], b[rows], c[rows], d[rows]
        out[rows] = polygon_light.vector_form_factor([ar * x + br * z, y, cr * x + dr * z])
    return out


def _correction(m: np.ndarray, rough: np.ndarray, mu: np.ndarray, w: np.ndarray, integral: np.ndarray) -> np.ndarray:
    """(n,) the fit's correction at the light's mean direction w (n, 3, local frame): the lobe
    over the LTC there, towards 1 as the lamp holds more of the lobe (integral (n,)).

    Why: no LTC matches the lobe everywhere (the fit's L1 distance is ~0.08 at roughness 0.5
    and 45 degrees): lamps in the lobe's tail read up to 2-3 x, lamps off its peak ~5% low
    (bunny_npm's facets under its large lamp, against 256 lamp samples: 7.3% mean error of the
    glossy lamp light). A small lamp's light is the lobe's value at its direction times its solid
    angle, so the ratio of the two distributions there makes it exact; a lamp holding the whole
    lobe needs none. Between, the ratio at the light's mean direction weighted by the lobe's
    share outside the lamp: 2.5% mean error there."""
    alpha2 = np.maximum(rough, MIN_FIT_ROUGHNESS) ** 4
    lobe = ggx_lobe(alpha2, mu, w) / np.maximum(sp._lerp_table(sp.tables()[0], [rough, mu]), 1e-6)
    fitted = density(m, w)
    ratio = np.where(fitted > 0, np.minimum(lobe / np.maximum(fitted, 1e-30), MAX_CORRECTION), 1.0)
    return 1.0 + (ratio - 1.0) * (1.0 - np.clip(integral, 0.0, 1.0))
