"""The stored-hit solver: fixed point == retraced bounces, exact invalidation, re-lighting without
probe rays, deterministic final-render warm-up."""

import dataclasses

import numpy as np
import pytest

from hybridgi_core import solver as solver_mod
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Light, Material, ObjectInfo, World, concat_geometry, make_snapshot
from hybridgi_core.solver import segments_meet_box
from hybridgi_core.system import GISystem
from tests.shapes import box

RHO, LE = 0.5, 1.0


def furnace(albedo=RHO, emission=LE):
    mat = Material("furnace", np.full(3, albedo, np.float32), None, np.full(3, emission, np.float32))
    return make_snapshot(box([0, 0, 0], [2, 2, 2]), [mat])


def floor_points(n=5):
    u = np.linspace(0.2, 1.8, n, dtype=np.float32)
    a, b = (x.ravel() for x in np.meshgrid(u, u))
    pts = np.stack([a, b, np.zeros_like(a)], 1)
    return pts, np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (a.size, 1))


class CountingTracer:
    """Wraps a tracer and counts the rays of each query."""

    def __init__(self, tracer):
        self._tracer = tracer
        self.intersect_rays = 0
        self.occluded_rays = 0

    def intersect(self, origins, *args, **kwargs):
        self.intersect_rays += len(origins)
        return self._tracer.intersect(origins, *args, **kwargs)

    def occluded(self, origins, *args, **kwargs):
        self.occluded_rays += len(origins)
        return self._tracer.occluded(origins, *args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._tracer, name)


def counted(gi):
    tracer = CountingTracer(gi.tracer)
    gi.solver.tracer = tracer
    gi.updater.tracer = tracer
    return tracer


@pytest.mark.parametrize("k", [1, 3, 6])
def test_k_iterations_over_stored_hits_equal_k_bounces_and_k_retraced_updates(k):
    """Closed furnace: after the traced batch and k iterations the indirect irradiance holds
    exactly bounces 1..k, pi Le (rho + ... + rho^k), and equals k + 1 retraced updates at alpha 1
    (the first retraced update only fills the direct band)."""
    s = CacheSettings(resolution=4, rays_per_cell=64, hysteresis=0.0)
    pts, up = floor_points()
    expect = np.pi * LE * sum(RHO**i for i in range(1, k + 1))
    with GISystem(furnace(), s) as gi:
        cells = gi.surface_cells()
        tracer = counted(gi)
        gi.solver.begin(cells)
        gi.solver.trace_batch(0)
        traced = tracer.intersect_rays
        for _ in range(k):
            gi.solver.relax()
        assert tracer.intersect_rays == traced == cells.size * s.rays_per_cell  # iterations trace nothing
        stored = gi.gather(pts, up).indirect
    np.testing.assert_allclose(stored, expect, rtol=5e-3)
    with GISystem(furnace(), s) as gi:
        for i in range(k + 1):
            gi.update(gi.surface_cells(), solver_mod.WARMUP_FRAME_BASE + i, alpha=1.0)
        retraced = gi.gather(pts, up).indirect
    np.testing.assert_allclose(stored, retraced, rtol=6e-3)


def test_extrapolated_fixed_point_reaches_infinite_bounces_in_few_iterations():
    """With the geometric tail the furnace reaches pi Le rho / (1 - rho) from one traced batch,
    in fewer iterations than the ~log(1e-3) / log(rho) = 10 plain ones need."""
    s = CacheSettings(resolution=4, rays_per_cell=64)
    pts, up = floor_points()
    with GISystem(furnace(), s) as gi:
        tracer = counted(gi)
        stats = gi.solve(batches=1)
        g = gi.gather(pts, up)
        assert tracer.intersect_rays == gi.surface_cells().size * s.rays_per_cell
    assert stats.iterations <= 6
    np.testing.assert_allclose(g.indirect, np.pi * LE * RHO / (1 - RHO), rtol=5e-3)
    np.testing.assert_allclose(g.direct, np.pi * LE, rtol=3e-3)


