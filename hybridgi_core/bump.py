"""Shading normals bent by normal maps, as Cycles lights them (bpy-free).

A normal map (`snapshot.NormalMap`, applied by the G-buffer) turns the shading normal N away
from the smooth surface normal Ns. Cycles then weighs a diffuse closure's light from direction
wi by its bump shadowing term (kernel/closure/bsdf.h `bump_shadowing_term`: zero where wi is on
the other side of the smooth surface than N says, else the GGX masking G1 of |Ns.wi| with a
roughness from the deviation, alpha^2 = tan^2(Ns, N) / 8), which darkens ridges turned towards a
low lamp (Diffuse Direct 20% at the crest of a 50-degree ridge under a 20-degree sun).

The G-buffer keeps Ns under each pixel (`GBufferPass.read_surface`), which final renders hand
to the lamps' and the pixel rays' code; where no image gives it (the viewport's worker),
`smooth_normals` recovers it from the ray mesh with one short ray back along N.
`irradiance_kernel` reads radiance SH through the lobe the term shapes (the pixel rays' cache).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np

from . import shipped

_F32 = np.float32


def has_normal_maps(scene) -> bool:
    """Whether any material of `scene` (a SceneSnapshot) bends its normals by a normal map."""
    return any(getattr(m, "normal_map", None) is not None for m in getattr(scene, "materials", ()))


def smooth_normals(surfaces, tracer, points: np.ndarray, normals: np.ndarray, eps: float) -> np.ndarray:
    """(n, 3) float32 unit interpolated vertex normals of the ray mesh under points (n, 3), on the
    side of their shading normals (n, 3): one ray from just above each point back along its
    normal (`surfaces` a `shading.SurfaceTable`, `tracer` the ray scene's). Where the ray finds
    nothing, the shading normal itself (the term is then 1)."""
    points = np.asarray(points, _F32).reshape(-1, 3)
    normals = np.asarray(normals, _F32).reshape(-1, 3)
    down = np.ascontiguousarray(-normals)
    start = np.ascontiguousarray(points + normals * _F32(4.0 * eps))
    probe = tracer.intersect(start, down, _F32(64.0 * eps), trusted=True)
    out = normals.copy()
    hit = np.flatnonzero(probe.prim >= 0)
    if hit.size:
        # `surface` turns each normal against its ray: towards the shading normal's side.
        found = surfaces.surface(probe.prim[hit], probe.u[hit], probe.v[hit], down[hit]).normal
        out[hit] = found
    return out


def shadowing_term(smooth: np.ndarray, normals: np.ndarray, wi: np.ndarray) -> np.ndarray:
    """(n,) float32 Cycles' bump shadowing term of a diffuse closure with (bent) normals (n, 3)
    over a surface whose smooth normals are `smooth` (n, 3), for unit directions wi (n, 3)
    towards the light (kernel/closure/bsdf.h, with bump map correction, Blender's default).
    1 where the normal is not bent."""
    cos_si = np.einsum("ij,ij->i", smooth, wi)
    cos_sn = np.einsum("ij,ij->i", smooth, normals)
    cos_ni = np.einsum("ij,ij->i", normals, wi)
    cos_i = np.abs(cos_si)
    cos_d = np.minimum(np.abs(cos_sn), _F32(1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        tan2_d = _F32(1.0) / np.maximum(cos_d * cos_d, _F32(1e-12)) - _F32(1.0)
        alpha2 = np.clip(_F32(0.125) * tan2_d, 0.0, 1.0)
        cos2_i = np.maximum(cos_i * cos_i, _F32(1e-12))
        g1 = _F32(2.0) / (_F32(1.0) + np.sqrt(_F32(1.0) + alpha2 * (_F32(1.0) - cos2_i) / cos2_i))
    term = np.where((cos_d >= 1.0) | (cos_i >= 1.0), _F32(1.0), g1)
    term = np.where(cos_i < 1e-6, _F32(0.0), term)
    # Light on the other side of the smooth surface than the bent normal says: none.
    term = np.where(cos_si * cos_sn * cos_ni < 0.0, _F32(0.0), term)
    return term.astype(_F32)


#: Samples of the bend angle (0 .. 90 degrees) in `_lobe_moments`' table.
LOBE_ANGLES = 128
#: Directions of the table's quadrature (a spherical Fibonacci set): moments within 0.004 (of pi)
#: of 256 x 65536's.
LOBE_DIRECTIONS = 16384
#: The table as `compute_lobe_moments` makes it, shipped so that a render of normal-mapped
#: surfaces does not compute it in every process (44 ms of a one-frame headless render). Rebuild
#: with `python -m hybridgi_core.bump`; tests/test_normal_map checks that it matches.
LOBE_FILE = Path(__file__).with_name("bump_lobe_moments.npz")
#: What the shipped file was computed from: a file of other sizes is ignored (then computed here).
LOBE_KEY = np.array([LOBE_ANGLES, LOBE_DIRECTIONS])
#: Shading normals within this cosine of the smooth normal count as unbent (`irradiance_kernel`).
UNBENT_COS = 1.0 - 1e-6


@lru_cache(maxsize=1)
def _lobe_moments() -> np.ndarray:
    """`compute_lobe_moments()`'s table: the shipped `LOBE_FILE` when it was made for these sizes,
    else computed; once per process."""
    table = shipped.load(LOBE_FILE, LOBE_KEY, "moments")
    return table[0] if table is not None else compute_lobe_moments()


def write_lobe_moments(path: Path = LOBE_FILE) -> None:
    """Write `compute_lobe_moments()` to `path` (the shipped file), keyed by the table's sizes."""
    shipped.write(path, LOBE_KEY, moments=compute_lobe_moments())


def compute_lobe_moments() -> np.ndarray:
    """(LOBE_ANGLES, 7) float64 moments of the lobe K(w) = max(0, N.w) x shadowing_term(Ns, N, w)
    in the frame where Ns = z and N = (sin t, 0, cos t), t = i / (LOBE_ANGLES - 1) x 90 degrees:
    int K, int x K, int z K, int x^2 K, int y^2 K, int z^2 K, int x z K (the others are 0 by the
    lobe's mirror symmetry in y). A quadrature over a Fibonacci sphere."""
    i = np.arange(LOBE_DIRECTIONS) + 0.5
    z = 1.0 - 2.0 * i / LOBE_DIRECTIONS
    r = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    phi = i * np.pi * (3.0 - np.sqrt(5.0))
    w = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
    da = 4.0 * np.pi / LOBE_DIRECTIONS
    up = np.broadcast_to(np.array([0.0, 0.0, 1.0], _F32), w.shape)
    out = np.zeros((LOBE_ANGLES, 7))
    wf = w.astype(_F32)
    for a, t in enumerate(np.linspace(0.0, 0.5 * np.pi, LOBE_ANGLES)):
        n = np.array([np.sin(t), 0.0, np.cos(t)])
        cos = np.maximum(w @ n, 0.0)
        nb = np.broadcast_to(n.astype(_F32), w.shape)
        k = cos * shadowing_term(up, nb, wf).astype(np.float64) * da
        x, y, zz = w[:, 0], w[:, 1], w[:, 2]
        out[a] = (k.sum(), (x * k).sum(), (zz * k).sum(), (x * x * k).sum(), (y * y * k).sum(),
                  (zz * zz * k).sum(), (x * zz * k).sum())
    return out


def lobe_moments() -> np.ndarray:
    """The bent lobe's moment table (`_lobe_moments`, computed once per process): what the GPU
    gather interpolates (`raster.gather.lobe_texels`) as `irradiance_kernel` does."""
    return _lobe_moments()


#: Texels of a normal map `map_bend_factor` averages over (a strided subset of larger maps).
BEND_SAMPLE_TEXELS = 1 << 16


def map_bend_factor(normal_map) -> float:
    """The share of a smooth surface's diffuse light that a tangent-space normal map leaves its
    surface: the bent lobe's integral (with Cycles' bump shadowing term) over the cosine lobe's,
    pi, for light from every direction above the surface, averaged over the map's texels.

    Why: probe-ray hits shade a normal-mapped surface with its facet normal (a hit only feeds a
    cell's average), so they reflected the smooth surface's light, where Cycles' bent normals
    reflect less (ridges tilted up to 50 degrees: 0.82 of it; the room's Diffuse Indirect +23%).
    1.0 without a map image (and for Bump nodes, whose bend depends on the mesh's UV scale)."""
    texture = None if normal_map is None else normal_map.texture
    if texture is None or normal_map.strength <= 0.0:
        return 1.0
    t = np.asarray(texture, np.float64).reshape(-1, 3)
    if t.shape[0] > BEND_SAMPLE_TEXELS:
        t = t[:: t.shape[0] // BEND_SAMPLE_TEXELS + 1]
    n = t * 2.0 - 1.0
    n[:, 2] -= 1.0
    n *= max(float(normal_map.strength), 0.0)
    n[:, 2] += 1.0  # Cycles' svm_node_normal_map: N + (mapped - N) strength, renormalized
    z = n[:, 2] / np.maximum(np.linalg.norm(n, axis=1), 1e-12)
    angle = np.arccos(np.clip(z, 0.0, 1.0)) / (0.5 * np.pi) * (LOBE_ANGLES - 1)
    share = _lobe_moments()[:, 0] / np.pi
    return float(np.clip(np.interp(angle, np.arange(LOBE_ANGLES), share).mean(), 0.0, 1.0))


def irradiance_kernel(smooth: np.ndarray, normals: np.ndarray, order: int) -> np.ndarray:
    """(n, K) float32 coefficients that turn radiance SH (n, K, c) into the irradiance a diffuse
    closure with bent normals (n, 3) over smooth normals `smooth` (n, 3) receives as Cycles
    weighs it: int L(w) max(0, N.w) shadowing_term(Ns, N, w) dw = sum_k kernel_k L_k. No light
    from below the smooth surface, the bump term's masking above it; `sh.basis(N) x
    sh.cosine_scale` exactly where N is not bent. The lobe's moments come from a table over the
    bend angle (`_lobe_moments`), turned into each pixel's frame (Ns, the bend's direction)."""
    from .sh import C0, C1, C2, C3, C4, basis, cosine_scale  # noqa: PLC0415

    g = np.asarray(smooth, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    plain = basis(n, order) * cosine_scale(order)
    cos = np.clip(np.einsum("ij,ij->i", g, n), -1.0, 1.0)
    bent = np.flatnonzero(cos < UNBENT_COS)
    if bent.size == 0:
        return plain
    g, n, cos = g[bent], n[bent], cos[bent]
    t = n - cos[:, None] * g
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
    b = np.cross(g, t)
    table = _lobe_moments()
    x = np.arccos(np.clip(cos, 0.0, 1.0)) / (0.5 * np.pi) * (LOBE_ANGLES - 1)
    i0 = np.minimum(x.astype(np.int64), LOBE_ANGLES - 2)
    f = (x - i0)[:, None]
    m = table[i0] * (1.0 - f) + table[i0 + 1] * f
    m0, mx, mz, mxx, myy, mzz, mxz = m.T
    first = mx[:, None] * t + mz[:, None] * g  # int w K

    def second(a, c):  # int (w.e_a)(w.e_c) K for world axes a, c
        return (mxx * t[:, a] * t[:, c] + myy * b[:, a] * b[:, c] + mzz * g[:, a] * g[:, c]
                + mxz * (t[:, a] * g[:, c] + g[:, a] * t[:, c]))

    k = np.empty((bent.size, plain.shape[1]))
    k[:, 0] = C0 * m0
    k[:, 1], k[:, 2], k[:, 3] = C1 * first[:, 1], C1 * first[:, 2], C1 * first[:, 0]
    if order >= 2:
        k[:, 4] = C2 * second(0, 1)
        k[:, 5] = C2 * second(1, 2)
        k[:, 6] = C3 * (3.0 * second(2, 2) - m0)
        k[:, 7] = C2 * second(0, 2)
        k[:, 8] = C4 * (second(0, 0) - second(1, 1))
    out = np.array(plain, _F32)
    out[bent] = k
    return out


if __name__ == "__main__":
    write_lobe_moments()
    print(f"wrote {LOBE_FILE}")  # noqa: T201 (a developer command)
