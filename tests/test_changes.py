"""The snapshot diff (hybridgi_core/changes.py) and the cache events GISession.sync raises from it,
with hand-made snapshots: no Blender."""

import dataclasses

import numpy as np
import pytest

from hybridgi_core.changes import diff_snapshots, object_boxes
from hybridgi_core.session import GISession
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Light, Material, ObjectInfo, World, concat_geometry, make_snapshot
from tests.shapes import box


def _light(x=5.0, energy=300.0):
    m = np.eye(4)
    m[:3, 3] = (x, 5.0, 8.0)
    return Light("POINT", np.ones(3), energy, m)


def _scene(objects, lights=None, world=None, materials=None):
    """objects : [(name, Geometry)] in order; object indices are assigned here."""
    parts = [dataclasses.replace(g, object_index=np.full(g.triangle_count, i, np.int32))
             for i, (_name, g) in enumerate(objects)]
    return make_snapshot(concat_geometry(parts), materials or [Material("grey")],
                         [_light()] if lights is None else lights, world or World(),
                         [ObjectInfo(name) for name, _g in objects])


def _cube(lo, size=1.0):
    lo = np.asarray(lo, np.float32)
    return box(lo, lo + np.float32(size), inward=False)


ROOM = ("room", box([0, 0, 0], [10, 10, 10]))


def test_identical_snapshots_have_no_changes():
    a = _scene([ROOM, ("ball", _cube([2, 4, 0]))])
    b = _scene([ROOM, ("ball", _cube([2, 4, 0]))])
    changes = diff_snapshots(a, b)
    assert not changes.any and changes.boxes == [] and changes.light_flux_change == 0.0


def test_first_snapshot_is_all_appeared():
    s = _scene([ROOM, ("ball", _cube([2, 4, 0]))])
    changes = diff_snapshots(None, s)
    assert changes.appeared == ["room", "ball"] and changes.topology_changed
    assert len(changes.boxes) == 2


def test_translation_and_rotation_are_moves_with_old_and_new_boxes():
    ball = _cube([2, 4, 0])
    moved = dataclasses.replace(ball, positions=ball.positions + np.float32([1.5, 0, 0]))
    changes = diff_snapshots(_scene([ROOM, ("ball", ball)]), _scene([ROOM, ("ball", moved)]))
    assert changes.moved == ["ball"] and changes.deformed == [] and not changes.topology_changed
    (lo0, hi0), (lo1, hi1) = changes.boxes
    np.testing.assert_allclose(lo0, [2, 4, 0]) and np.testing.assert_allclose(hi1, [4.5, 5, 1])
    np.testing.assert_allclose(hi0, [3, 5, 1]) and np.testing.assert_allclose(lo1, [3.5, 4, 0])

    c, s = np.cos(0.7), np.sin(0.7)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float32)
    turned = dataclasses.replace(ball, positions=(ball.positions @ rot.T).astype(np.float32))
    assert diff_snapshots(_scene([ROOM, ("ball", ball)]), _scene([ROOM, ("ball", turned)])).moved == ["ball"]


def test_a_vertex_pulled_out_is_a_deformation():
    ball = _cube([2, 4, 0])
    positions = ball.positions.copy()
    corner = np.flatnonzero((positions == np.float32([3, 5, 1])).all(axis=1))
    positions[corner] += np.float32([0, 0, 0.5])
    changes = diff_snapshots(_scene([ROOM, ("ball", ball)]),
                             _scene([ROOM, ("ball", dataclasses.replace(ball, positions=positions))]))
    assert changes.deformed == ["ball"] and changes.moved == []
    assert changes.displaced == ["ball"]


def test_appeared_vanished_and_retopologised_objects_are_named_with_their_boxes():
    old = _scene([ROOM, ("ball", _cube([2, 4, 0])), ("gone", _cube([7, 7, 7]))])
    bigger = concat_geometry([_cube([2, 4, 0]), _cube([2, 4, 2])])  # same name, more triangles
    new = _scene([ROOM, ("ball", bigger), ("new", _cube([5, 1, 1], 0.5))])
    changes = diff_snapshots(old, new)
    assert changes.appeared == ["new"] and changes.vanished == ["gone"]
    assert changes.retopologised == ["ball"] and changes.topology_changed
    assert changes.moved == [] and changes.deformed == []
    boxes = {(tuple(np.round(lo, 3)), tuple(np.round(hi, 3))) for lo, hi in changes.boxes}
    assert ((7, 7, 7), (8, 8, 8)) in boxes  # where "gone" was
    assert ((5, 1, 1), (5.5, 1.5, 1.5)) in boxes  # where "new" is
    assert ((2, 4, 0), (3, 5, 3)) in boxes  # the re-topologised ball where it is now
    assert not any(lo[0] == 0 and hi[0] == 10 for lo, hi in changes.boxes)  # the room did not change