def test_warm_up_is_the_solver_deterministic_and_traces_its_batches_only():
    s = CacheSettings(resolution=6, rays_per_cell=32, threads=2)
    runs = []
    for _ in range(2):
        with GISystem(room_with_ball(), s) as gi:
            tracer = counted(gi)
            stats = gi.warm_up(16)
            cells = gi.surface_cells()
            runs.append((gi.cache.sh_indirect.copy(), gi.cache.sh_direct.copy(), gi.cache.depth.copy()))
            # 16 updates = 2 traced batches; every other step iterates without rays.
            assert tracer.intersect_rays == 2 * cells.size * s.rays_per_cell
            assert sum(st.rays for st in stats) == tracer.intersect_rays
            assert gi.cache.valid[cells].sum() > 0
    for a, b in zip(runs[0], runs[1], strict=True):
        np.testing.assert_array_equal(a, b)


def room_with_ball(ball_lo=(4.0, 4.5, 0.0), energy=300.0, ball_dynamic=False):
    room = box([0, 0, 0], [10, 10, 10], inward=True, obj=0)
    ball = box(ball_lo, np.asarray(ball_lo, np.float32) + 1.0, inward=False, obj=1)
    light = Light("POINT", np.ones(3), energy, np.array([[1, 0, 0, 5], [0, 1, 0, 5], [0, 0, 1, 8], [0, 0, 0, 1.0]]))
    return make_snapshot(
        concat_geometry([room, ball]), [Material()], [light], World(),
        [ObjectInfo("room"), ObjectInfo("ball", dynamic=ball_dynamic)],
    )


def emissive_panel_room():
    """A 4 m room lit only by a glowing slab under its ceiling (sampled by the hits: no lamp)."""
    room = box([0, 0, 0], [4, 4, 4], inward=True, obj=0)
    slab = box([1.2, 1.2, 3.7], [2.8, 2.8, 3.75], inward=False, material=1, obj=1)
    mats = [Material("white", np.full(3, 0.7, np.float32)),
            Material("panel", np.full(3, 0.8, np.float32), None, np.full(3, 20.0, np.float32))]
    return make_snapshot(concat_geometry([room, slab]), mats, [], World(), [ObjectInfo("room"), ObjectInfo("slab")])


def _stored_ray_segments(gi):
    """Per stored batch: (cells (m,), origins (n, 3), dirs (n, 3), t (n,)) of every stored ray."""
    out = []
    for c in gi.solver.chunks:
        out.append((c.cells, np.repeat(gi.cache.centers[c.cells], c.r, axis=0), c.ray_dirs, c.prim, c.t))
    return out


