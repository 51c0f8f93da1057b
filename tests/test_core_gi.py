"""The cache end to end on analytic scenes: furnace, closed-box AO, leaks, determinism, bad input."""

import subprocess
import sys

import numpy as np
import pytest

from hybridgi_core.errors import EmptySceneError
from hybridgi_core.settings import AO_ONLY, CacheSettings
from hybridgi_core.snapshot import (
    Light,
    Material,
    ObjectInfo,
    World,
    concat_geometry,
    geometry_from_arrays,
    make_snapshot,
)
from hybridgi_core.system import GISystem
from tests.shapes import box


def furnace_scene(albedo, emission):
    mat = Material("furnace", np.full(3, albedo, np.float32), None, np.full(3, emission, np.float32))
    return make_snapshot(box([0, 0, 0], [2, 2, 2]), [mat])


@pytest.mark.parametrize("h", [0.0, 0.5])
def test_furnace_converges_to_analytic_multibounce(h):
    """Closed box, uniform emission Le and albedo rho: radiance everywhere Le / (1 - rho).

    A cell receives E_direct = pi Le straight from the walls and E_indirect = pi rho Le / (1 - rho)
    bounced; the cache must converge to both (tolerance 0.5%: only float error and the EMA tail).
    """
    rho, le = 0.5, 1.0
    s = CacheSettings(resolution=4, rays_per_cell=64, hysteresis=h)
    with GISystem(furnace_scene(rho, le), s) as gi:
        gi.warm_up(60 if h else 30)
        # Points on the floor and on a wall, as the G-buffer would give them.
        u = np.linspace(0.1, 1.9, 7, dtype=np.float32)
        a, b = (x.ravel() for x in np.meshgrid(u, u))
        floor = np.stack([a, b, np.zeros_like(a)], 1)
        wall = np.stack([np.full_like(a, 2.0), a, b], 1)
        points = np.concatenate([floor, wall])
        normals = np.concatenate([np.tile([[0.0, 0, 1]], (a.size, 1)), np.tile([[-1.0, 0, 0]], (a.size, 1))]).astype(np.float32)
        g = gi.gather(points, normals)
    np.testing.assert_allclose(g.direct, np.pi * le, rtol=5e-3)
    np.testing.assert_allclose(g.indirect, np.pi * rho * le / (1 - rho), rtol=5e-3)
    assert ((g.ao >= 0) & (g.ao <= 1)).all()


def test_ao_closed_box_is_zero_and_open_space_is_one():
    s = CacheSettings(resolution=4, rays_per_cell=64, ao_distance=10.0, indirect_quality=AO_ONLY)
    with GISystem(make_snapshot(box([0, 0, 0], [2, 2, 2]), [Material()]), s) as gi:
        gi.warm_up(2)
        u = np.linspace(0.1, 1.9, 6, dtype=np.float32)
        a, b = (x.ravel() for x in np.meshgrid(u, u))
        floor = np.stack([a, b, np.zeros_like(a)], 1)
        up = np.tile([[0.0, 0.0, 1.0]], (a.size, 1)).astype(np.float32)
        np.testing.assert_allclose(gi.gather(floor, up).ao, 0.0, atol=1e-6)

    # A small floor tile, AO distance shorter than the distance to it: everything open.
    tile = geometry_from_arrays([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
    s = s.with_(ao_distance=0.05, resolution=2)
    with GISystem(make_snapshot(tile, [Material()]), s) as gi:
        gi.warm_up(2)
        up = np.tile([[0.0, 0.0, 1.0]], (4, 1)).astype(np.float32)
        pts = np.array([[0.25, 0.25, 0.0], [0.75, 0.75, 0.0], [0.5, 0.5, 0.0], [0.2, 0.8, 0.0]], np.float32)
        np.testing.assert_allclose(gi.gather(pts, up).ao, 1.0, atol=0.02)


def two_rooms():
    """Two closed 2 m rooms sharing a 2 cm wall; a point light in the left room only."""
    left = box([-2.01, 0, 0], [-0.01, 2, 2])
    right = box([0.01, 0, 0], [2.01, 2, 2], obj=1)
    light = Light("POINT", np.ones(3), 500.0, np.array([[1, 0, 0, -1], [0, 1, 0, 1], [0, 0, 1, 1.5], [0, 0, 0, 1]]))
    return make_snapshot(concat_geometry([left, right]), [Material()], [light], World(),
                         [ObjectInfo("left"), ObjectInfo("right")])


def test_no_light_leaks_through_a_thin_wall():
    s = CacheSettings(resolution=16, rays_per_cell=64, hysteresis=0.5)
    with GISystem(two_rooms(), s) as gi:
        gi.warm_up(8)
        ys = np.linspace(0.3, 1.7, 8)
        up = np.tile([[0.0, 0.0, 1.0]], (8, 1)).astype(np.float32)
        lit = np.stack([np.full(8, -0.05), ys, np.full(8, 0.0)], 1).astype(np.float32)
        dark = lit * np.array([-1, 1, 1], np.float32)
        e_lit = gi.gather(lit, up).indirect.mean()
        e_dark = gi.gather(dark, up).indirect.mean()
        from hybridgi_core.evaluate import gather

        e_leaky = gather(gi.cache, dark, up, visibility=False).indirect.mean()
    assert e_lit > 1.0  # the lit room does receive bounce light next to the wall
    assert e_dark < 0.01 * e_lit, (e_dark, e_lit)
    # Without the visibility test the same points leak: proves the test can fail.
    assert e_leaky > 0.2 * e_lit, (e_leaky, e_lit)


def test_same_seed_same_cache_and_other_seed_differs():
    def run(seed):
        s = CacheSettings(resolution=8, rays_per_cell=16, seed=seed, threads=2)
        with GISystem(two_rooms(), s) as gi:
            gi.warm_up(3)
            return gi.cache.sh_indirect.copy(), gi.cache.depth.copy()

    a, b, c = run(1), run(1), run(2)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], c[0])


