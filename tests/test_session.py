"""GISession: snapshot diffs become the cache's named events, localized to what changed."""

import numpy as np

from hybridgi_core.session import GISession
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Light, Material, ObjectInfo, World, concat_geometry, make_snapshot
from tests.shapes import box


def cube(lo, size, obj, inward=False):
    return box(lo, np.asarray(lo, np.float32) + np.float32(size), inward=inward, obj=obj)


def scene(ball_x=2.0, energy=300.0):
    room = cube([0, 0, 0], 10.0, 0, inward=True)
    ball = cube([ball_x, 4.5, 0.0], 1.0, 1)
    light = Light("POINT", np.ones(3), energy, np.array([[1, 0, 0, 5], [0, 1, 0, 5], [0, 0, 1, 8], [0, 0, 0, 1.0]]))
    return make_snapshot(concat_geometry([room, ball]), [Material()], [light], World(),
                         [ObjectInfo("room"), ObjectInfo("ball")])


SETTINGS = CacheSettings(resolution=20, rays_per_cell=16, hysteresis=0.9)


def test_moving_one_object_refreshes_only_cells_near_it():
    s = GISession(SETTINGS)
    assert s.sync(scene()).rebuilt
    s.system.warm_up(2)
    assert not s.sync(scene()).rebuilt  # identical snapshot: nothing to do
    assert s.system.cache.urgency.max() == 0

    first = s.sync(scene(ball_x=3.0))  # a static object starts moving: one rebuild, cache kept
    assert first.moved == ["ball"] and first.rebuilt
    assert s.system.cache.samples.max() > 0  # the cache survived the rebuild
    s.system.cache.urgency[:] = 0
    second = s.sync(scene(ball_x=4.0))  # now dynamic: no rebuild
    assert second.moved == ["ball"] and not second.rebuilt
    touched = np.flatnonzero(s.system.cache.urgency > 0)
    assert touched.size == second.touched_cells
    assert 0 < touched.size < 0.25 * s.system.cache.grid.count
    centres = s.system.cache.centers[touched]
    # Every refreshed cell lies within the influence radius of the ball's old or new box.
    r = s.system.cache.influence_radius()
    d = np.maximum(np.maximum(np.array([3.0, 4.5, 0.0]) - centres, centres - np.array([5.0, 5.5, 1.0])), 0)
    assert (np.linalg.norm(d, axis=1) <= r + 1e-4).all()
    # The tracer sees the ball at its new place.
    hits = s.system.tracer.intersect(np.array([[4.5, 0.5, 0.5]], np.float32), np.array([[0, 1.0, 0]], np.float32))
    assert abs(hits.t[0] - 4.0) < 1e-3
    s.close()


def test_light_change_raises_urgency_everywhere_but_keeps_geometry():
    s = GISession(SETTINGS)
    s.sync(scene())
    s.system.warm_up(2)
    tracer = s.system.tracer
    rep = s.sync(scene(energy=600.0))
    assert rep.lights_changed and not rep.rebuilt and not rep.moved
    assert s.system.tracer is tracer
    assert (s.system.cache.urgency >= 0.5).all()
    assert s.system.scene.lights[0].power == 600.0
    s.close()


def test_settings_change_rebuilds_with_fresh_cache():
    s = GISession(SETTINGS)
    s.sync(scene())
    s.system.warm_up(1)
    s.set_settings(SETTINGS.with_(resolution=10))
    assert s.sync(scene()).rebuilt
    assert s.system.cache.samples.max() == 0 and s.system.cache.grid.dims[0] == 10
    s.close()