@pytest.mark.parametrize("ray_length", [0.0, 2.5])
def test_invalidation_marks_exactly_the_rays_that_reach_the_moved_box(ray_length):
    """Moving the ball from A to B: the stale rays are exactly those that hit the ball at A (a
    ball triangle) or that hit it at B (traced again with the same directions), up to rays
    grazing the boxes within the epsilon pad; with a ray length no cell farther than it from
    both boxes has a stale ray."""
    s = CacheSettings(resolution=12, rays_per_cell=32, ray_length=ray_length)
    a_lo, b_lo = np.array([2.0, 4.5, 0.0], np.float32), np.array([6.0, 4.5, 0.0], np.float32)
    with GISystem(room_with_ball(a_lo, ball_dynamic=True), s, dynamic_objects=frozenset({1})) as gi:
        gi.solve(batches=1)
        before = _stored_ray_segments(gi)
        ball_prims = np.flatnonzero(gi.ray_geometry.object_index == 1)
        gi.move_dynamic(room_with_ball(b_lo, ball_dynamic=True))  # invalidates its own boxes
        tfar = np.float32(ray_length) if ray_length > 0 else np.float32(np.inf)
        stale, expect, cells_stale = 0, 0, set()
        for chunk, (cells, o, d, prim, _t) in zip(gi.solver.chunks, before, strict=True):
            marked = np.zeros(prim.size, bool) if chunk.ray_stale is None else chunk.ray_stale
            now = gi.tracer.intersect(o.astype(np.float32), d.astype(np.float32), tfar)
            should = np.isin(prim, ball_prims) | np.isin(now.prim, ball_prims)
            assert not (should & ~marked).any()  # every ray the move changed is marked
            stale += int(marked.sum())
            expect += int(should.sum())
            cells_stale |= set(cells[marked.reshape(cells.size, -1).any(axis=1)].tolist())
            # Rays not marked keep their hit exactly.
            np.testing.assert_array_equal(now.prim[~marked], prim[~marked])
    assert expect > 0, "the test scene must have rays that reach the ball"
    assert stale - expect <= max(4, 0.05 * expect), (stale, expect)
    assert stale < 0.5 * sum(p.size for _c, _o, _d, p, _t in before)
    if ray_length > 0:
        c = gi.cache.centers[sorted(cells_stale)]
        d = np.minimum(
            np.linalg.norm(np.maximum(np.maximum(a_lo - c, c - (a_lo + 1)), 0), axis=1),
            np.linalg.norm(np.maximum(np.maximum(b_lo - c, c - (b_lo + 1)), 0), axis=1),
        )
        assert (d <= ray_length + 1e-3).all()


@pytest.mark.parametrize("kind", ["POINT", "SUN", "AREA"])
def test_shadow_marks_of_a_moved_box_are_those_of_every_stored_hits_segment_to_the_lamp(kind):
    """`_mark_shadows` culls by cell before it tests hits: it must flag exactly the hits whose own
    segment to the lamp (grown by its extent) meets the box, as testing every hit does."""
    s = CacheSettings(resolution=12, rays_per_cell=32)
    tilt = np.array([[1, 0, 0, 5], [0, 0.8, -0.6, 5], [0, 0.6, 0.8, 8], [0, 0, 0, 1.0]])
    light = Light(kind, np.ones(3), 300.0 if kind != "SUN" else 3.0, tilt, radius=0.3, size=1.5)
    snap = dataclasses.replace(room_with_ball(), lights=[light])
    lo, hi = np.array([3.0, 2.0, 1.0], np.float32), np.array([4.0, 3.5, 2.0], np.float32)
    with GISystem(snap, s) as gi:
        gi.solve(batches=1)
        pad = np.float32(gi.solver.epsilon) * 4
        grow = np.float32(0.0 if kind == "SUN" else solver_mod._light_extent(light))
        expect, marked = [], []
        for chunk in gi.solver.chunks:
            p = chunk.positions(gi.cache.centers)
            d, reach = solver_mod._to_lamp(light, p)
            expect.append(segments_meet_box(p, d, reach, lo - pad - grow, hi + pad + grow))
            chunk.lamp_stale[:] = False
        gi.solver.invalidate_boxes([(lo, hi)])
        marked = [chunk.lamp_stale.copy() for chunk in gi.solver.chunks]
    expect, marked = np.concatenate(expect), np.concatenate(marked)
    assert 0 < expect.sum() < expect.size
    np.testing.assert_array_equal(marked, expect)