def test_empty_and_degenerate_scenes_raise_clear_errors():
    empty = geometry_from_arrays(np.zeros((0, 3)), np.zeros((0, 3), int))
    with pytest.raises(EmptySceneError):
        GISystem(make_snapshot(empty, [Material()]), CacheSettings())
    degenerate = geometry_from_arrays([[0, 0, 0], [1, 1, 1], [2, 2, 2], [np.nan, 0, 0]], [[0, 1, 2], [0, 1, 3]])
    snap = make_snapshot(degenerate, [Material()])
    assert snap.geometry.triangle_count == 0
    with pytest.raises(EmptySceneError):
        GISystem(snap, CacheSettings())


def test_nan_triangles_dropped_rest_still_traced():
    good = box([0, 0, 0], [1, 1, 1])
    bad = geometry_from_arrays([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]])
    snap = make_snapshot(concat_geometry([good, bad]), [Material("m", np.full(3, 0.5, np.float32), None, np.ones(3, np.float32))])
    assert snap.geometry.triangle_count == 12
    with GISystem(snap, CacheSettings(resolution=2, rays_per_cell=16)) as gi:
        gi.warm_up(2)
        assert np.isfinite(gi.cache.sh_direct).all() and gi.cache.sh_direct[:, 0].max() > 0


def test_no_lights_black_world_gives_zero_light_not_an_error():
    with GISystem(make_snapshot(box([0, 0, 0], [1, 1, 1]), [Material()]), CacheSettings(resolution=4, rays_per_cell=8)) as gi:
        gi.warm_up(2)
        g = gi.gather(gi.cache.centers, np.tile([[0, 0, 1.0]], (gi.cache.grid.count, 1)).astype(np.float32))
        assert (g.direct == 0).all() and (g.indirect == 0).all()
        assert (gi.direct(gi.cache.centers, np.tile([[0, 0, 1.0]], (gi.cache.grid.count, 1)), frame=0) == 0).all()


def test_sky_reaches_a_floor_as_direct_light():
    """An open floor under a uniform sky of radiance L: irradiance pi L arrives as Direct."""
    floor = geometry_from_arrays([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], [[0, 1, 2], [0, 2, 3]])
    snap = make_snapshot(floor, [Material()], [], World(np.full(3, 0.5, np.float32)))
    with GISystem(snap, CacheSettings(resolution=8, rays_per_cell=256, hysteresis=0.0)) as gi:
        gi.warm_up(1)
        pts = np.array([[0, 0, 0], [1, 2, 0], [-3, 1, 0]], np.float32)
        up = np.tile([[0, 0, 1.0]], (3, 1)).astype(np.float32)
        g = gi.gather(pts, up)
    # L2 SH of a hemisphere step rings a little; 3% is well within what the cache can resolve.
    np.testing.assert_allclose(g.direct, np.pi * 0.5, rtol=0.03)
    # The floor reflects 0.8 * 0.5 back up, but only onto the floor's own back side: nothing indirect.
    assert g.indirect.max() < 0.02


