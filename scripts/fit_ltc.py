"""Fit the linearly transformed cosines (Heitz et al. 2016) of Cycles' GGX reflection lobe and
write `hybridgi_core/ltc_ggx.npz` (`hybridgi_core.ltc` reads it).

    .venv/bin/python scripts/fit_ltc.py            # ~1 min on one core

Why a fit of our own: the lamps' glossy light of an area lamp is an integral of the lobe over the
lamp's polygon. An LTC is a clamped cosine seen through a 3x3 matrix, so that integral is the
polygon's form factor after the matrix's inverse (Lambert's formula, `polygon_light`): no lamp
samples at all. The lobe fitted is what `glossy._lobe_terms` evaluates with F = 1: D G2 / (4 cos_i)
(GGX, height-correlated Smith), normalised by its albedo, in the frame where the view lies in the
x-z plane. Each cell's inverse matrix [[a, 0, b], [0, 1, 0], [c, 0, d]] minimises the L1 distance
between the two distributions (what bounds the error of the integral over any lamp), estimated
with a fixed set of the lobe's visible-normal samples and of cosine samples (their balance
heuristic), plus the LTC's mass below the horizon. Nelder-Mead per cell, each started from its
neighbour (rough to smooth, normal to grazing incidence).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from hybridgi_core import ltc  # noqa: E402
from hybridgi_core.specular import _lambda  # noqa: E402

#: Samples per set (lobe, cosine) in each cell's objective: a stratified grid of SIDE x SIDE.
SIDE = 40


def _grid_uv(side: int) -> tuple[np.ndarray, np.ndarray]:
    u = (np.arange(side) + 0.5) / side
    a, b = np.meshgrid(u, u, indexing="ij")
    return a.ravel(), b.ravel()


def lobe(alpha: float, v: np.ndarray, wi: np.ndarray) -> np.ndarray:
    """(N,) the lobe (`ltc.ggx_lobe`) towards unit directions wi (N, 3), view v (3,) in the x-z plane."""
    return ltc.ggx_lobe(np.full(wi.shape[0], alpha * alpha), np.full(wi.shape[0], v[2]), wi)


def lobe_samples(alpha: float, v: np.ndarray, u1: np.ndarray, u2: np.ndarray):
    """(N, 3) the lobe's visible normals (Heitz, JCGT 2018) reflected: directions drawn by `_pdf_lobe`."""
    vh = np.array([alpha * v[0], alpha * v[1], v[2]])
    vh /= np.linalg.norm(vh)
    t1 = np.cross([0.0, 0.0, 1.0], vh)
    t1 = t1 / np.linalg.norm(t1) if np.linalg.norm(t1) > 1e-9 else np.array([1.0, 0.0, 0.0])
    t2 = np.cross(vh, t1)
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    p1 = r * np.cos(phi)
    s = 0.5 * (1.0 + vh[2])
    p2 = (1.0 - s) * np.sqrt(np.maximum(1.0 - p1 * p1, 0.0)) + s * r * np.sin(phi)
    pn = np.sqrt(np.maximum(1.0 - p1 * p1 - p2 * p2, 0.0))
    nh = p1[:, None] * t1 + p2[:, None] * t2 + pn[:, None] * vh
    h = np.stack([alpha * nh[:, 0], alpha * nh[:, 1], np.maximum(nh[:, 2], 1e-9)], axis=1)
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    return 2.0 * (h @ v)[:, None] * h - v[None, :]


def cosine_samples(u1: np.ndarray, u2: np.ndarray) -> np.ndarray:
    """(N, 3) cosine-distributed directions of the upper hemisphere (pdf z / pi)."""
    r = np.sqrt(u1)
    phi = 2.0 * np.pi * u2
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1.0 - u1, 0.0))], axis=1)


def _objective(params, wi, target, q):
    a, b, c, d = params
    m_inv = np.array([[a, 0.0, b], [0.0, 1.0, 0.0], [c, 0.0, d]])
    det = abs(np.linalg.det(m_inv))
    if det < 1e-12 or not np.all(np.isfinite(m_inv)):
        return 1e9
    g = ltc.density(params, wi)
    m = np.linalg.inv(m_inv)
    row = m[2] / np.linalg.norm(m[2])
    below = 1.0 - 0.5 * (1.0 + row[2])
    return float(np.mean(np.abs(target - g) / q)) + below