def test_a_box_moved_between_an_emitter_and_a_wall_re_shades_the_wall_hits():
    """Hits that sample an emitter (`GISolver.hit_emitters`) take its light through shadow rays a
    moved box may cross without crossing their probe ray: `invalidate_boxes` flags them as a lamp's
    (`_emitter_spheres`), every hit whose segment to a panel triangle meets the box at least."""
    s = CacheSettings(resolution=12, rays_per_cell=32)
    panel = emissive_panel_room()
    lo, hi = np.array([1.0, 1.0, 1.2], np.float32), np.array([2.0, 2.0, 1.6], np.float32)
    with GISystem(panel, s) as gi:
        gi.solve(batches=1)
        assert gi.solver.hit_emitters() is not None
        for chunk in gi.solver.chunks:
            chunk.lamp_stale[:] = False
        gi.solver.invalidate_boxes([(lo, hi)])
        marked = np.concatenate([chunk.lamp_stale for chunk in gi.solver.chunks])
        # Every hit whose segment to a panel triangle's centre meets the box (grown by its radius).
        em = gi.solver.hit_emitters()
        pad = np.float32(gi.solver.epsilon) * 4
        expect = []
        for chunk in gi.solver.chunks:
            p = chunk.positions(gi.cache.centers)
            hit = np.zeros(p.shape[0], bool)
            for c, r in zip(em.centre, em.radius, strict=True):
                to = c[None, :] - p
                reach = np.linalg.norm(to, axis=1)
                hit |= segments_meet_box(p, to / reach[:, None], reach, lo - pad - r, hi + pad + r)
            expect.append(hit)
        expect = np.concatenate(expect)
    assert 0 < expect.sum() < expect.size
    assert (marked >= expect).all()


def test_resolve_after_a_move_retraces_only_stale_rays_and_matches_a_fresh_solve():
    s = CacheSettings(resolution=12, rays_per_cell=32, ray_length=3.0)
    a_lo, b_lo = (2.0, 4.5, 0.0), (3.0, 4.5, 0.0)
    with GISystem(room_with_ball(a_lo, ball_dynamic=True), s, dynamic_objects=frozenset({1})) as gi:
        gi.solve(batches=2)
        tracer = counted(gi)
        gi.move_dynamic(room_with_ball(b_lo, ball_dynamic=True))
        stale = gi.solver.stale_rays()
        assert 0 < stale < 0.2 * 2 * gi.solver.cells.size * s.rays_per_cell
        # The ball's new surfaces read a few cells no surface read before: traced as well.
        new_cells = np.setdiff1d(gi.surface_cells(), gi.solver.cells).size
        gi.resolve()
        assert tracer.intersect_rays == stale + 2 * new_cells * s.rays_per_cell
        assert gi.solver.stale_rays() == 0
        moved = gi.cache.sh_indirect.copy()
        cells = gi.solver.cells
    with GISystem(room_with_ball(b_lo, ball_dynamic=True), s, dynamic_objects=frozenset({1})) as fresh:
        fresh.solve(cells, batches=2)  # the same cells: the old surfaces' cells stay in the solver
        ref = fresh.cache.sh_indirect
    # Same directions and same hits everywhere: only the iteration's stopping point differs.
    np.testing.assert_allclose(moved[cells, 0], ref[cells, 0], rtol=0.04, atol=1e-3 * np.abs(ref[cells, 0]).max())


@pytest.mark.parametrize("table", [False, True])
def test_light_change_reshades_stored_hits_without_probe_rays(table):
    """Doubling a point light (hard shadows: no sampling noise) doubles the indirect light; the
    re-solve traces shadow rays at the stored hits and not a single probe ray (with the lamp
    table: at a share of the first batch's hits only)."""
    s = CacheSettings(resolution=10, rays_per_cell=32)
    pts = np.array([[3.0, 3.0, 0.0], [7.0, 6.0, 0.0], [5.0, 2.0, 0.0]], np.float32)
    up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (3, 1))
    with GISystem(room_with_ball(), s) as gi:
        gi.solver.use_lamp_table = table
        gi.solve(batches=2)
        before = gi.gather(pts, up).indirect
        tracer = counted(gi)
        gi.set_lights(room_with_ball(energy=600.0))
        stats = gi.on_lights_changed(resolve=True)
        after = gi.gather(pts, up).indirect
        hits = sum(c.hit.size for c in gi.solver.chunks)
        first = sum(c.hit.size for c in gi.solver.chunks if c.batch == 0)
    assert tracer.intersect_rays == 0
    if table:
        # Shadow rays from a few first-batch hits per bin; the second batch reads the table and
        # traces only hits in bins the first never reached.
        assert tracer.occluded_rays < 0.75 * hits
    else:
        assert tracer.occluded_rays > 0.5 * first  # one per stored hit facing the lamp (+ the filter's)
    assert tracer.occluded_rays > 0
    assert stats.iterations > 0
    np.testing.assert_allclose(after, 2.0 * before, rtol=5e-3)