def test_core_imports_without_blender():
    code = (
        "import sys\n"
        "class Block:\n"
        "    def find_spec(self, name, path=None, target=None):\n"
        "        if name.split('.')[0] in ('bpy', 'gpu', 'mathutils', 'bmesh'):\n"
        "            raise ImportError('blocked: ' + name)\n"
        "sys.meta_path.insert(0, Block())\n"
        "import hybridgi_core.system, hybridgi_core.evaluate, hybridgi_core.update, hybridgi_core.lod\n"
        "import hybridgi_core.trace.reference, hybridgi_core.trace.embree, hybridgi_core.visible\n"
        "print('ok')\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


def test_cell_debug_colors_mark_cells_and_their_state():
    from hybridgi_core.visible import cell_debug_colors

    with GISystem(make_snapshot(box([0, 0, 0], [2, 2, 2]), [Material()]), CacheSettings(resolution=4, rays_per_cell=8)) as gi:
        pts = np.array([[0.3, 0.3, 0.0], [1.7, 1.7, 0.0]], np.float32)
        up = np.tile([[0, 0, 1.0]], (2, 1)).astype(np.float32)
        assert (cell_debug_colors(gi.cache, pts, up) == 0.05).all()  # nothing sampled yet: dark
        gi.warm_up(1)
        young = cell_debug_colors(gi.cache, pts, up)
        assert not np.allclose(young[0], young[1])  # different cells, different colours
        gi.warm_up(20, start=1, total=21)
        old = cell_debug_colors(gi.cache, pts, up)
        np.testing.assert_allclose(old, 2 * young, rtol=1e-5)  # converged cells at full brightness


def test_direct_light_split_over_workers_matches_one_call():
    """`GISystem.direct` cuts large calls into blocks for the worker pool: a hard point lamp (no
    random samples) gives exactly the single call's light, shadows included; an area lamp's
    blocks draw other samples, so it agrees in the mean (and is repeatable)."""
    from hybridgi_core.lights import direct_irradiance
    from hybridgi_core.sampling import frame_rng
    from hybridgi_core.system import DIRECT_BLOCK_RAYS

    area = np.eye(4)
    area[:3, 3] = (1.0, 1.0, 1.9)
    lamps = [Light("POINT", np.ones(3), 300.0, np.array([[1, 0, 0, 1.5], [0, 1, 0, 0.5], [0, 0, 1, 1.5], [0, 0, 0, 1.0]])),
             Light("AREA", np.ones(3), 50.0, area, size=0.5)]
    blocker = box([0.8, 0.8, 0.9], [1.2, 1.2, 1.0], inward=False, obj=1)
    geo = concat_geometry([box([0, 0, 0], [2, 2, 2]), blocker])
    objects = [ObjectInfo("room"), ObjectInfo("blocker")]
    rng = np.random.default_rng(5)
    n = 3 * DIRECT_BLOCK_RAYS // 4 + 17  # 4 samples: three blocks and a bit
    pts = np.column_stack([rng.uniform(0.05, 1.95, (n, 2)), np.full(n, 1e-3)]).astype(np.float32)
    nrm = np.tile(np.float32([[0, 0, 1]]), (n, 1))
    for lamp, exact in ((lamps[0], True), (lamps[1], False)):
        snap = make_snapshot(geo, [Material()], lights=[lamp], objects=objects)
        with GISystem(snap, CacheSettings(resolution=4, rays_per_cell=8)) as gi:
            split = gi.direct(pts, nrm, frame=3, samples=4)
            one = direct_irradiance([lamp], pts, nrm, gi.tracer, frame_rng(gi.settings.seed + 1, 3), samples=4,
                                    epsilon=float(gi.tracer.epsilon))
            assert split.shape == (n, 3) and (one == 0).any() and (one > 0).any()  # shadowed and lit
            if exact:
                np.testing.assert_array_equal(split, one)
            else:
                np.testing.assert_allclose(split.mean(), one.mean(), rtol=0.01)
                np.testing.assert_array_equal(split, gi.direct(pts, nrm, frame=3, samples=4))


def test_corner_visibility_split_over_workers_is_the_single_call(monkeypatch):
    """`GISystem.corner_visibility` traces blocks of points on the worker pool: the same mask as
    one call, occluded corners included."""
    from hybridgi_core import system as system_mod
    from hybridgi_core.evaluate import corner_visibility

    monkeypatch.setattr(system_mod, "VISIBILITY_BLOCK", 100)
    blocker = box([0.8, 0.8, 0.2], [1.2, 1.2, 1.6], inward=False, obj=1)
    snap = make_snapshot(concat_geometry([box([0, 0, 0], [2, 2, 2]), blocker]), [Material()],
                         objects=[ObjectInfo("room"), ObjectInfo("blocker")])
    rng = np.random.default_rng(2)
    # Points around the blocker, facing every way: some of their corner cells lie behind it.
    pts = rng.uniform(0.6, 1.4, (1050, 3)).astype(np.float32)
    nrm = rng.normal(size=(1050, 3)).astype(np.float32)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    with GISystem(snap, CacheSettings(resolution=8, rays_per_cell=8)) as gi:
        split = gi.corner_visibility(pts, nrm)
        one = corner_visibility(gi.cache, gi.tracer, pts, nrm, float(gi.tracer.epsilon))
    assert split.shape == (1050, 8) and one.any() and not one.all()
    np.testing.assert_array_equal(split, one)

