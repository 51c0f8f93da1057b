"""Ray tracing backends: Embree against the numpy reference, dynamic updates, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core.errors import EmptySceneError, InvalidGeometryError
from hybridgi_core.snapshot import Geometry, concat_geometry, geometry_from_arrays
from hybridgi_core.trace import SURFACE_EPSILON, Hits
from hybridgi_core.trace.embree import MIN_CHUNK_RAYS, EmbreeTracer
from hybridgi_core.trace.reference import NumpyTracer

#: Barycentric distance to an edge below which embree (float32) and the reference (float64) may
#: legitimately disagree on hit/miss or on which of two triangles sharing the edge was hit.
EDGE_MARGIN = 1e-4
T_RTOL = 1e-4

# The unit cube [0, 1]^3 as 12 triangles, faces wound outwards (winding must not matter).
CUBE_CORNERS = np.array([[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)], np.float32)
CUBE_QUADS = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
CUBE_TRIS = np.array([t for a, b, c, d in CUBE_QUADS for t in ((a, b, c), (a, c, d))], np.int32)


def cube(scale: float = 1.0, offset=(0.0, 0.0, 0.0), object_index: int = 0) -> Geometry:
    return geometry_from_arrays(CUBE_CORNERS * scale + np.float32(offset), CUBE_TRIS, object_index=object_index)


def soup(n: int = 300, seed: int = 0) -> Geometry:
    """n random triangles (edges ~0.15) inside the unit cube; they intersect each other."""
    rng = np.random.default_rng(seed)
    centres = rng.random((n, 1, 3))
    corners = centres + rng.normal(scale=0.08, size=(n, 3, 3))
    return geometry_from_arrays(corners.reshape(-1, 3), np.arange(3 * n).reshape(-1, 3))


def random_rays(n: int, seed: int = 1, lo: float = -0.5, hi: float = 1.5) -> tuple[np.ndarray, np.ndarray]:
    """Origins uniform in [lo, hi]^3, unit directions towards a random point of the unit cube."""
    rng = np.random.default_rng(seed)
    origins = rng.uniform(lo, hi, (n, 3))
    d = rng.random((n, 3)) - origins
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return origins.astype(np.float32), d.astype(np.float32)


def edge_distance(hits: Hits) -> np.ndarray:
    """(n,) smallest barycentric coordinate of each hit (inf for misses)."""
    w = np.minimum(np.minimum(hits.u, hits.v), 1.0 - hits.u - hits.v)
    return np.where(hits.hit, w, np.inf)


def assert_agree(ref: Hits, emb: Hits, max_mismatch_share: float = 1e-3) -> None:
    """Hit/miss agree except for a few rays grazing an edge; t agrees; prim agrees unless tied."""
    mismatch = ref.hit != emb.hit
    grazing = np.minimum(edge_distance(ref), edge_distance(emb)) < EDGE_MARGIN
    assert not (mismatch & ~grazing).any(), f"{int((mismatch & ~grazing).sum())} clear hit/miss disagreements"
    assert mismatch.mean() <= max_mismatch_share
    both = ref.hit & emb.hit
    assert both.sum() > 0.2 * len(ref.t), "the test rays should hit something"
    np.testing.assert_allclose(emb.t[both], ref.t[both], rtol=T_RTOL)
    other_prim = both & (ref.prim != emb.prim)
    # A different triangle at the same distance is a tie (shared edge, crossing triangles).
    np.testing.assert_allclose(emb.t[other_prim], ref.t[other_prim], rtol=T_RTOL)
    assert other_prim.mean() <= max_mismatch_share
    same = both & (ref.prim == emb.prim)
    np.testing.assert_allclose(emb.u[same], ref.u[same], atol=1e-3)
    np.testing.assert_allclose(emb.v[same], ref.v[same], atol=1e-3)
    assert np.isinf(emb.t[~emb.hit]).all() and np.isinf(ref.t[~ref.hit]).all()


def hit_points(geometry: Geometry, hits: Hits) -> np.ndarray:
    """(k, 3) world positions of the hits from prim and barycentrics."""
    p = geometry.positions[geometry.triangles[hits.prim[hits.hit]]].astype(np.float64)
    u, v = hits.u[hits.hit, None], hits.v[hits.hit, None]
    return (1 - u - v) * p[:, 0] + u * p[:, 1] + v * p[:, 2]


@pytest.fixture(params=["numpy", "embree"])
def make_tracer(request):
    tracers = []

    def make(geometry, **kwargs):
        t = NumpyTracer(geometry) if request.param == "numpy" else EmbreeTracer(geometry, **kwargs)
        tracers.append(t)
        return t

    yield make
    for t in tracers:
        if isinstance(t, EmbreeTracer):
            t.close()


# -- agreement with the reference -----------------------------------------------------------------


def test_embree_matches_reference_on_triangle_soup():
    geometry = soup()
    origins, directions = random_rays(6000)
    with EmbreeTracer(geometry) as emb:
        assert_agree(NumpyTracer(geometry).intersect(origins, directions), emb.intersect(origins, directions))
        np.testing.assert_array_equal(emb.occluded(origins, directions), emb.intersect(origins, directions).hit)


def test_embree_matches_reference_on_closed_box():
    geometry = cube()
    origins, directions = random_rays(6000, seed=2)
    ref = NumpyTracer(geometry).intersect(origins, directions)
    with EmbreeTracer(geometry) as emb:
        assert_agree(ref, emb.intersect(origins, directions))


@pytest.mark.parametrize("scale", [1e-3, 1e-1, 1.0, 1e2, 1e4])
def test_agreement_holds_across_scales(scale):
    g = soup(200, seed=3)
    geometry = geometry_from_arrays(g.positions * np.float32(scale), g.triangles)
    origins, directions = random_rays(2000, seed=4)
    origins = origins * np.float32(scale)
    ref = NumpyTracer(geometry).intersect(origins, directions)
    with EmbreeTracer(geometry) as emb:
        hits = emb.intersect(origins, directions)
        assert_agree(ref, hits)
        assert emb.extent == pytest.approx(scale * np.linalg.norm(np.ptp(g.positions, axis=0)), rel=1e-5)
        assert emb.epsilon == pytest.approx(SURFACE_EPSILON * emb.extent)


def test_threaded_batches_give_the_same_hits_as_one_thread():
    geometry = soup()
    origins, directions = random_rays(3 * MIN_CHUNK_RAYS + 123, seed=5)
    with EmbreeTracer(geometry, threads=1) as one, EmbreeTracer(geometry, threads=2) as two:
        a, b = one.intersect(origins, directions), two.intersect(origins, directions)
        for field in ("t", "prim", "u", "v"):
            np.testing.assert_array_equal(getattr(a, field), getattr(b, field))
        np.testing.assert_array_equal(one.occluded(origins, directions), two.occluded(origins, directions))
        two.close()
        np.testing.assert_array_equal(two.intersect(origins, directions).prim, a.prim)  # usable after close


@pytest.mark.parametrize(
    ("backend", "n_rays"),
    [(NumpyTracer, 3000), (lambda g: EmbreeTracer(g, threads=1), 3000), (lambda g: EmbreeTracer(g, threads=2), 2 * MIN_CHUNK_RAYS + 77)],
    ids=["numpy", "embree", "embree-threaded"],
)
def test_one_shared_direction_and_trusted_rays_give_the_same_answers(backend, n_rays):
    """A (1, 3) direction stands for every ray (shadow rays towards a sun), and trusted=True only
    skips the input checks: both must answer exactly as the general call does, threaded or not."""
    tracer = backend(soup())
    origins, _ = random_rays(n_rays, seed=9)
    d = np.array([[0.36, -0.48, 0.8]], np.float32)
    full = np.repeat(d, n_rays, axis=0)
    tfar = np.float32(0.7)
    general = tracer.intersect(origins, full, tfar)
    assert 0.1 < general.hit.mean() < 0.9  # the batch has both hits and misses
    for kwargs in ({}, {"trusted": True}):
        for dirs in (d, full):
            h = tracer.intersect(origins, dirs, tfar, **kwargs)
            for field in ("t", "prim", "u", "v"):
                np.testing.assert_array_equal(getattr(h, field), getattr(general, field))
            np.testing.assert_array_equal(tracer.occluded(origins, dirs, tfar, **kwargs), general.hit)
    if isinstance(tracer, EmbreeTracer):
        tracer.close()


# -- distances and tfar -----------------------------------------------------------------------


def test_tfar_limits_intersect_and_occluded(make_tracer):
    tracer = make_tracer(cube())
    # From the centre, +x: the wall at t = 0.5.
    origins = np.full((4, 3), 0.5, np.float32)
    directions = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (4, 1))
    tfar = np.array([0.4, 0.49, 0.51, np.inf], np.float32)
    tfar_before = tfar.copy()
    hits = tracer.intersect(origins, directions, tfar)
    np.testing.assert_array_equal(hits.hit, [False, False, True, True])
    np.testing.assert_allclose(hits.t[hits.hit], 0.5, rtol=1e-6)
    np.testing.assert_array_equal(tracer.occluded(origins, directions, tfar), [False, False, True, True])
    np.testing.assert_array_equal(tfar, tfar_before)  # inputs are never written to
    # A scalar tfar applies to every ray.
    assert not tracer.occluded(origins, directions, 0.3).any()
    assert tracer.intersect(origins, directions, 0.7).hit.all()


def test_ray_from_inside_closed_box_hits_in_every_direction(make_tracer):
    geometry = cube()
    tracer = make_tracer(geometry)
    rng = np.random.default_rng(6)
    n = 4000
    origins = rng.uniform(0.02, 0.98, (n, 3)).astype(np.float32)
    # Half the directions aim exactly at box edges and at the faces' triangulation diagonals,
    # where a non-watertight triangle test leaks.
    targets = rng.random((n, 3))
    targets[: n // 4, :2] = rng.integers(0, 2, (n // 4, 2))
    targets[n // 4: n // 2, 0] = rng.integers(0, 2, n // 4)
    targets[n // 4: n // 2, 2] = targets[n // 4: n // 2, 1]
    directions = targets - origins
    directions = (directions / np.linalg.norm(directions, axis=1, keepdims=True)).astype(np.float32)
    hits = tracer.intersect(origins, directions)
    assert hits.hit.all()
    assert tracer.occluded(origins, directions).all()
    p = hit_points(geometry, hits)
    on_wall = np.minimum(np.abs(p), np.abs(p - 1.0)).min(axis=1)
    assert on_wall.max() < 1e-5
    np.testing.assert_allclose(origins + hits.t[:, None] * directions, p, atol=1e-5)


# -- dynamic objects --------------------------------------------------------------------------


def scene_with_moving_quad(x: float) -> Geometry:
    """Static cube (object 0) and a dynamic quad (object 1) across y, z in [0.25, 0.75] at x."""
    quad = np.array([[x, 0.25, 0.25], [x, 0.75, 0.25], [x, 0.75, 0.75], [x, 0.25, 0.75]], np.float32)
    return concat_geometry([cube(), geometry_from_arrays(quad, [[0, 1, 2], [0, 2, 3]], object_index=1)])


def test_update_dynamic_moves_hits_and_keeps_static_hits():
    rng = np.random.default_rng(7)
    n = 2000
    origins = np.column_stack([np.full(n, 0.05), rng.uniform(0.1, 0.9, (n, 2))]).astype(np.float32)
    directions = np.tile(np.array([[1.0, 0.0, 0.0]], np.float32), (n, 1))
    through_quad = (np.abs(origins[:, 1:] - 0.5) < 0.24).all(axis=1)
    clear = (np.abs(origins[:, 1:] - 0.5) > 0.26).any(axis=1)
    quad_prims = {12, 13}

    start = scene_with_moving_quad(0.3)
    with EmbreeTracer(start, dynamic_objects=frozenset({1})) as tracer:
        before = tracer.intersect(origins, directions)
        np.testing.assert_allclose(before.t[through_quad], 0.25, rtol=1e-5)
        assert set(before.prim[through_quad]) <= quad_prims

        moved = scene_with_moving_quad(0.8)
        tracer.update_dynamic(moved)
        assert tracer.geometry is moved
        after = tracer.intersect(origins, directions)
        np.testing.assert_allclose(after.t[through_quad], 0.75, rtol=1e-5)
        assert set(after.prim[through_quad]) <= quad_prims
        # Rays that miss the quad hit the static wall at x = 1 exactly as before.
        np.testing.assert_array_equal(after.prim[clear], before.prim[clear])
        np.testing.assert_array_equal(after.t[clear], before.t[clear])
        np.testing.assert_allclose(after.t[clear], 0.95, rtol=1e-5)
        # The whole moved scene agrees with a reference built from scratch.
        assert_agree(NumpyTracer(moved).intersect(origins, directions), after)
        assert not tracer.occluded(origins, directions, 0.5).any()
        occluded = tracer.occluded(origins, directions, 0.8)
        assert occluded[through_quad].all() and not occluded[clear].any()

        # Moved out of the box (behind the wall): every ray now hits the wall.
        tracer.update_dynamic(scene_with_moving_quad(1.5))
        gone = tracer.intersect(origins, directions)
        assert (gone.prim < 12).all()
        np.testing.assert_allclose(gone.t, 0.95, rtol=1e-5)
        assert tracer.extent == pytest.approx(np.linalg.norm([1.5, 1.0, 1.0]), rel=1e-6)


def test_all_dynamic_scene_and_topology_check():
    geometry = cube(object_index=0)
    with EmbreeTracer(geometry, dynamic_objects=frozenset({0})) as tracer:
        origin = np.full((1, 3), 0.5, np.float32)
        up = np.array([[0.0, 0.0, 1.0]], np.float32)
        assert tracer.intersect(origin, up).t[0] == pytest.approx(0.5)
        tracer.update_dynamic(cube(scale=2.0))
        assert tracer.intersect(origin, up).t[0] == pytest.approx(1.5)
        with pytest.raises(InvalidGeometryError):
            tracer.update_dynamic(concat_geometry([cube(), cube()]))


# -- bad input --------------------------------------------------------------------------------


def empty_geometry() -> Geometry:
    return geometry_from_arrays(np.zeros((0, 3)), np.zeros((0, 3), np.int32))


@pytest.mark.parametrize("backend", [NumpyTracer, EmbreeTracer])
def test_empty_geometry_raises(backend):
    with pytest.raises(EmptySceneError):
        backend(empty_geometry())


def test_nan_and_zero_directions_miss_without_disturbing_other_rays(make_tracer):
    tracer = make_tracer(cube())
    origins = np.full((7, 3), 0.5, np.float32)
    origins[4] = np.nan
    directions = np.array(
        [[1, 0, 0], [np.nan, 0, 0], [0, 0, 0], [0, np.inf, 0], [0, 0, 1], [0, 1, 0], [0, -1, 0]], np.float32
    )
    # Rays 5 and 6 are fine but have a NaN and a negative tfar (embreex alone calls the latter occluded).
    tfar = np.array([np.inf, np.inf, np.inf, np.inf, np.inf, np.nan, -1.0], np.float32)
    hits = tracer.intersect(origins, directions, tfar)
    np.testing.assert_array_equal(hits.hit, [True, False, False, False, False, False, False])
    assert hits.t[0] == pytest.approx(0.5)
    assert np.isinf(hits.t[1:]).all() and (hits.prim[1:] == -1).all()
    np.testing.assert_array_equal(tracer.occluded(origins, directions, tfar), hits.hit)
    assert np.isnan(directions[1, 0])  # the caller's arrays were not cleaned in place


def test_float64_and_non_contiguous_input_is_accepted(make_tracer):
    tracer = make_tracer(cube())
    rays = np.zeros((3, 2, 3))
    rays[:, 0] = 0.5
    rays[:, 1] = [[1, 0, 0], [0, -1, 0], [0, 0, 1]]
    hits = tracer.intersect(rays[:, 0], rays[:, 1])  # strided float64 views
    np.testing.assert_allclose(hits.t, 0.5, rtol=1e-6)
    assert hits.t.dtype == np.float32 and hits.prim.dtype == np.int32


def test_mismatched_shapes_raise(make_tracer):
    tracer = make_tracer(cube())
    with pytest.raises(ValueError):
        tracer.intersect(np.zeros((3, 3), np.float32), np.zeros((2, 3), np.float32))
    with pytest.raises(ValueError):
        tracer.intersect(np.zeros((3, 3), np.float32), np.ones((3, 3), np.float32), np.ones(2, np.float32))


def test_empty_batch_returns_empty_hits(make_tracer):
    tracer = make_tracer(cube())
    hits = tracer.intersect(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32))
    assert hits.t.shape == (0,) and hits.prim.shape == (0,)
    assert tracer.occluded(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)).shape == (0,)


def test_raw_throughput_is_a_positive_rate():
    with EmbreeTracer(soup(), threads=2) as tracer:
        rate = tracer.raw_throughput(n_rays=3 * MIN_CHUNK_RAYS)
    assert np.isfinite(rate) and rate > 1e4


def test_weld_positions_merges_exact_duplicates_only():
    """Corners repeated per triangle (as snapshots store them) weld to the distinct positions;
    positions that differ in one bit (or only in the sign of zero) stay apart."""
    from hybridgi_core.trace import embree
    from hybridgi_core.trace.embree import weld_positions

    rng = np.random.default_rng(3)
    distinct = rng.integers(0, 6, (300, 3)).astype(np.float32)
    distinct = np.unique(distinct, axis=0)
    near = distinct[:1].copy()
    near[0, 0] = np.nextafter(near[0, 0], np.float32(np.inf))
    signed = np.array([[0.0, 0.0, 0.0], [-0.0, 0.0, 0.0]], np.float32)
    v = np.concatenate([distinct[rng.integers(0, len(distinct), 5000)], near, signed])
    expect = np.unique(v.view(np.uint32), axis=0).shape[0]
    first, inverse = weld_positions(v)
    assert np.array_equal(v[first][inverse], v)
    assert np.all(np.diff(first) > 0)
    assert first.size == expect
    # The exact fallback a hash collision takes groups the same way.
    order, group, head = embree._lexsort_groups(v.view(np.uint32))
    assert head.size == expect
    assert np.array_equal(v[head[group]], v[order])
    empty_first, empty_inverse = weld_positions(np.zeros((0, 3), np.float32))
    assert empty_first.size == 0 and empty_inverse.size == 0


def test_c_api_upload_is_taken_and_hits_exactly_what_triangle_mesh_hits(monkeypatch):
    """The fast upload (`embree_upload`) must be the path this platform takes, and give the very
    hits of embreex's own TriangleMesh, static and dynamic scenes alike (it builds the same BVH)."""
    from hybridgi_core.trace import embree_upload  # noqa: PLC0415

    geometry = concat_geometry([soup(400, seed=3), cube(0.5, (0.2, 0.2, 0.2), object_index=1)])
    origins, directions = random_rays(20000, seed=5)
    taken = []
    real = embree_upload.upload
    monkeypatch.setattr(embree_upload, "upload", lambda *a: taken.append(real(*a)) or taken[-1])
    with EmbreeTracer(geometry, dynamic_objects=frozenset({1})) as fast:
        fast_hits = fast.intersect(origins, directions)
        fast_blocked = fast.occluded(origins, directions, np.float32(0.7))
    assert taken == [True, True]
    monkeypatch.setattr(embree_upload, "upload", lambda *a: False)
    with EmbreeTracer(geometry, dynamic_objects=frozenset({1})) as slow:
        slow_hits = slow.intersect(origins, directions)
        slow_blocked = slow.occluded(origins, directions, np.float32(0.7))
    assert fast_hits.hit.mean() > 0.3
    for name in ("t", "prim", "u", "v"):
        np.testing.assert_array_equal(getattr(fast_hits, name), getattr(slow_hits, name))
    np.testing.assert_array_equal(fast_blocked, slow_blocked)


