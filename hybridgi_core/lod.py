"""Level of detail for the ray mesh: quadric decimation per (object, material) group.

Probe rays only need coarse occlusion and a mean albedo, so the traced mesh may hold far fewer
triangles than the rasterized one. Decimating each (object, material) group on its own keeps
object and material ids exact; borders are preserved so groups stay sealed against each other
(an open seam would leak light through a wall).
"""

from __future__ import annotations

import logging
import threading

import fast_simplification
import numpy as np

from .errors import SettingsError
from .snapshot import Geometry, concat_geometry

log = logging.getLogger(__name__)

#: Groups with fewer triangles are kept whole: decimating them saves little and ruins their shape.
MIN_DECIMATE_TRIANGLES = 32
#: A decimated group keeps at least this many triangles (a closed tetrahedron).
MIN_GROUP_TARGET = 4
#: fast_simplification's aggressiveness (its default): higher is faster but coarser.
AGGRESSIVENESS = 7.0

# fast_simplification keeps the mesh being simplified in module-global C++ state.
_SIMPLIFY_LOCK = threading.Lock()


def decimate(geometry: Geometry, ratio: float) -> Geometry:
    """Reduce the triangle count to about `ratio` times the input, per (object, material) group.

    Parameters
    ----------
    geometry : Geometry to simplify (not modified)
    ratio : share of triangles to keep, in (0, 1]; 1 returns `geometry` itself

    Returns
    -------
    Geometry whose decimated groups are unindexed (three vertices per triangle) with flat normals
    and NaN uvs (shading then uses the material's mean albedo); groups smaller than
    MIN_DECIMATE_TRIANGLES are copied unchanged. A group's count can stay above its target where
    its preserved border holds most of its triangles.
    """
    if not 0.0 < ratio <= 1.0:  # written this way so NaN fails too
        raise SettingsError(f"lod ratio must be in (0, 1], got {ratio!r}")
    if ratio == 1.0 or geometry.triangle_count == 0:
        return geometry

    keys = (geometry.object_index.astype(np.int64) << 32) | geometry.material_index.astype(np.int64)
    _, group_of, counts = np.unique(keys, return_inverse=True, return_counts=True)
    order = np.argsort(group_of, kind="stable")
    parts: list[Geometry] = []
    kept_whole = 0
    for tri_ids in np.split(order, np.cumsum(counts)[:-1]):
        mask = np.zeros(geometry.triangle_count, bool)
        mask[tri_ids] = True
        group = geometry.subset(mask)
        target = max(MIN_GROUP_TARGET, int(round(ratio * group.triangle_count)))
        simplified = None
        if group.triangle_count >= MIN_DECIMATE_TRIANGLES and target < group.triangle_count:
            simplified = _decimate_group(group, target)
        if simplified is None:
            kept_whole += 1
            parts.append(group)
        else:
            parts.append(simplified)
    out = concat_geometry(parts)
    log.info(
        "ray mesh LOD: %d -> %d triangles (ratio %.3g, %d groups, %d kept whole)",
        geometry.triangle_count, out.triangle_count, ratio, len(parts), kept_whole,
    )
    return out


def _decimate_group(group: Geometry, target: int) -> Geometry | None:
    """Simplify one group (single object and material id) to about `target` triangles.

    Returns None when the simplifier leaves nothing usable, so the caller keeps the group whole.
    """
    # Corners are split wherever normals or uvs differ; weld by position or every edge is a border.
    points, inverse = _weld(group.positions)
    triangles = inverse[group.triangles].astype(np.int32)
    with _SIMPLIFY_LOCK:
        new_points, faces = fast_simplification.simplify(
            points.astype(np.float64), triangles, target_count=target, agg=AGGRESSIVENESS, preserve_border=True
        )
    corners = new_points[np.asarray(faces, np.int64).reshape(-1, 3)]
    cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    extent = max(float(np.abs(points).max()), 1.0)
    # The same zero-area test as snapshot.sanitized, so nothing degenerate reaches Embree.
    keep = np.linalg.norm(cross, axis=1) > 1e-12 * extent**2
    corners = corners[keep]
    n = corners.shape[0]
    if n == 0:
        log.warning("decimating a %d-triangle group left no triangles; keeping it whole", group.triangle_count)
        return None
    normals = cross[keep] / np.linalg.norm(cross[keep], axis=1, keepdims=True)
    return Geometry(
        positions=corners.reshape(-1, 3).astype(np.float32),
        triangles=np.arange(3 * n, dtype=np.int32).reshape(-1, 3),
        normals=np.repeat(normals, 3, axis=0).astype(np.float32),
        uvs=np.full((3 * n, 2), np.nan, np.float32),
        material_index=np.full(n, group.material_index[0], np.int32),
        object_index=np.full(n, group.object_index[0], np.int32),
    )


def _weld(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge bit-identical positions.

    positions : (V, 3) float32. Returns (U, 3) float32 unique points and (V,) int64 indices into them.
    """
    # np.unique(axis=0) sorts rows as opaque bytes, ~10x slower than lexsort on the columns.
    p = positions + np.float32(0.0)  # -0.0 -> 0.0, so the two zeros weld
    order = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))
    ordered = p[order]
    first = np.ones(len(p), bool)
    first[1:] = (ordered[1:] != ordered[:-1]).any(axis=1)
    inverse = np.empty(len(p), np.int64)
    inverse[order] = np.cumsum(first) - 1
    return ordered[first], inverse
