"""Surface attributes at ray hits: position, normals, albedo, emission.

Per-triangle data is packed into one float32 record so a hit costs a single `np.take` row gather
(about 3x faster than chained fancy indexing over several arrays).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .snapshot import Geometry, Material

# Record layout (floats): v0 | e1 | e2 | n0 | n1 | n2 | uv0 | uv1 | uv2 | material | face normal
_V0, _E1, _E2, _N0, _N1, _N2 = (slice(3 * i, 3 * i + 3) for i in range(6))
_UV0, _UV1, _UV2 = slice(18, 20), slice(20, 22), slice(22, 24)
_MAT = 24
_FN = slice(25, 28)
RECORD_FLOATS = 28


@dataclass
class SurfaceHits:
    """Attributes of n hit points. position/normal/face_normal : (n, 3); albedo/emission : (n, 3);
    backface : (n,) bool (the ray arrived from behind the geometric normal)."""

    position: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray
    emission: np.ndarray
    backface: np.ndarray


class SurfaceTable:
    """Packed triangles and materials of one traced Geometry (built once per geometry change)."""

    def __init__(self, geometry: Geometry, materials: list[Material]):
        self.records = _pack(geometry, np.arange(geometry.triangle_count))
        self.set_materials(materials)

    def update_rows(self, geometry: Geometry, rows: np.ndarray) -> None:
        """Re-pack the triangles `rows` (moved or deformed) from `geometry` (same topology).

        A new records array is swapped in whole, so a worker reading the old one stays consistent.
        """
        records = self.records.copy()
        records[rows] = _pack(geometry, rows)
        self.records = records

    def set_materials(self, materials: list[Material]) -> None:
        self.materials = materials
        self.albedo = np.array([m.base_color for m in materials], np.float32).reshape(-1, 3)
        self.mean_albedo = np.array([m.mean_albedo for m in materials], np.float32).reshape(-1, 3)
        self.emission = np.array([m.emission for m in materials], np.float32).reshape(-1, 3)
        self.textured = [i for i, m in enumerate(materials) if m.texture is not None]

    def surface(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray, ray_dirs: np.ndarray) -> SurfaceHits:
        """Attributes at hits (prim >= 0 only). prim (n,) int32, u, v (n,) float32, ray_dirs (n, 3)."""
        r = np.take(self.records, prim, axis=0)
        u = u[:, None]
        v = v[:, None]
        w0 = 1.0 - u - v
        pos = r[:, _E1] * u
        pos += r[:, _V0]
        pos += v * r[:, _E2]
        nrm = r[:, _N0] * w0
        nrm += u * r[:, _N1]
        nrm += v * r[:, _N2]
        # Normalize and turn to the side the ray came from (probe rays see both faces of open
        # meshes) in one scale: the sign of n . d does not depend on n's length.
        scale = 1.0 / np.sqrt(np.maximum(np.einsum("ij,ij->i", nrm, nrm), np.float32(1e-24)))
        np.negative(scale, out=scale, where=np.einsum("ij,ij->i", nrm, ray_dirs) > 0)
        nrm *= scale[:, None]
        backface = np.einsum("ij,ij->i", r[:, _FN], ray_dirs) > 0
        mat = r[:, _MAT].astype(np.int32)
        albedo = np.take(self.albedo, mat, axis=0)
        if self.textured:
            uv = w0 * r[:, _UV0] + u * r[:, _UV1] + v * r[:, _UV2]
            for m in self.textured:
                sel = mat == m
                if not sel.any():
                    continue
                tex_uv = uv[sel]
                known = np.isfinite(tex_uv).all(axis=1)
                col = np.tile(self.mean_albedo[m], (tex_uv.shape[0], 1))
                col[known] = self.albedo[m] * sample_texture(self.materials[m].texture, tex_uv[known])
                albedo[sel] = col
        return SurfaceHits(pos, nrm, albedo, np.take(self.emission, mat, axis=0), backface)


def _pack(geometry: Geometry, rows: np.ndarray) -> np.ndarray:
    """(len(rows), RECORD_FLOATS) float32 records of the given triangles."""
    tris = geometry.triangles[rows]
    p = geometry.positions[tris]  # (m, 3, 3)
    n = geometry.normals[tris]
    uv = geometry.uvs[tris]
    rec = np.empty((tris.shape[0], RECORD_FLOATS), np.float32)
    rec[:, _V0] = p[:, 0]
    rec[:, _E1] = p[:, 1] - p[:, 0]
    rec[:, _E2] = p[:, 2] - p[:, 0]
    rec[:, _N0], rec[:, _N1], rec[:, _N2] = n[:, 0], n[:, 1], n[:, 2]
    rec[:, _UV0], rec[:, _UV1], rec[:, _UV2] = uv[:, 0], uv[:, 1], uv[:, 2]
    rec[:, _MAT] = geometry.material_index[rows]
    fn = np.cross(rec[:, _E1], rec[:, _E2])
    length = np.linalg.norm(fn, axis=1, keepdims=True)
    rec[:, _FN] = np.divide(fn, length, out=np.zeros_like(fn), where=length > 0)
    return rec


def sample_texture(texture: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup with repeat wrapping. texture (h, w, 3) float32, uv (n, 2) -> (n, 3)."""
    h, w = texture.shape[:2]
    x = np.mod(uv[:, 0], 1.0) * w - 0.5
    y = np.mod(uv[:, 1], 1.0) * h - 0.5
    x0 = np.floor(x)
    y0 = np.floor(y)
    fx = (x - x0)[:, None].astype(np.float32)
    fy = (y - y0)[:, None].astype(np.float32)
    x0 = x0.astype(np.int64) % w
    y0 = y0.astype(np.int64) % h
    x1 = (x0 + 1) % w
    y1 = (y0 + 1) % h
    t = texture
    top = t[y0, x0] * (1 - fx) + t[y0, x1] * fx
    bottom = t[y1, x0] * (1 - fx) + t[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)
