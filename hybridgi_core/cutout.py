"""Alpha cutouts for rays: which hits land on a cut-out part of an alpha-textured surface.

The tracer asks `Cutouts` about its hits and continues the rays that hit a hole past it
(`EmbreeTracer.set_cutouts`), so probe rays, shadow rays and visibility rays all see through
leaves, fences and decals where Cycles does. The image's own pixels are cut in the G-buffer
shader from the same alpha. Pure numpy.
"""

from __future__ import annotations

import numpy as np

from .snapshot import ALPHA_CUTOFF, Geometry, Material


class Cutouts:
    """Per-triangle alpha lookups of one ray geometry (indices as the tracer's prim ids), and the
    triangles shadow rays pass through (`shadow_transparent`): objects hidden from shadow rays
    (`ObjectInfo.casts_shadow`) and materials Cycles makes transparent to them
    (`Material.shadow_transparent`, a Light Path > Is Shadow Ray mix)."""

    def __init__(self, geometry: Geometry, materials: list[Material], objects=None):
        unshadowing = [i for i, m in enumerate(materials) if getattr(m, "shadow_transparent", False)]
        passed = [i for i, o in enumerate(objects or ()) if not getattr(o, "casts_shadow", True)]
        skip = np.zeros(geometry.triangle_count, bool)
        if unshadowing:
            skip |= np.isin(np.asarray(geometry.material_index), unshadowing)
        if passed:
            skip |= np.isin(np.asarray(geometry.object_index), passed)
        self._shadow_skip = skip if skip.any() else None
        # Clear materials (`Material.clear`: clear glass, Transparent BSDF) are a hole everywhere.
        clear = [i for i, m in enumerate(materials) if getattr(m, "clear", False)]
        cut = [i for i, m in enumerate(materials) if m.alpha is not None and i not in clear]
        self._alpha = {i: np.asarray(materials[i].alpha, np.float32) for i in cut}
        self._material = np.asarray(geometry.material_index, np.int32)
        self._has = np.isin(self._material, cut) if cut else np.zeros(geometry.triangle_count, bool)
        uvs = np.asarray(geometry.uvs, np.float32)
        self._corner_uv = uvs[geometry.triangles] if self._has.any() else None  # (T, 3, 2)
        if self._corner_uv is not None:
            # Triangles without a usable UV (NaN) stay solid.
            self._has &= np.isfinite(self._corner_uv).all(axis=(1, 2))
        self._clear = np.isin(self._material, clear) if clear else None
        glass = [i for i in clear if getattr(materials[i], "refractive", False)]
        self._glass = np.isin(self._material, glass) if glass else None

    @property
    def any(self) -> bool:
        return bool(self._has.any()) or self._clear is not None

    @property
    def shadow_any(self) -> bool:
        """Whether any triangle lets shadow rays through."""
        return self._shadow_skip is not None

    @property
    def glass_any(self) -> bool:
        """Whether any clear triangle is refractive glass (`Material.refractive`)."""
        return self._glass is not None

    def shadow_passes_glass(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(n,) bool: a shadow ray of a lamp that glass stops passes the hit: a hole or a triangle
        shadow rays pass (`shadow_transparent`), but not refractive glass. Cycles' shadow rays stop
        at glass closures, and the light it refracts reaches a diffuse surface only along caustic
        paths: a sun through a glazed window leaves no sunlit patch at 1024 spp, clamped or not."""
        passes = self.transparent(prim, u, v)
        if self._glass is not None:
            passes &= ~((prim >= 0) & self._glass[np.maximum(prim, 0)])
        return passes | self.shadow_transparent(prim)

    def shadow_transparent(self, prim: np.ndarray) -> np.ndarray:
        """(n,) bool: the hit triangle lets shadow rays through (prim -1: False)."""
        if self._shadow_skip is None:
            return np.zeros(prim.shape[0], bool)
        return (prim >= 0) & self._shadow_skip[np.maximum(prim, 0)]

    def transparent(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """(n,) bool: the hit (triangle prim, Embree barycentrics u, v) lies in a hole."""
        out = np.zeros(prim.shape[0], bool)
        if not self.any:
            return out
        hit = prim >= 0
        if self._clear is not None:
            out[hit] = self._clear[prim[hit]]
        rows = np.flatnonzero(hit)
        rows = rows[self._has[prim[rows]]]
        if rows.size == 0:
            return out
        tri = prim[rows]
        c = self._corner_uv[tri]
        uu, vv = u[rows, None], v[rows, None]
        uv = (1.0 - uu - vv) * c[:, 0] + uu * c[:, 1] + vv * c[:, 2]
        mats = self._material[tri]
        for m, alpha in self._alpha.items():
            sel = mats == m
            if not sel.any():
                continue
            h, w = alpha.shape
            # Bilinear, repeating, texel centres at (i + 0.5) / size: as the G-buffer samples it.
            st = uv[sel] * np.array([w, h], np.float32) - 0.5
            f = np.floor(st)
            t = st - f
            x0 = f[:, 0].astype(np.int64) % w
            y0 = f[:, 1].astype(np.int64) % h
            x1, y1 = (x0 + 1) % w, (y0 + 1) % h
            a = (alpha[y0, x0] * (1 - t[:, 0]) + alpha[y0, x1] * t[:, 0]) * (1 - t[:, 1]) \
                + (alpha[y1, x0] * (1 - t[:, 0]) + alpha[y1, x1] * t[:, 0]) * t[:, 1]
            out[rows[sel]] = a < ALPHA_CUTOFF
        return out