def test_cells_inside_a_moving_object_are_not_shaded_and_restart_when_it_leaves():
    """Inside cells keep tracing (their inside test stays current) but take no radiance; a cell the
    object moves away from becomes valid again only after an update has shaded it."""
    big = 3.0
    def snap(x):
        room = cube([0, 0, 0], 10.0, 0, inward=True)
        block = cube([x, 3.5, 0.0], big, 1)
        light = Light("POINT", np.ones(3), 300.0, np.array([[1, 0, 0, 5], [0, 1, 0, 5], [0, 0, 1, 8], [0, 0, 0, 1.0]]))
        return make_snapshot(concat_geometry([room, block]), [Material()], [light], World(),
                             [ObjectInfo("room"), ObjectInfo("block")])

    s = GISession(SETTINGS)
    s.sync(snap(1.0))
    cache = s.system.cache
    everything = np.arange(cache.grid.count)
    s.system.update(everything, frame=0)
    s.system.update(everything, frame=1)
    inside = np.flatnonzero(cache.inside)
    assert inside.size > 0
    shaded_before = cache.samples[inside].copy()
    radiance = cache.sh_indirect[inside].copy()
    s.system.update(everything, frame=2)
    np.testing.assert_array_equal(cache.samples[inside], shaded_before)  # not shaded again
    np.testing.assert_array_equal(cache.sh_indirect[inside], radiance)  # radiance untouched
    outside = np.flatnonzero(~cache.inside & (cache.samples > 0))
    assert (cache.samples[outside] == 3).all()

    s.sync(snap(6.0))  # the block moves away: its old cells are open again
    s.system.update(everything, frame=3)
    freed = inside[~cache.inside[inside]]
    assert freed.size > 0
    assert (cache.samples[freed] == 0).all() and not cache.valid[freed].any()  # stale: not read
    s.system.update(everything, frame=4)
    assert cache.valid[freed].all() and (cache.samples[freed] == 1).all()
    s.close()


def test_new_holes_in_a_material_rebuild_the_rays_scene_and_keep_the_cache():
    """An alpha edit (`SceneChanges.cutouts_changed`) moves what rays hit: the ray scene is built
    again over the new holes, the cache kept, as for new triangles; a colour edit only re-shades."""
    from tests.test_cutout import _quad

    def screen_scene(alpha=None, colour=0.8):
        floor, screen = _quad(0.0, 1), _quad(1.0, 0)
        floor.object_index[:], screen.object_index[:] = 0, 1
        materials = [Material("screen", base_color=np.full(3, colour, np.float32), alpha=alpha), Material("floor")]
        light = Light("SUN", np.ones(3), 3.0, np.eye(4))
        return make_snapshot(concat_geometry([floor, screen]), materials, [light], World(),
                             [ObjectInfo("floor"), ObjectInfo("screen")])

    s = GISession(CacheSettings(resolution=8, rays_per_cell=8))
    assert s.sync(screen_scene()).rebuilt
    s.system.warm_up(1)
    down = np.array([[0, 0, -1.0]], np.float32)
    origin = np.array([[0.25, 0.5, 2.0]], np.float32)
    assert abs(s.system.tracer.intersect(origin, down).t[0] - 1.0) < 1e-3  # the screen is solid
    recoloured = s.sync(screen_scene(colour=0.3))
    assert recoloured.changes.colours_only and not recoloured.rebuilt
    holes = np.ones((4, 8), np.float32)
    holes[:, :4] = 0.0  # its left half cut out
    cut = s.sync(screen_scene(alpha=holes, colour=0.3))
    assert cut.changes.cutouts_changed and not cut.changes.colours_only
    assert cut.rebuilt and not cut.fresh and s.system.cache.samples.max() > 0  # the cache survived
    assert abs(s.system.tracer.intersect(origin, down).t[0] - 2.0) < 1e-3  # through the hole to the floor
    s.close()


def test_a_dynamic_objects_move_marks_the_same_stored_rays_through_the_session_as_moving_it_directly():
    """The session raises the diff's boxes once (`move_dynamic(invalidate=False)`): its stale
    rays and shadow marks hold every one the system's own invalidation of the moved triangles
    marks (here exactly those: the diff's boxes are the moved triangles')."""
    marks = []
    for through_session in (True, False):
        s = GISession(CacheSettings(resolution=12, rays_per_cell=16))
        s.sync(scene(ball_x=2.0))
        s.sync(scene(ball_x=2.5))  # the ball turns dynamic (one rebuild)
        s.system.solve(batches=1)
        for chunk in s.system.solver.chunks:
            chunk.lamp_stale[:] = False
        if through_session:
            report = s.sync(scene(ball_x=4.0))
            assert not report.rebuilt and report.moved == ["ball"]
        else:
            s.system.move_dynamic(scene(ball_x=4.0))
        marks.append([(c.ray_stale.copy(), c.lamp_stale.copy()) for c in s.system.solver.chunks])
        s.close()
    assert any(r.any() for r, _ in marks[0]) and any(lamp.any() for _, lamp in marks[0])
    for (ra, la), (rb, lb) in zip(marks[0], marks[1], strict=True):
        assert not (rb & ~ra).any() and not (lb & ~la).any()
        assert ra.sum() == rb.sum() and la.sum() == lb.sum()
