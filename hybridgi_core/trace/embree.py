"""Embree ray tracer (embreex): a static scene built once plus a small per-frame dynamic scene.

Triangles of objects that move over the animation go into the dynamic scene, which
`update_dynamic` rebuilds from the current vertex positions; everything else is built once.
Queries run both scenes and keep the nearest hit, so `Hits.prim` always indexes the full Geometry.

Threads: embreex releases the GIL inside `run()`, so big batches are split over a thread pool
owned by the tracer. Worker threads touch numpy and embreex only.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np
from embreex import rtcore as rtc
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh

from ..errors import EmptySceneError, InvalidGeometryError, SettingsError
from ..rows import column_bounds
from ..snapshot import Geometry
from . import SURFACE_EPSILON, Hits, embree_upload
from .reference import prepare_rays

log = logging.getLogger(__name__)

#: Fewest rays one worker task gets: below this the pool's overhead outweighs the parallelism.
MIN_CHUNK_RAYS = 8192
#: Tasks per worker thread for a large batch, so a thread that drew cheap rays picks up more work.
CHUNKS_PER_THREAD = 4
#: Robust mode makes Embree's triangle test watertight. Without it, rays from inside a closed box
#: aimed at its edges and diagonals escape (0.2-1.6% of such rays, measured): light leaks in GI.
ROBUST = True


#: Least push of a ray origin off its surface, in float32 steps of the scene's largest coordinate.
ORIGIN_ULPS = 8

#: Cut-out layers a ray passes through before it counts as stopped (foliage: a handful).
CUTOUT_LAYERS = 8


@dataclass
class _SubScene:
    """One committed Embree scene over a subset of the Geometry's triangles.

    ids : (k,) int32, global triangle index of each Embree primID
    vertex_ids : (m,) int64, the Geometry vertices the subset uses (compacted)
    local_triangles : (k, 3) int32, triangles indexing vertex_ids
    vertices : (m, 3) float32, the positions Embree was given, kept alive beside the scene
    """

    scene: rtcs.EmbreeScene
    mesh: TriangleMesh | None  # None: uploaded through Embree's C API (`embree_upload`)
    ids: np.ndarray
    vertex_ids: np.ndarray
    local_triangles: np.ndarray
    vertices: np.ndarray
    identity: bool = False  # ids == arange(k): primIDs are already global ids


def _rows(a: np.ndarray, sl: slice) -> np.ndarray:
    """a[sl], except that a single row (one direction for every ray) is shared by every slice."""
    return a if a.shape[0] == 1 else a[sl]


class EmbreeTracer:
    """Closest-hit and occlusion queries on Embree, with a rebuildable dynamic part.

    Implements the `Tracer` protocol. Hits count for 0 < t <= tfar (Embree's tnear is 0: offset
    origins off surfaces by `epsilon`). Rays with NaN origins or NaN/zero directions miss.

    Parameters
    ----------
    geometry : Geometry with at least one triangle
    dynamic_objects : object indices whose triangles go into the dynamic scene
    threads : worker threads for large batches (1 = trace on the calling thread)
    """

    def __init__(self, geometry: Geometry, dynamic_objects: frozenset[int] = frozenset(), threads: int = 2) -> None:
        if geometry.triangle_count == 0:
            raise EmptySceneError("the scene has no triangles to trace")
        if not 1 <= threads <= 64:
            raise SettingsError(f"threads must be 1..64, got {threads}")
        self.geometry = geometry
        self._cutouts = None  # see set_cutouts
        self._shadow_skip = None
        self.dynamic_objects = frozenset(int(i) for i in dynamic_objects)
        self.threads = int(threads)
        self._device = rtc.EmbreeDevice()
        dyn_mask = np.isin(geometry.object_index, np.fromiter(self.dynamic_objects, np.int64))
        start = time.perf_counter()
        self._static = self._build(geometry, np.flatnonzero(~dyn_mask).astype(np.int32), weld=True)
        self._dynamic = self._build(geometry, np.flatnonzero(dyn_mask).astype(np.int32))
        self._static_bounds = self._bounds(self._static)
        self._set_extent()
        self._pool = (
            ThreadPoolExecutor(self.threads, thread_name_prefix="hybridgi-embree") if self.threads > 1 else None
        )
        log.info(
            "embree scenes built in %.1f ms: %d static, %d dynamic triangles, extent %.4g",
            1e3 * (time.perf_counter() - start), self._count(self._static), self._count(self._dynamic), self.extent,
        )

    # -- lifecycle ----------------------------------------------------------------------------

    def close(self) -> None:
        """Stop the worker threads. Later queries still work, on the calling thread."""
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None

    def __enter__(self) -> EmbreeTracer:
        return self

    def __exit__(self, *exc_info) -> None:
        self.close()

    def update_dynamic(self, geometry: Geometry) -> None:
        """Rebuild the dynamic scene from `geometry`'s current vertex positions.

        geometry : the full current Geometry, with the triangles, vertex layout and object ids given
        at construction; only the dynamic triangles' positions are read. The static scene is kept.
        Call it between query batches: a query already running finishes on the old frame, but
        `self.geometry` (where its prims are looked up) switches at once.
        """
        if (
            geometry.triangle_count != self.geometry.triangle_count
            or geometry.positions.shape != self.geometry.positions.shape
            or not np.array_equal(geometry.object_index, self.geometry.object_index)
        ):
            raise InvalidGeometryError(
                "update_dynamic needs the construction's topology "
                f"({self.geometry.triangle_count} triangles and {self.geometry.positions.shape[0]} vertices, got "
                f"{geometry.triangle_count} and {geometry.positions.shape[0]}); rebuild the tracer"
            )
        old = self._dynamic
        self.geometry = geometry
        if old is None:
            return
        vertices = np.ascontiguousarray(geometry.positions[old.vertex_ids], np.float32)
        # A new scene is swapped in whole, so a query running on another thread sees either frame.
        self._dynamic = self._commit(old.ids, old.vertex_ids, old.local_triangles, vertices)
        self._set_extent()

    # -- queries ------------------------------------------------------------------------------

    def set_cutouts(self, cutouts) -> None:
        """Rays pass through the holes `cutouts.transparent(prim, u, v)` reports (a `cutout.Cutouts`
        or None): `intersect` continues them past such hits and `occluded` ignores them; shadow
        rays (`occluded_shadow`) pass its `shadow_transparent` triangles too."""
        self._cutouts = cutouts if cutouts is not None and cutouts.any else None
        self._shadow_skip = cutouts if cutouts is not None and cutouts.shadow_any else None
        self._glass = cutouts if cutouts is not None and cutouts.glass_any else None

    @property
    def has_shadow_skips(self) -> bool:
        """Whether shadow rays pass some triangles (`set_cutouts`): `lights.shadow_query`."""
        return self._shadow_skip is not None

    @property
    def has_glass(self) -> bool:
        """Whether some clear triangles are refractive glass (`cutout.Cutouts.glass_any`)."""
        return self._glass is not None

    def occluded_shadow(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False,
        glass: bool = False,
    ) -> np.ndarray:
        """`occluded` for shadow rays: objects hidden from shadow rays and materials transparent
        to them (`set_cutouts`) do not block (closest hits, continued past them); with `glass`,
        refractive clear triangles do (`cutout.Cutouts.shadow_passes_glass`)."""
        rules = self._glass if glass else None
        if rules is not None:
            hits = self._intersect_once(origins, directions, tfar, trusted)
            passed = self._continue_past(origins, directions, tfar, hits, rules.shadow_passes_glass,
                                         self._intersect_once, layers=2 * CUTOUT_LAYERS)
            return passed.prim >= 0
        skip = self._shadow_skip
        if skip is None:
            return self.occluded(origins, directions, tfar, trusted)
        hits = self.intersect(origins, directions, tfar, trusted)
        passed = self._continue_past(origins, directions, tfar, hits,
                                     lambda prim, _u, _v, _d: skip.shadow_transparent(prim), self.intersect)
        return passed.prim >= 0

    def intersect(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False
    ) -> Hits:
        """Closest hit of each ray over both scenes, through alpha cutouts (`set_cutouts`).

        origins : (n, 3) float (cast to float32); directions : (n, 3) or (1, 3); tfar : scalar or
        (n,); trusted : see `Tracer`. Returns `Hits` of length n; prim indexes `self.geometry`.
        """
        hits = self._intersect_once(origins, directions, tfar, trusted)
        cutouts = self._cutouts
        if cutouts is None:
            return hits
        return self._continue_past(origins, directions, tfar, hits, cutouts.transparent, self._intersect_once)

    def intersect_glass(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False
    ) -> Hits:
        """`intersect`, except that refractive glass stops the rays (other holes and clear
        surfaces pass): the camera's refraction paths (`refraction.py`)."""
        rules = self._glass
        if rules is None:
            return self.intersect(origins, directions, tfar, trusted)
        hits = self._intersect_once(origins, directions, tfar, trusted)
        return self._continue_past(origins, directions, tfar, hits, rules.camera_passes, self._intersect_once)

    def _continue_past(self, origins, directions, tfar, hits: Hits, passes, trace, layers: int = CUTOUT_LAYERS) -> Hits:
        """`hits` with the rays whose hit `passes(prim, u, v)` marks (an alpha cutout's hole, a
        triangle shadow rays pass) continued just beyond it by `trace` (an intersect), at most
        `layers` times; a ray that leaves its reach misses (t inf, prim -1). `passes` takes the
        hits' prim, u, v and the rays' directions."""
        o = np.asarray(origins, np.float32).reshape(-1, 3)
        d = np.broadcast_to(np.asarray(directions, np.float32).reshape(-1, 3), o.shape)
        limit = np.broadcast_to(np.asarray(tfar, np.float32), (o.shape[0],))
        t, prim, u, v = hits.t.copy(), hits.prim.copy(), hits.u.copy(), hits.v.copy()
        eps = np.float32(self.epsilon)
        for _layer in range(layers):
            through = np.flatnonzero(passes(prim, u, v, d))
            if through.size == 0:
                break
            start = t[through] + eps
            again = trace(o[through] + d[through] * start[:, None], d[through],
                          np.maximum(limit[through] - start, 0.0), True)
            t[through] = np.where(again.prim >= 0, start + again.t, np.float32(np.inf))
            prim[through], u[through], v[through] = again.prim, again.u, again.v
        return Hits(t, prim, u, v)

    def _intersect_once(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False
    ) -> Hits:
        """The closest hit over both scenes, holes included."""
        o, d, tf, valid = self._embree_rays(origins, directions, tfar, trusted)
        n = o.shape[0]
        scenes = [s for s in (self._static, self._dynamic) if s is not None]
        if len(scenes) == 1 and scenes[0].identity and not self._parallel(n):
            # One call on one scene whose primIDs are the global ids: its arrays are the answer.
            res = scenes[0].scene.run(o, d, dists=tf, query="INTERSECT", output=1)
            prim = res["primID"]
            if valid is not None:
                prim[~valid] = -1
            return Hits(np.where(prim >= 0, res["tfar"], np.float32(np.inf)), prim, res["u"], res["v"])
        prim = np.full(n, -1, np.int32)
        u = np.zeros(n, np.float32)
        v = np.zeros(n, np.float32)

        def work(sl: slice) -> None:
            if len(scenes) == 1 and scenes[0].identity:
                # One scene whose primIDs are the global ids: copy its answers straight out.
                res = scenes[0].scene.run(o[sl], _rows(d, sl), dists=tf[sl], query="INTERSECT", output=1)
                hit = res["primID"] >= 0
                prim[sl] = res["primID"]
                if not np.shares_memory(res["tfar"], tf):
                    tf[sl] = res["tfar"]
                np.copyto(u[sl], res["u"], where=hit)
                np.copyto(v[sl], res["v"], where=hit)
                return
            for sub in scenes:
                res = sub.scene.run(o[sl], _rows(d, sl), dists=tf[sl], query="INTERSECT", output=1)
                hit = res["primID"] >= 0
                # tf now holds the nearest t so far: the next scene only looks for nearer hits.
                tf[sl] = res["tfar"]
                prim[sl][hit] = sub.ids[res["primID"][hit]]
                u[sl][hit] = res["u"][hit]
                v[sl][hit] = res["v"][hit]

        self._for_chunks(n, work)
        if valid is not None:
            prim[~valid] = -1
        t = np.where(prim >= 0, tf, np.float32(np.inf))
        return Hits(t, prim, u, v)

    def occluded(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = np.inf, trusted: bool = False
    ) -> np.ndarray:
        """(n,) bool: a triangle of either scene lies on the ray at 0 < t <= tfar.

        directions : (n, 3) or (1, 3); trusted : see `Tracer`. Through alpha cutouts, a ray is
        occluded only by a solid part: it is found as the closest hit (slower than Embree's any-hit
        query, so only for scenes that have cutouts, and only for the rays the any-hit query finds
        blocked by anything: a sunlit ground's shadow rays under a tree of alpha-cut leaves)."""
        blocked = self._occluded_any(origins, directions, tfar, trusted)
        if self._cutouts is None:
            return blocked
        rows = np.flatnonzero(blocked)
        if rows.size:
            o = np.asarray(origins, np.float32).reshape(-1, 3)[rows]
            d = np.asarray(directions, np.float32).reshape(-1, 3)
            d = d if d.shape[0] == 1 else d[rows]
            far = np.asarray(tfar, np.float32)
            far = far if far.ndim == 0 else far.reshape(-1)[rows]
            blocked[rows] = self.intersect(o, d, far, trusted).prim >= 0
        return blocked

    def _occluded_any(self, origins, directions, tfar, trusted) -> np.ndarray:
        """(n,) bool: any triangle of either scene, holes included, lies on the ray at 0 < t <= tfar."""
        o, d, tf, valid = self._embree_rays(origins, directions, tfar, trusted)
        n = o.shape[0]
        scenes = [s for s in (self._static, self._dynamic) if s is not None]
        out = np.zeros(n, bool)

        def work(sl: slice) -> None:
            for sub in scenes:
                out[sl] |= sub.scene.run(o[sl], _rows(d, sl), dists=tf[sl], query="OCCLUDED") >= 0

        self._for_chunks(n, work)
        # embreex reports a ray Embree skipped (tfar < tnear) as occluded: mask those out here.
        return out if valid is None else out & valid

    @property
    def epsilon(self) -> float:
        """Distance (metres) to push ray origins off a surface before tracing: SURFACE_EPSILON of
        the scene's size, and at least ORIGIN_ULPS float32 steps of its largest coordinate (a
        scene placed 100 km from the origin, as georeferenced models are, has 8 mm steps: a
        smaller push left its surfaces shadowing themselves)."""
        return max(SURFACE_EPSILON * self.extent, ORIGIN_ULPS * self.coordinate_step)

    def raw_throughput(self, n_rays: int = 200_000, seed: int = 0) -> float:
        """Closest-hit rays per second on random rays from inside the bounds, all threads."""
        rng = np.random.default_rng(seed)
        lo, hi = self._bounds_all()
        origins = (lo + rng.random((n_rays, 3)) * (hi - lo)).astype(np.float32)
        directions = rng.normal(size=(n_rays, 3))
        directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)
        self.intersect(origins[:1024], directions[:1024], trusted=True)  # first-touch costs stay out of the timing
        start = time.perf_counter()
        self.intersect(origins, directions, trusted=True)
        rate = n_rays / max(time.perf_counter() - start, 1e-9)
        log.info("embree raw throughput: %.3g rays/s on %d threads", rate, self.threads)
        return rate

    # -- internals ----------------------------------------------------------------------------

    def _embree_rays(
        self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray, trusted: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]:
        """(n, 3) float32 C-contiguous origins, (n, 3) or (1, 3) directions, (n,) float32 tfar and
        (n,) bool valid, or None when every ray is valid.

        Invalid rays get a harmless finite ray with tfar < tnear, which Embree skips, and the
        callers mask their results with `valid`; the caller's arrays are never written to.
        """
        if trusted:
            o = np.ascontiguousarray(origins, np.float32)
            d = np.ascontiguousarray(directions, np.float32)
            tf = np.empty(o.shape[0], np.float32)
            tf[:] = tfar
            return o, d, tf, None
        origins, directions, tf, valid = prepare_rays(origins, directions, tfar)
        o = np.ascontiguousarray(origins, np.float32)
        d = np.ascontiguousarray(directions, np.float32)
        if not valid.all():
            bad = ~valid
            o = o.copy() if np.may_share_memory(o, origins) else o
            d = d.copy() if np.may_share_memory(d, directions) else d
            o[bad] = 0.0
            d[bad] = (0.0, 0.0, 1.0)
            tf[bad] = -1.0
            return o, d, tf, valid
        return o, d, tf, None

    def _parallel(self, n: int) -> bool:
        """Whether a batch of n rays is split over the worker pool."""
        return self._pool is not None and n >= 2 * MIN_CHUNK_RAYS

    def _for_chunks(self, n: int, work: Callable[[slice], None]) -> None:
        """Run work over slices of range(n), on the pool when the batch is large enough."""
        if n == 0:
            return
        pool = self._pool
        if not self._parallel(n):
            work(slice(0, n))
            return
        size = max(MIN_CHUNK_RAYS, math.ceil(n / (self.threads * CHUNKS_PER_THREAD)))
        futures = [pool.submit(work, slice(s, min(s + size, n))) for s in range(0, n, size)]
        for f in futures:
            f.result()  # re-raises a worker's exception here

    def _build(self, geometry: Geometry, ids: np.ndarray, weld: bool = False) -> _SubScene | None:
        """The sub-scene of triangles `ids`. weld : merge vertices at the same position (static
        scenes only: the dynamic scene's vertices are re-read by index every frame, and two corners
        that meet now may part later)."""
        if ids.size == 0:
            return None
        whole = ids.size == geometry.triangle_count  # ids ascending and unique: every triangle
        corners = geometry.triangles.ravel() if whole else geometry.triangles[ids].ravel()
        # np.unique(corners, return_inverse=True) without its sort: a mask over the vertices.
        used = np.zeros(geometry.positions.shape[0], bool)
        used[corners] = True
        if used.all():  # a snapshot's corner-split vertices: all used, none to compact
            vertex_ids = np.arange(used.size)
            inverse = corners
            vertices = np.ascontiguousarray(geometry.positions, np.float32)
        else:
            vertex_ids = np.flatnonzero(used)
            inverse = (np.cumsum(used) - 1)[corners]
            vertices = np.ascontiguousarray(geometry.positions[vertex_ids], np.float32)
        if weld and not embree_upload.available(rtcs.EmbreeScene, self._device):
            # Snapshots repeat a vertex per corner (normals and UVs are per corner), and embreex
            # copies vertices element by element through Python indexing (~1 us per vertex):
            # welding the atrium's 959k corners to 166k vertices halves its build. Embree sees the
            # same triangles, so every hit is bit for bit the same. The C API upload copies them
            # in one memmove: there the weld's sort cost more than it saved (a 2M-triangle mesh's
            # 6M corners: ~0.7 s).
            first, merged = weld_positions(vertices)
            vertex_ids, vertices, inverse = vertex_ids[first], np.ascontiguousarray(vertices[first]), merged[inverse]
        local = inverse.reshape(-1, 3).astype(np.int32)
        return self._commit(ids, vertex_ids, local, vertices)

    def _commit(
        self, ids: np.ndarray, vertex_ids: np.ndarray, local: np.ndarray, vertices: np.ndarray
    ) -> _SubScene:
        scene = rtcs.EmbreeScene(self._device, robust=ROBUST)
        mesh = None if embree_upload.upload(scene, self._device, vertices, local) else TriangleMesh(scene, vertices, local)
        # embreex commits lazily on the first run(); do it here, on one thread, not racing in workers.
        scene.run(np.zeros((1, 3), np.float32), np.array([[0.0, 0.0, 1.0]], np.float32), dists=np.zeros(1, np.float32))
        identity = bool(np.array_equal(ids, np.arange(ids.size)))
        return _SubScene(scene, mesh, ids, vertex_ids, local, vertices, identity)

    @staticmethod
    def _count(sub: _SubScene | None) -> int:
        return 0 if sub is None else int(sub.ids.size)

    @staticmethod
    def _bounds(sub: _SubScene | None) -> tuple[np.ndarray, np.ndarray] | None:
        if sub is None:
            return None
        v = sub.vertices
        finite = v if np.isfinite(v).all() else v[np.isfinite(v).all(axis=1)]  # no copy when all are
        if finite.size == 0:
            return None
        lo, hi = column_bounds(finite)
        return lo.astype(np.float64), hi.astype(np.float64)

    def _bounds_all(self) -> tuple[np.ndarray, np.ndarray]:
        """(lo, hi) float64 (3,) bounds of both scenes' current vertices."""
        boxes = [b for b in (self._static_bounds, self._bounds(self._dynamic)) if b is not None]
        if not boxes:
            return np.zeros(3), np.zeros(3)
        return np.min([b[0] for b in boxes], axis=0), np.max([b[1] for b in boxes], axis=0)

    def _set_extent(self) -> None:
        lo, hi = self._bounds_all()
        #: Scene bounding-box diagonal in metres; the scale for `epsilon`.
        self.extent = float(np.linalg.norm(hi - lo))
        #: float32 spacing at the scene's largest coordinate magnitude (its positions' precision).
        self.coordinate_step = float(np.spacing(np.float32(max(np.abs(lo).max(), np.abs(hi).max()))))