def test_corner_split_and_welded_vertices_give_the_same_hits(monkeypatch):
    """With the C API upload the static scene keeps the snapshot's corner-split vertices (no weld:
    its sort cost more than the memmove it saved); Embree sees the same triangles either way, so
    every hit is the same bit for bit as with the welded vertices the slow upload path takes."""
    from hybridgi_core.trace import embree_upload

    # A closed mesh whose triangles share their corners' positions: 2,400 corners, 402 positions.
    rng = np.random.default_rng(5)
    grid = rng.random((402, 3)).astype(np.float32)
    corners = grid[rng.integers(0, 402, (800, 3))]
    geometry = geometry_from_arrays(corners.reshape(-1, 3), np.arange(2400).reshape(-1, 3))
    origins, dirs = random_rays(4000, seed=9)
    if not embree_upload.available(__import__("embreex").rtcore_scene.EmbreeScene, __import__("embreex").rtcore.EmbreeDevice()):
        pytest.skip("embreex's C API path is not available here")
    with EmbreeTracer(geometry, threads=1) as split:
        assert split._static.vertices.shape[0] == 2400  # not welded
        a = split.intersect(origins, dirs)
    monkeypatch.setattr(embree_upload, "available", lambda *args: False)
    with EmbreeTracer(geometry, threads=1) as welded:
        assert welded._static.vertices.shape[0] < 2400
        b = welded.intersect(origins, dirs)
    assert np.count_nonzero(a.prim >= 0) > 500
    for name in ("prim", "t", "u", "v"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
