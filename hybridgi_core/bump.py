"""Shading normals bent by normal maps, as Cycles lights them (bpy-free).

A normal map (`snapshot.NormalMap`, applied by the G-buffer) turns the shading normal N away
from the smooth surface normal Ns. Cycles then weighs a diffuse closure's light from direction
wi by its bump shadowing term (kernel/closure/bsdf.h `bump_shadowing_term`: zero where wi is on
the other side of the smooth surface than N says, else the GGX masking G1 of |Ns.wi| with a
roughness from the deviation, alpha^2 = tan^2(Ns, N) / 8), which darkens ridges turned towards a
low lamp (Diffuse Direct 20% at the crest of a 50-degree ridge under a 20-degree sun).

The G-buffer hands the CPU only N; `smooth_normals` recovers Ns under each pixel from the ray
mesh with one short ray back along N, so the lamps' and the pixel rays' code need no new input.
"""

from __future__ import annotations

import numpy as np

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