def weld_positions(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices with bit-identical positions merged: (first (k,) intp, inverse (n,) intp) with
    vertices[first][inverse] == vertices, first ascending.

    vertices : (n, 3) float32. One sort (not an argsort: numpy's sort of uint64 is ~5x faster) of
    a 64-bit key: the high bits a hash of the three coordinates' bits, the low bits the vertex's
    index. Every group of equal hashes is checked against its first member; a collision (about
    one mesh in 30 at a million vertices) falls back to the exact lexsort of the three columns.
    """
    n = vertices.shape[0]
    if n == 0:
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    bits = np.ascontiguousarray(vertices, np.float32).view(np.uint32)
    wide = bits.astype(np.uint64)
    shift = np.uint64(max(1, int(n - 1).bit_length()))
    with np.errstate(over="ignore"):
        key = wide[:, 0] * np.uint64(0x9E3779B97F4A7C15)
        key ^= wide[:, 1] * np.uint64(0xC2B2AE3D27D4EB4F)
        key ^= wide[:, 2] * np.uint64(0x165667B19E3779F9)
    key >>= shift
    key <<= shift
    key |= np.arange(n, dtype=np.uint64)
    key.sort()
    order = (key & ((np.uint64(1) << shift) - np.uint64(1))).astype(np.intp)
    key >>= shift
    new = np.empty(n, bool)
    new[0] = True
    np.not_equal(key[1:], key[:-1], out=new[1:])
    group = np.cumsum(new) - 1
    head = order[new]  # each group's lowest index (the index breaks ties in the sort)
    # Exact check, a column at a time (fancy indexing whole (n, 3) rows is ~10x slower).
    lead = head[group]
    if not all(np.array_equal(col[order], col[lead]) for col in (np.ascontiguousarray(bits[:, c]) for c in range(3))):
        order, group, head = _lexsort_groups(bits)
    # Renumber the groups by their first member so `first` ascends (vertex order kept).
    by_first = np.argsort(head)
    rank = np.empty(head.size, np.intp)
    rank[by_first] = np.arange(head.size)
    inverse = np.empty(n, np.intp)
    inverse[order] = rank[group]
    return head[by_first].astype(np.intp), inverse


def _lexsort_groups(bits: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`weld_positions`' exact fallback: (order (n,), group of each sorted row (n,), each group's
    lowest index) of (n, 3) uint32 rows grouped by a lexsort."""
    order = np.lexsort((bits[:, 2], bits[:, 1], bits[:, 0]))
    sb = bits[order]
    new = np.empty(order.size, bool)
    new[0] = True
    new[1:] = (sb[1:] != sb[:-1]).any(axis=1)
    return order, np.cumsum(new) - 1, np.minimum.reduceat(order, np.flatnonzero(new))
