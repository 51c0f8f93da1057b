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

    def __init__(self, geometry: Geometry, materials: list[Material], objects=None,
                 glass: tuple[float, float] = (1.0, 1.0)):
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
        # Surfaces seen with a chance (`Material.coverage`): per triangle, 1 elsewhere.
        cover = np.array([1.0 if i in clear else float(getattr(m, "coverage", 1.0)) for i, m in enumerate(materials)]
                         + [1.0], np.float32)
        self._cover = cover[self._material] if (cover < 1.0).any() else None
        refractive = [i for i in clear if getattr(materials[i], "refractive", False)]
        self._glass = np.isin(self._material, refractive) if refractive else None
        # Rays crossing glass (`glass_transmission`): (entering, leaving) share that passes.
        self._glass_pass = tuple(float(np.clip(t, 0.0, 1.0)) for t in glass)
        self._glass_normal = None
        if self._glass is not None and min(self._glass_pass) < 1.0:
            corners = np.asarray(geometry.positions, np.float32)[np.asarray(geometry.triangles)]
            self._glass_normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])

    @property
    def any(self) -> bool:
        return bool(self._has.any()) or self._clear is not None or self._cover is not None

    @property
    def shadow_any(self) -> bool:
        """Whether any triangle lets shadow rays through."""
        return self._shadow_skip is not None

    @property
    def glass_any(self) -> bool:
        """Whether any clear triangle is refractive glass (`Material.refractive`)."""
        return self._glass is not None

    def _thin_glass(self, out: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
                    directions: np.ndarray) -> None:
        """Stop, in `out`, the rays whose glass crossing the hash draws as not passing."""
        rows = np.flatnonzero((prim >= 0) & self._glass[np.maximum(prim, 0)])
        if rows.size == 0:
            return
        d = np.broadcast_to(directions, (prim.shape[0], 3))[rows]
        leaving = np.einsum("ij,ij->i", self._glass_normal[prim[rows]], d) > 0
        share = np.where(leaving, np.float32(self._glass_pass[1]), np.float32(self._glass_pass[0]))
        out[rows] = _hash01(prim[rows], u[rows], v[rows]) < share

    def _uncovered(self, out: np.ndarray, prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> None:
        """Pass, in `out`, the hits on surfaces seen with a chance (`Material.coverage`) that the
        hash of the hit draws as not seen: a point of the surface is seen by every ray or by
        none, and its share of seen points is the coverage."""
        rows = np.flatnonzero(prim >= 0)
        cover = self._cover[prim[rows]]
        rows, cover = rows[cover < 1.0], cover[cover < 1.0]
        if rows.size:
            out[rows] |= _hash01(prim[rows], u[rows], v[rows]) >= cover

    def shadow_passes_glass(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
                            directions: np.ndarray | None = None) -> np.ndarray:
        """(n,) bool: a shadow ray of a lamp that glass stops passes the hit: where a camera ray
        passes (`camera_passes`: a hole, not refractive glass) or on a triangle shadow rays pass
        (`shadow_transparent`). Cycles' shadow rays stop
        at glass closures, and the light it refracts reaches a diffuse surface only along caustic
        paths: a sun through a glazed window leaves no sunlit patch at 1024 spp, clamped or not."""
        return self.camera_passes(prim, u, v) | self.shadow_transparent(prim)

    def camera_passes(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray, directions=None) -> np.ndarray:
        """(n,) bool: a camera ray passes the hit: a hole or clear surface, but not refractive glass,
        which the camera's refraction paths stop at (`refraction.py`)."""
        passes = self.transparent(prim, u, v)
        if self._glass is not None:
            passes &= ~((prim >= 0) & self._glass[np.maximum(prim, 0)])
        return passes

    def shadow_transparent(self, prim: np.ndarray) -> np.ndarray:
        """(n,) bool: the hit triangle lets shadow rays through (prim -1: False)."""
        if self._shadow_skip is None:
            return np.zeros(prim.shape[0], bool)
        return (prim >= 0) & self._shadow_skip[np.maximum(prim, 0)]

    def transparent(self, prim: np.ndarray, u: np.ndarray, v: np.ndarray,
                    directions: np.ndarray | None = None) -> np.ndarray:
        """(n,) bool: the hit (triangle prim, Embree barycentrics u, v) lies in a hole. With the
        rays' `directions`, a ray crossing refractive glass passes with the probability of
        `glass_transmission` (leaving it through a face turned its way, else entering), drawn by
        a hash of the hit: it stops there otherwise, on a surface that reflects nothing."""
        out = np.zeros(prim.shape[0], bool)
        if not self.any:
            return out
        hit = prim >= 0
        if self._clear is not None:
            out[hit] = self._clear[prim[hit]]
            if self._glass_normal is not None and directions is not None:
                self._thin_glass(out, prim, u, v, np.asarray(directions, np.float32).reshape(-1, 3))
        if self._cover is not None:
            self._uncovered(out, prim, u, v)
        rows = np.flatnonzero(hit)
        rows = rows[self._has[prim[rows]]]
        if rows.size == 0:
            return out
        tri = prim[rows]
        c = np.take(self._corner_uv, tri, axis=0)  # (k, 3, 2); take: a gather of whole rows
        uu, vv = u[rows, None], v[rows, None]
        uv = (1.0 - uu - vv) * c[:, 0] + uu * c[:, 1] + vv * c[:, 2]
        mats = np.take(self._material, tri) if len(self._alpha) > 1 else None
        for m, alpha in self._alpha.items():
            sel = slice(None) if mats is None else np.flatnonzero(mats == m)
            if mats is not None and sel.size == 0:
                continue
            out[rows[sel]] = _bilinear(alpha, uv[sel]) < ALPHA_CUTOFF
        return out


def _bilinear(alpha: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """(k,) float32 of texture `alpha` (h, w) at `uv` (k, 2): bilinear, repeating, texel centres
    at (i + 0.5) / size, as the G-buffer samples it; flat gathers (np.take), float32 (the rays'
    holes took 1.6 s of CPU under a tree of 3000 alpha-cut leaves with 2-D fancy indexing)."""
    h, w = alpha.shape
    flat = alpha.reshape(-1)
    s = uv[:, 0] * np.float32(w) - np.float32(0.5)
    t = uv[:, 1] * np.float32(h) - np.float32(0.5)
    fs, ft = np.floor(s), np.floor(t)
    ds, dt = s - fs, t - ft
    x0 = fs.astype(np.int64) % w
    y0 = ft.astype(np.int64) % h
    x1 = x0 + 1
    x1[x1 == w] = 0
    row0 = y0 * w
    row1 = np.where(y0 + 1 == h, 0, row0 + w)
    top = np.take(flat, row0 + x0) * (1 - ds) + np.take(flat, row0 + x1) * ds
    bottom = np.take(flat, row1 + x0) * (1 - ds) + np.take(flat, row1 + x1) * ds
    return top * (1 - dt) + bottom * dt


#: Share of the light Cycles lets through refractive glass, (entering, leaving) its volume, under
#: its Filter Glossy off and at its default 1 (`glass_transmission`). Measured: a room lit by a
#: uniform sky through a 2 cm Glass BSDF slab, its floor and a monkey against the open room,
#: 256 spp: 0.51-0.57 at Filter Glossy 1 (0.41-0.46 with a Principled BSDF's transmission),
#: 0.96-1.02 at 0; a single-plane pane 0.92-0.95 (one crossing). The blur makes the glass rough
#: for rays after a diffuse bounce, and a rough slab sends much of it back or along.
GLASS_SMOOTH = (0.95, 0.97)
GLASS_BLURRED = (0.95, 0.56)


def glass_transmission(filter_glossy: float) -> tuple[float, float]:
    """(entering, leaving) share of rays that cross refractive glass at Cycles' Filter Glossy
    (`CacheSettings.filter_glossy`): measured at 0 and 1, linear between, the blurred values
    beyond 1."""
    t = float(np.clip(filter_glossy, 0.0, 1.0)) if np.isfinite(filter_glossy) else 1.0
    return tuple(a + t * (b - a) for a, b in zip(GLASS_SMOOTH, GLASS_BLURRED, strict=True))


def _hash01(prim: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n,) float32 in [0, 1): a hash of hits (triangle, barycentrics), the same for the same hit."""
    h = np.asarray(prim, np.int64).astype(np.uint32) * np.uint32(0x9E3779B1)
    h ^= np.ascontiguousarray(u, np.float32).view(np.uint32) * np.uint32(0x85EBCA77)
    h ^= np.ascontiguousarray(v, np.float32).view(np.uint32) * np.uint32(0xC2B2AE3D)
    h ^= h >> np.uint32(16)
    h *= np.uint32(0x7FEB352D)
    h ^= h >> np.uint32(15)
    h *= np.uint32(0x846CA68B)
    h ^= h >> np.uint32(16)
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))
