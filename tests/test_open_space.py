"""Cells the camera shares its space with are never inside geometry (hybridgi_core/open_space.py):
a room modelled with its normals facing out is lit as the same room facing in."""

from __future__ import annotations

import numpy as np

from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Light, Material, World, concat_geometry, make_snapshot
from hybridgi_core.system import GISystem
from tests.cli_renders import QUICK, cornell_variants, layer, rendered
from tests.shapes import box


def _lit_room(inward: bool):
    """A closed 2 m room (normals in, or out as a scaled default cube's) and a point lamp in it."""
    light = Light("POINT", np.ones(3), 300.0, np.array([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1.5], [0, 0, 0, 1]]))
    return make_snapshot(box([0, 0, 0], [2, 2, 2], inward=inward), [Material()], [light], World())


def test_a_room_with_its_normals_facing_out_is_lit_as_one_facing_in_once_the_camera_is_in_it():
    """Probe rays from inside a room whose faces point out meet only back faces, as inside a
    solid: every cell was switched off, and the room read no bounce light (a room of single-sided
    walls with a window against Cycles: Diffuse Indirect 65% low). Cycles shades both sides: with
    the camera in the room its cells are open space (`open_space.py`), and the room is lit as the
    same room facing in; seen from outside, the box's cells stay inside geometry."""
    s = CacheSettings(resolution=8, rays_per_cell=64)
    u = np.linspace(0.3, 1.7, 5, dtype=np.float32)
    a, b = (x.ravel() for x in np.meshgrid(u, u))
    floor = np.stack([a, b, np.zeros_like(a)], 1)
    up = np.tile([[0.0, 0.0, 1.0]], (a.size, 1)).astype(np.float32)
    light = {}
    for inward, eye in ((True, (1.0, 0.4, 1.0)), (False, (1.0, 0.4, 1.0)), (False, None)):
        with GISystem(_lit_room(inward), s) as gi:
            gi.viewpoint = eye
            gi.warm_up(4)
            light[inward, eye] = gi.gather(floor, up).indirect.mean()
            if eye is not None:
                assert gi.cache.valid[gi.solver.cells].mean() > 0.9
    facing_in = light[True, (1.0, 0.4, 1.0)]
    assert facing_in > 1.0
    assert abs(light[False, (1.0, 0.4, 1.0)] / facing_in - 1.0) < 0.1, light
    assert light[False, None] < 0.2 * facing_in, light  # no camera inside: the old dark room
    # A solid box seen from outside: its cells stay inside geometry.
    solid = make_snapshot(concat_geometry([box([0, 0, 0], [1, 1, 1], inward=False), box([-3, -3, -1], [4, 4, 3])]),
                          [Material()], [], World(color=(0.5, 0.5, 0.5)))
    with GISystem(solid, s) as gi:
        gi.viewpoint = (2.5, 2.5, 1.5)
        gi.warm_up(2)
        centres = gi.cache.centers
        within = np.all((centres > 0.05) & (centres < 0.95), axis=1)
        assert within.any() and gi.cache.inside[within].all()
        assert not gi.cache.open[within].any()


def test_the_cornell_box_with_every_normal_flipped_renders_as_the_cornell_box(tmp_path):
    """Through the real engine: the Cornell box with every face's normal flipped (Cycles renders
    both the same) keeps its bounce light. Measured at 160x120 (quick settings): Diffuse Indirect
    mean 0.1558, flipped 0.0752 before (its cells switched off as inside geometry), 0.1373 with the
    cells the camera sees open, 0.1572 with their open neighbours too (the cells behind the blocks);
    Diffuse Direct the same. 640x360, default settings, flipped against unflipped: Combined 0.0925
    -> 0.0029."""
    cornell_variants(tmp_path, "bpy.ops.wm.open_mainfile(filepath=src)\n"
                               "for m in bpy.data.meshes:\n    m.flip_normals()\n"
                               "bpy.ops.wm.save_as_mainfile(filepath=out + '/flipped.blend')\n")
    means = {}
    for name in ("cornell", "flipped"):
        channels = rendered(tmp_path / f"{name}.blend", tmp_path / name, "160x120", *QUICK)
        means[name] = [float(layer(channels, p).mean()) for p in ("Diffuse Indirect", "Diffuse Direct")]
    (di, dd), (di_flipped, dd_flipped) = means["cornell"], means["flipped"]
    assert di > 0.05 and abs(dd_flipped / dd - 1.0) < 0.02, means
    assert abs(di_flipped / di - 1.0) < 0.05, means


def test_a_geometry_event_closes_the_cells_near_it_and_the_open_ones_open_again_at_once():
    """A geometry event closes the cells near it (the change may have shut a space); those still in
    the camera's space open again at once, the ones behind an occluder too (from their open
    neighbours), not at the next traced batch, which a change leaving every stored ray as it was
    never brings: the room would keep a dark hole around an edited object."""
    room = box([0, 0, 0], [4, 4, 2], inward=False)
    block = box([2.2, 1.2, 0], [2.8, 2.8, 1.5], inward=False, obj=1)
    light = Light("POINT", np.ones(3), 300.0, np.array([[1, 0, 0, 1], [0, 1, 0, 1], [0, 0, 1, 1.5], [0, 0, 0, 1]]))
    scene = make_snapshot(concat_geometry([room, block]), [Material()], [light], World())
    with GISystem(scene, CacheSettings(resolution=12, rays_per_cell=32)) as gi:
        gi.viewpoint = (0.5, 2.0, 1.0)
        gi.warm_up(2)
        behind = (gi.cache.centers[:, 0] > 3.0) & (gi.cache.centers[:, 2] < 1.4)  # hidden by the block
        opened = gi.cache.open.copy()
        assert opened[behind].any()  # reached from the open neighbours around the block
        valid = gi.cache.valid.copy()
        gi.on_geometry_changed([(np.array([2.2, 1.2, 0.0]), np.array([2.8, 2.8, 1.5]))])
        np.testing.assert_array_equal(gi.cache.open, opened)
        np.testing.assert_array_equal(gi.cache.valid, valid)