def _relit(energy, warm: bool, lamp_at=(5.0, 5.0, 8.0)):
    """(indirect at three floor points, iterations) of the room's cache solved, then re-solved
    from its stored hits after a lamp edit (power `energy`, position `lamp_at`), with or without
    the warm start (`GISolver._warm_start`)."""
    s = CacheSettings(resolution=10, rays_per_cell=32)
    pts = np.array([[3.0, 3.0, 0.0], [7.0, 6.0, 0.0], [5.0, 2.0, 0.0]], np.float32)
    up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (3, 1))
    edited = room_with_ball(energy=energy)
    lamp = edited.lights[0]
    matrix = np.array(lamp.matrix, np.float64)
    matrix[:3, 3] = lamp_at
    edited = dataclasses.replace(edited, lights=[dataclasses.replace(lamp, matrix=matrix)])
    with GISystem(room_with_ball(), s) as gi:
        gi.solve(batches=2)
        gi.set_lights(edited)
        gi.on_lights_changed()
        if not warm:
            gi.solver._warm = None
        stats = gi.resolve()
        return gi.gather(pts, up).indirect, stats.iterations


def test_a_lamp_edit_solves_from_the_old_solution_scaled_by_the_first_bounces_change():
    """After a lamp edit the iterations start from the old solution times each cell's change of
    first bounce: a change of power is then solved in a few iterations (the fixed point scales
    with it; what is left is the old solve's filtered tail) and a moved lamp no later; either way
    the same fixed point as iterations from the old solution."""
    warm, n_warm = _relit(750.0, warm=True)
    cold, n_cold = _relit(750.0, warm=False)
    assert 2 * n_warm < n_cold
    np.testing.assert_allclose(warm, cold, rtol=2e-3)
    moved, n_moved = _relit(300.0, warm=True, lamp_at=(3.0, 6.0, 6.0))
    moved_cold, n_moved_cold = _relit(300.0, warm=False, lamp_at=(3.0, 6.0, 6.0))
    assert n_moved <= n_moved_cold
    np.testing.assert_allclose(moved, moved_cold, rtol=1e-2)


def test_material_change_reshades_the_stored_hits():
    """A darker albedo at the same hits: the fixed point drops as rho / (1 - rho) does for a
    furnace, without retracing."""
    s = CacheSettings(resolution=4, rays_per_cell=64)
    pts, up = floor_points()
    with GISystem(furnace(0.5), s) as gi:
        gi.solve(batches=1)
        tracer = counted(gi)
        gi.set_lights(furnace(0.25))
        gi.on_lights_changed(resolve=True)
        g = gi.gather(pts, up)
    assert tracer.intersect_rays == 0
    np.testing.assert_allclose(g.indirect, np.pi * LE * 0.25 / 0.75, rtol=5e-3)


def test_segments_meet_box_slab_cases():
    lo, hi = np.zeros(3, np.float32), np.ones(3, np.float32)
    o = np.array([[-1, 0.5, 0.5], [-1, 0.5, 0.5], [-1, 0.5, 0.5], [0.5, 0.5, 0.5], [-1, 2, 0.5], [-1, 0.5, 0.5]], np.float32)
    d = np.array([[1, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1], [1, 0, 0], [1, 0, 0]], np.float32)
    reach = np.array([np.inf, 0.9, np.inf, 0.0, np.inf, 1.0], np.float32)
    np.testing.assert_array_equal(segments_meet_box(o, d, reach, lo, hi), [True, False, False, True, False, True])