def test_reordered_objects_with_the_same_geometry_have_no_geometry_change():
    a, b = ("a", _cube([1, 1, 1])), ("b", _cube([6, 6, 6]))
    changes = diff_snapshots(_scene([ROOM, a, b]), _scene([ROOM, b, a]))
    assert not changes.geometry_changed


def test_light_changes_say_how_far_the_light_jumped():
    geo = [ROOM, ("ball", _cube([2, 4, 0]))]
    base = _scene(geo)
    brighter = diff_snapshots(base, _scene(geo, lights=[_light(energy=330.0)]))
    assert brighter.lights_changed and not brighter.geometry_changed
    assert brighter.light_flux_change == pytest.approx(30 / 330, rel=1e-6)
    assert not brighter.light_jumped(reach=1.0, threshold=0.25)
    doubled = diff_snapshots(base, _scene(geo, lights=[_light(energy=600.0)]))
    assert doubled.light_jumped(reach=1.0, threshold=0.25)
    moved = diff_snapshots(base, _scene(geo, lights=[_light(x=7.0)]))
    assert moved.light_moved == pytest.approx(2.0) and moved.light_jumped(reach=1.0, threshold=0.25)
    assert not moved.light_jumped(reach=3.0, threshold=0.25)
    added = diff_snapshots(base, _scene(geo, lights=[_light(), _light(x=1.0)]))
    assert added.light_flux_change == float("inf")


def test_world_and_material_changes_are_named():
    geo = [ROOM]
    base = _scene(geo, materials=[Material("grey"), Material("lamp")])
    sky = diff_snapshots(base, _scene(geo, world=World(color=np.full(3, 0.5, np.float32)),
                                      materials=[Material("grey"), Material("lamp")]))
    assert sky.world_changed and not sky.lights_changed and sky.shading_changed
    glowing = Material("lamp", emission=np.full(3, 4.0, np.float32))
    lit = diff_snapshots(base, _scene(geo, materials=[Material("grey"), glowing]))
    assert lit.materials_changed == ["lamp"] and lit.light_flux_change == 1.0
    # One material baked on two meshes is two materials of one name: unchanged, it is no change.
    twice = [Material("grey"), Material("noise", bake_id="a"), Material("noise", bake_id="b")]
    assert diff_snapshots(_scene(geo, materials=twice), _scene(geo, materials=list(twice))).materials_changed == []



def test_a_diffuse_colour_edit_is_told_apart_from_other_material_edits():
    """`colours_only`: the changed materials differ in their base colour or their colour
    texture's texels only (the viewport lights such an edit again as a lamp's, keeping the view)."""
    geo = [ROOM]
    texels = np.full((4, 4, 3), 0.5, np.float32)
    base = _scene(geo, materials=[Material("grey"), Material("wood", texture=texels)])

    def edit(**changes):
        materials = [Material("grey"), dataclasses.replace(base.materials[1], **changes)]
        return diff_snapshots(base, _scene(geo, materials=materials))

    for colour_edit in (edit(base_color=np.array([0.1, 0.2, 0.7], np.float32)), edit(texture=texels * 0.5)):
        assert colour_edit.materials_changed == ["wood"] and colour_edit.colours_only
        assert not colour_edit.lights_changed and colour_edit.light_flux_change == 0.0
    for other in (edit(texture=np.full((8, 8, 3), 0.5, np.float32)),  # another image
                  edit(texture=None), edit(emission=np.full(3, 2.0, np.float32)), edit(clear=True),
                  edit(alpha=np.ones((4, 4), np.float32))):
        assert other.materials_changed == ["wood"] and not other.colours_only
    assert not diff_snapshots(base, base).colours_only  # nothing changed: no colour edit either
    added = diff_snapshots(base, _scene(geo, materials=[*base.materials, Material("new")]))
    assert added.materials_changed == ["new"] and not added.colours_only
    both = diff_snapshots(base, _scene(geo, lights=[_light(x=3.0)], materials=[Material("grey"),
                                       dataclasses.replace(base.materials[1], base_color=np.zeros(3, np.float32))]))
    assert both.lights_changed and both.colours_only