def nelder_mead(f, x0, step, iters=600, tol=1e-7):
    """Plain Nelder-Mead (no scipy at run or build time)."""
    n = x0.size
    pts = [x0] + [x0 + np.eye(n)[i] * step[i] for i in range(n)]
    vals = [f(p) for p in pts]
    for _ in range(iters):
        order = np.argsort(vals)
        pts = [pts[i] for i in order]
        vals = [vals[i] for i in order]
        if abs(vals[-1] - vals[0]) < tol:
            break
        c = np.mean(pts[:-1], axis=0)
        xr = c + (c - pts[-1])
        fr = f(xr)
        if fr < vals[0]:
            xe = c + 2.0 * (c - pts[-1])
            fe = f(xe)
            pts[-1], vals[-1] = (xe, fe) if fe < fr else (xr, fr)
        elif fr < vals[-2]:
            pts[-1], vals[-1] = xr, fr
        else:
            xc = c + 0.5 * (pts[-1] - c) if fr >= vals[-1] else c + 0.5 * (xr - c)
            fc = f(xc)
            if fc < min(fr, vals[-1]):
                pts[-1], vals[-1] = xc, fc
            else:
                pts = [pts[0]] + [pts[0] + 0.5 * (p - pts[0]) for p in pts[1:]]
                vals = [vals[0]] + [f(p) for p in pts[1:]]
    i = int(np.argmin(vals))
    return pts[i], vals[i]


def fit_cell(rough: float, mu: float, x0: np.ndarray, uv) -> tuple[np.ndarray, float]:
    alpha = max(rough, ltc.MIN_FIT_ROUGHNESS) ** 2
    mu = max(mu, ltc.MIN_MU)
    v = np.array([np.sqrt(1.0 - mu * mu), 0.0, mu])
    l1 = lobe_samples(alpha, v, *uv)
    wi = np.concatenate([l1, cosine_samples(*uv)])
    # Balance heuristic over both sets: q = (pdf_lobe + pdf_cos) / 2 per sample.
    pdf = _pdf_lobe(alpha, v, wi)
    q = 0.5 * (pdf + np.maximum(wi[:, 2], 0.0) / np.pi)
    f = lobe(alpha, v, wi)
    albedo = float(np.mean(f[: l1.shape[0]] / np.maximum(pdf[: l1.shape[0]], 1e-30)))
    target = f / max(albedo, 1e-12)
    keep = q > 0
    obj = lambda x: _objective(x, wi[keep], target[keep], q[keep])  # noqa: E731
    step = 0.1 * np.maximum(np.abs(x0), 0.05)
    x, err = nelder_mead(obj, x0, step)
    x, err = nelder_mead(obj, x, 0.02 * np.maximum(np.abs(x), 0.05))  # restart: NM stalls on ridges
    return x, err


def _pdf_lobe(alpha, v, wi) -> np.ndarray:
    """(N,) the visible-normal reflection pdf of directions wi (N, 3) (`lobe_samples`)."""
    h = wi + v[None, :]
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), 1e-12)
    a2 = alpha * alpha
    x = h[:, 2] ** 2 * (a2 - 1.0) + 1.0
    d = a2 / (np.pi * x * x)
    g1 = 1.0 / (1.0 + _lambda(a2, v[2]))
    vdh = np.maximum(h @ v, 0.0)
    return np.where(vdh > 0, g1 * d / (4.0 * v[2]), 0.0)


def fit_table(size: int) -> tuple[np.ndarray, np.ndarray]:
    uv = _grid_uv(SIDE)
    table = np.zeros((size, size, 4))
    errors = np.zeros((size, size))
    roughs, mus = ltc.grid(size)
    start = np.array([1.0, 0.0, 0.0, 1.0])
    for j in range(size):  # view: normal -> grazing
        x0 = start
        for i in range(size - 1, -1, -1):  # roughness: 1 -> smooth
            x, err = fit_cell(roughs[i], mus[j], x0, uv)
            table[i, j], errors[i, j] = x, err
            x0 = x
            if i == size - 1:
                start = x
        print(f"mu {mus[j]:.3f}: L1 {errors[:, j].min():.3f}..{errors[:, j].max():.3f}", flush=True)  # noqa: T201
    return table, errors


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=ltc.TABLE_SIZE)
    parser.add_argument("--out", type=Path, default=ltc.TABLE_FILE)
    args = parser.parse_args()
    table, errors = fit_table(args.size)
    np.savez_compressed(args.out, m_inv=table.astype(np.float32), l1=errors.astype(np.float32))
    print(f"wrote {args.out}: L1 median {np.median(errors):.3f}, max {errors.max():.3f}")  # noqa: T201
    return 0


if __name__ == "__main__":
    sys.exit(main())