def test_hits_sharing_a_cell_and_normal_are_evaluated_once_with_the_same_result(monkeypatch):
    """The solver evaluates hits that read one cell off one side of equally oriented triangles
    once per iteration (`solver._hit_pairs`): a room with a lamp-lit ball solves bit for bit as
    when every hit is evaluated, and the shared path is taken."""
    def solved(share):
        monkeypatch.setattr(solver_mod, "SHARED_HITS_PER_TRIANGLE", 16 if share else 10**12)
        with GISystem(room_with_ball(), CacheSettings(resolution=6, rays_per_cell=32)) as gi:
            gi.solve(batches=1)
            pairs = [c.pairs for c in gi.solver.chunks]
            return gi.cache.sh_indirect.copy(), pairs

    shared, pairs = solved(True)
    plain, none = solved(False)
    assert all(p is None for p in none)
    assert any(p is not None for p in pairs)
    assert all(p[0].size < p[2].size for p in pairs if p is not None)
    assert np.abs(plain).max() > 0
    np.testing.assert_array_equal(shared, plain)


def test_relight_batch_by_batch_equals_the_full_reshade_without_probe_rays():
    """The viewport's progressive re-shade (`relight_batch`): after batch 0 alone the fixed point
    solves from that batch's sources; once every batch is re-shaded a doubled point light has
    doubled the indirect light exactly, with shadow rays only."""
    s = CacheSettings(resolution=10, rays_per_cell=32)
    pts = np.array([[3.0, 3.0, 0.0], [7.0, 6.0, 0.0], [5.0, 2.0, 0.0]], np.float32)
    up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (3, 1))
    with GISystem(room_with_ball(), s) as gi:
        gi.solve(batches=2)
        before = gi.gather(pts, up).indirect
        tracer = counted(gi)
        gi.set_lights(room_with_ball(energy=600.0))
        first = gi.solver.relight_batch(0, materials=False)
        assert gi.solver._materials_stale  # batch 1 still to re-shade
        gi.solver.solve(16)
        partial = gi.gather(pts, up).indirect
        gi.solver.relight_batch(1, materials=False)
        assert not gi.solver._materials_stale
        gi.solver.solve(16)
        gi.solver.filter_cells(bands=("sh_indirect",))
        after = gi.gather(pts, up).indirect
    assert tracer.intersect_rays == 0 and first.shadow_points > 0
    assert np.isfinite(partial).all() and (partial > 1.5 * before).all()  # batch 0's light, doubled
    np.testing.assert_allclose(after, 2.0 * before, rtol=5e-3)


def test_relight_batch_with_materials_reaches_the_new_furnace_answer():
    s = CacheSettings(resolution=4, rays_per_cell=64)
    pts, up = floor_points()
    with GISystem(furnace(0.5), s) as gi:
        gi.solve(batches=2)
        tracer = counted(gi)
        gi.set_lights(furnace(0.25))
        for b in range(2):
            gi.solver.relight_batch(b, materials=True)
        gi.solver.solve(16)
        g = gi.gather(pts, up)
    assert tracer.intersect_rays == 0
    np.testing.assert_allclose(g.indirect, np.pi * LE * 0.25 / 0.75, rtol=5e-3)


