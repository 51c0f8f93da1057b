"""Brute-force numpy ray tracer: the reference the Embree backend is tested against.

Every ray is tested against every triangle (Möller–Trumbore, float64, both faces), so it is only
meant for small scenes (up to a few thousand triangles) and for tests.
"""

from __future__ import annotations

import logging

import numpy as np

from ..errors import EmptySceneError
from ..snapshot import Geometry
from . import Hits

log = logging.getLogger(__name__)

#: Upper bound on ray x triangle pairs held at once; each pair costs ~100 bytes of temporaries.
PAIR_BUDGET = 1 << 19


def prepare_rays(
    origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Validate ray arrays and mark rays that cannot hit anything.

    Parameters
    ----------
    origins : (n, 3) array-like, any float dtype
    directions : (n, 3), or (1, 3) for one direction shared by every ray
    tfar : scalar or (n,) array-like, maximum hit distance

    Returns
    -------
    origins, directions : (n, 3) arrays as given (not copied, never to be mutated; a shared
        direction comes back as a read-only broadcast view)
    tfar : (n,) float32, a fresh array the caller may overwrite
    valid : (n,) bool, false for non-finite origins, zero / non-finite directions and NaN or
        negative tfar; such rays are reported as misses by both backends
    """
    origins = np.asarray(origins)
    directions = np.asarray(directions)
    if directions.shape == (1, 3) and origins.ndim == 2:
        directions = np.broadcast_to(directions, origins.shape)
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both be (n, 3), got {origins.shape} and {directions.shape}")
    n = origins.shape[0]
    tfar_arr = np.asarray(tfar, np.float32)
    if tfar_arr.ndim > 1 or (tfar_arr.ndim == 1 and tfar_arr.shape[0] != n):
        raise ValueError(f"tfar must be a scalar or ({n},), got {tfar_arr.shape}")
    tfar_out = np.empty(n, np.float32)
    tfar_out[:] = tfar_arr
    with np.errstate(invalid="ignore", over="ignore"):
        dd = np.einsum("ij,ij->i", directions, directions)
        if n and _bounded(origins) and _bounded(directions):
            # Every component finite and far from overflow (NaN fails the comparisons): the
            # per-ray test below would pass every ray, so only zero directions remain.
            valid = dd > 0.0
        else:
            # Row sums propagate NaN/inf, so one finiteness test per ray covers all six components
            # (a sum that overflows a finite ray to inf marks it invalid too: far beyond any scene).
            finite = np.isfinite(np.einsum("ij->i", origins) + np.einsum("ij->i", directions))
            valid = finite & (dd > 0.0)
        valid &= (tfar_out >= 0.0) if tfar_arr.ndim else bool(tfar_arr >= 0.0)
    return origins, directions, tfar_out, valid


#: Components below this magnitude cannot overflow a row sum of three (float32 max ~3.4e38).
_SAFE_COMPONENT = 1e37


def _bounded(a: np.ndarray) -> bool:
    """All components of a within +-_SAFE_COMPONENT (false for NaN): two fast whole-array passes."""
    return bool(a.max() < _SAFE_COMPONENT) and bool(a.min() > -_SAFE_COMPONENT)


class NumpyTracer:
    """Closest-hit and occlusion queries by testing every ray against every triangle.

    Implements the `Tracer` protocol. Hits count for 0 < t <= tfar, like Embree with tnear = 0.
    """

    def __init__(self, geometry: Geometry) -> None:
        if geometry.triangle_count == 0:
            raise EmptySceneError("the scene has no triangles to trace")
        self.geometry = geometry
        p = geometry.positions[geometry.triangles].astype(np.float64)
        # Component-wise (3, T) arrays: broadcasting against (c, 1) ray components keeps every
        # temporary (c, T) instead of (c, T, 3).
        self._v0 = np.ascontiguousarray(p[:, 0].T)
        self._e1 = np.ascontiguousarray((p[:, 1] - p[:, 0]).T)
        self._e2 = np.ascontiguousarray((p[:, 2] - p[:, 0]).T)
        self._chunk = max(1, PAIR_BUDGET // geometry.triangle_count)

    def intersect(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False
    ) -> Hits:
        """Closest hit of each ray.

        origins : (n, 3) float32; directions : (n, 3) or (1, 3); tfar : scalar or (n,). Returns
        `Hits` of length n. The reference always checks its rays: `trusted` is accepted and ignored.
        """
        origins, directions, tfar, valid = prepare_rays(origins, directions, tfar)
        n = origins.shape[0]
        t_out = np.full(n, np.inf, np.float32)
        prim_out = np.full(n, -1, np.int32)
        u_out = np.zeros(n, np.float32)
        v_out = np.zeros(n, np.float32)
        idx = np.flatnonzero(valid)
        for start in range(0, idx.size, self._chunk):
            rays = idx[start:start + self._chunk]
            t, prim, u, v = self._closest(
                origins[rays].astype(np.float64), directions[rays].astype(np.float64), tfar[rays].astype(np.float64)
            )
            t_out[rays], prim_out[rays], u_out[rays], v_out[rays] = t, prim, u, v
        return Hits(t_out, prim_out, u_out, v_out)

    def occluded(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False
    ) -> np.ndarray:
        """(n,) bool: some triangle lies on the ray at 0 < t <= tfar."""
        return self.intersect(origins, directions, tfar).hit

    def _closest(
        self, o: np.ndarray, d: np.ndarray, tfar: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Möller–Trumbore against all triangles. o, d : (c, 3) float64; tfar : (c,) float64."""
        e1x, e1y, e1z = (c[None, :] for c in self._e1)
        e2x, e2y, e2z = (c[None, :] for c in self._e2)
        dx, dy, dz = (c[:, None] for c in d.T)
        px = dy * e2z - dz * e2y
        py = dz * e2x - dx * e2z
        pz = dx * e2y - dy * e2x
        det = e1x * px + e1y * py + e1z * pz
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / det
            tx = o[:, 0:1] - self._v0[0][None, :]
            ty = o[:, 1:2] - self._v0[1][None, :]
            tz = o[:, 2:3] - self._v0[2][None, :]
            u = (tx * px + ty * py + tz * pz) * inv
            del px, py, pz
            qx = ty * e1z - tz * e1y
            qy = tz * e1x - tx * e1z
            qz = tx * e1y - ty * e1x
            del tx, ty, tz
            v = (dx * qx + dy * qy + dz * qz) * inv
            t = (e2x * qx + e2y * qy + e2z * qz) * inv
            # det == 0 (ray parallel to the plane) gives inf/NaN, which every comparison rejects.
            ok = (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0) & (t > 0.0) & (t <= tfar[:, None])
        t = np.where(ok, t, np.inf)
        best = np.argmin(t, axis=1)
        rows = np.arange(t.shape[0])
        t_best = t[rows, best]
        hit = np.isfinite(t_best)
        prim = np.where(hit, best, -1).astype(np.int32)
        u_best = np.where(hit, u[rows, best], 0.0)
        v_best = np.where(hit, v[rows, best], 0.0)
        return t_best.astype(np.float32), prim, u_best.astype(np.float32), v_best.astype(np.float32)