def test_object_boxes_in_one_pass_match_per_object_boxes():
    rng = np.random.default_rng(3)
    objects = [(f"o{i}", _cube(rng.uniform(0, 9, 3), rng.uniform(0.1, 1))) for i in range(50)]
    s = _scene(objects)
    boxes = object_boxes(s)
    for i, (name, g) in enumerate(objects):
        np.testing.assert_allclose(boxes[name][0], g.positions.min(axis=0))
        np.testing.assert_allclose(boxes[name][1], g.positions.max(axis=0))
        assert (s.geometry.object_index == i).sum() == g.triangle_count


# --- GISession raises the events itself ------------------------------------------------------------

SETTINGS = CacheSettings(resolution=12, rays_per_cell=8, hysteresis=0.9)


def test_session_raises_geometry_events_for_appearing_and_vanishing_objects():
    """The cache is kept across the rebuild, and only cells near what appeared or vanished
    re-converge: no owner has to add boxes of its own."""
    s = GISession(SETTINGS)
    first = s.sync(_scene([ROOM, ("gone", _cube([1, 1, 1]))]))
    assert first.rebuilt and first.fresh and first.touched_cells == 0
    s.system.warm_up(2)
    cache = s.system.cache
    report = s.sync(_scene([ROOM, ("new", _cube([8, 8, 8]))]))
    assert report.rebuilt and not report.fresh and s.system.cache is cache
    assert report.changes.appeared == ["new"] and report.changes.vanished == ["gone"]
    touched = np.flatnonzero(cache.urgency > 0)
    assert 0 < touched.size == report.touched_cells < cache.grid.count
    assert set(touched) == set(report.touched)
    s.close()


def test_session_raises_light_events_with_a_topology_change_too():
    s = GISession(SETTINGS)
    s.sync(_scene([ROOM]))
    s.system.warm_up(1)
    report = s.sync(_scene([ROOM, ("new", _cube([8, 8, 8]))], lights=[_light(energy=900.0)]))
    assert report.rebuilt and report.lights_changed
    assert s.system.cache.urgency.min() >= 0.5  # every cell re-converges at the raised weight
    s.close()


def test_session_new_settings_start_a_fresh_cache():
    s = GISession(SETTINGS)
    s.sync(_scene([ROOM]))
    s.system.warm_up(1)
    s.set_settings(dataclasses.replace(SETTINGS, rays_per_cell=16))
    report = s.sync(_scene([ROOM]))
    assert report.fresh and not s.system.cache.samples.any()
    s.close()


def test_a_material_swapped_on_unmoved_triangles_reaches_the_rays():
    """A slot given another material (or UVs or smoothing edited) changes no position: the diff
    said nothing had changed, so the session kept the surface table of the old materials and
    the cache the light of the old colour (a live view 7.7% off a new one, Cornell box)."""
    ball = _cube([2, 4, 0])
    red = Material("red", base_color=np.float32([0.8, 0.1, 0.1]))
    grey = _scene([ROOM, ("ball", ball)], materials=[Material("grey"), red])
    recoloured = _scene([ROOM, ("ball", ball)], materials=[Material("grey"), red])
    recoloured.geometry.material_index[recoloured.geometry.object_index == 1] = 1
    changes = diff_snapshots(grey, recoloured)
    assert changes.resurfaced == ["ball"] and changes.shading_changed and not changes.geometry_changed
    smoothed = _scene([ROOM, ("ball", ball)], materials=[Material("grey"), red])
    rows = np.unique(smoothed.geometry.triangles[smoothed.geometry.object_index == 1])
    smoothed.geometry.normals[rows] = smoothed.geometry.normals[rows][::-1]
    assert diff_snapshots(grey, smoothed).resurfaced == ["ball"]
    # The same materials listed in another order: the same surfaces.
    reordered = _scene([ROOM, ("ball", ball)], materials=[red, Material("grey")])
    reordered.geometry.material_index[:] = 1
    assert not diff_snapshots(grey, reordered).any

    s = GISession(SETTINGS)
    s.sync(grey)
    s.system.warm_up(1)
    report = s.sync(recoloured)
    table = s.system.surfaces
    assert np.array_equal(table.material_index, recoloured.geometry.material_index)
    assert not report.fresh and s.system.cache.urgency.min() >= 0.5  # re-lit like a colour edit
    s.close()