def test_a_batch_traced_after_a_solve_looks_up_only_its_own_hits():
    """Batches added one by one between solves (the viewport's refinement) read the same cells
    as a full lookup of every stored hit, and the solved cache is the same."""
    s = CacheSettings(resolution=10, rays_per_cell=32)
    with GISystem(room_with_ball(), s) as gi:
        sol = gi.solver
        sol.begin(gi.surface_cells())
        sol.trace_batch(0)
        sol.solve(16)
        sol.trace_batch(1)
        sol.solve(16)
        incremental = [sol._read_cells[c.flat] for c in sol.chunks]
        x = gi.cache.sh_indirect.copy()
        sol._lookup_valid = None  # force the full lookup
        sol._ensure_lookup()
        full = [sol._read_cells[c.flat] for c in sol.chunks]
        sol._sources = None
        sol.relax()
    for a, b in zip(incremental, full, strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_allclose(gi.cache.sh_indirect, x, rtol=0, atol=2e-3 * np.abs(x).max())


def test_relight_may_start_with_a_batch_that_does_not_carry_the_bounces():
    """The viewport re-shades its short first batch first (`worker_solve.relight_order`) while a
    later full batch carries the bounces: the partial solve already holds the new light, and once
    both are re-shaded a doubled lamp has doubled the indirect light, as in any other order."""
    s = CacheSettings(resolution=10, rays_per_cell=32)
    pts = np.array([[3.0, 3.0, 0.0], [7.0, 6.0, 0.0], [5.0, 2.0, 0.0]], np.float32)
    up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (3, 1))
    with GISystem(room_with_ball(), s) as gi:
        sol = gi.solver
        sol.begin(gi.surface_cells())
        sol.trace_batch(0, rays=16)
        sol.trace_batch(1)
        sol.bounce_from = 1  # as the viewport moves it once a full batch exists
        sol.solve(16)
        before = gi.gather(pts, up).indirect
        gi.set_lights(room_with_ball(energy=600.0))
        sol.relight_batch(0, materials=False)
        sol.solve(16)
        partial = gi.gather(pts, up).indirect
        sol.relight_batch(1, materials=False)
        sol.solve(16)
        after = gi.gather(pts, up).indirect
    assert np.isfinite(partial).all() and (partial > 1.5 * before).all()
    # Each solve stops at its convergence tolerance from a different start: 0.65-0.7% here,
    # with the same magnitude (opposite sign) when the bouncing batch is re-shaded first.
    np.testing.assert_allclose(after, 2.0 * before, rtol=1e-2)


@pytest.mark.parametrize("materials", [False, True])
def test_relight_batch_in_parts_equals_the_whole_batch(materials):
    """The viewport re-shades a batch over several steps (`relight_batch(part=)`): the parts
    together store exactly the lamp light (and materials) of one whole-batch re-shade, and the
    solve from them is the same."""
    s = CacheSettings(resolution=12, rays_per_cell=32, threads=2)
    results = []
    for parts in (1, 3):
        with GISystem(room_with_ball(), s) as gi:
            sol = gi.solver
            sol.min_chunks = 5  # several chunks per batch to split
            sol.begin(gi.surface_cells())
            sol.trace_batch(0)
            sol.trace_batch(1)
            sol.solve(16)
            gi.set_lights(room_with_ball(energy=450.0))
            for b in range(2):
                for i in range(parts):
                    sol.relight_batch(b, materials=materials, part=(i, parts) if parts > 1 else None)
            sol.solve(16)
            results.append(([c.e_lamp.copy() for c in sol.chunks], gi.cache.sh_indirect.copy()))
    assert len(results[0][0]) >= 10
    for a, b in zip(results[0][0], results[1][0], strict=True):
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(results[0][1], results[1][1])


def test_a_lamp_edit_sharing_the_materials_keeps_the_surface_table():
    """`set_lights` with a snapshot that shares the current materials list (a lamp edit) keeps
    the surface table's arrays; a new list (a material edit) replaces them and is shaded with."""
    import dataclasses  # noqa: PLC0415

    s = CacheSettings(resolution=6, rays_per_cell=16)
    snap = room_with_ball()
    with GISystem(snap, s) as gi:
        albedo = gi.surfaces.albedo
        lamp = dataclasses.replace(snap, lights=room_with_ball(energy=600.0).lights)
        gi.set_lights(lamp)
        assert gi.surfaces.albedo is albedo and gi.updater.scene.lights[0].power == 600.0
        dark = [dataclasses.replace(m, base_color=np.full(3, 0.1, np.float32)) for m in snap.materials]
        gi.set_lights(dataclasses.replace(lamp, materials=dark))
        assert gi.surfaces.albedo is not albedo
        np.testing.assert_allclose(gi.surfaces.albedo, 0.1)
