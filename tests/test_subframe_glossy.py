"""The glossy light a jittered subframe's samples take (hybridgi_core/raster/subframe_glossy.py):
the centre pixel's where they see its surface, a neighbour's where they see the neighbour's."""

from __future__ import annotations

import numpy as np

from hybridgi_core.raster.subframe_glossy import subframe_glossy
from hybridgi_core.raster.subpixel import CentreSample, subframe_surfaces

H, W = 3, 4


def _centre():
    """A plane z = 0 facing +z over columns 0-1 (pixel x at x = 0.01 x metres), background over
    columns 2-3; its glossy light 5 per pixel, 0 on the background."""
    position = np.zeros((H, W, 4), np.float32)
    normal = np.zeros((H, W, 4), np.float32)
    y, x = np.mgrid[0:H, 0:W]
    position[..., 0], position[..., 1] = 0.01 * x, 0.01 * y
    position[:, :2, 3] = 1.0
    normal[:, :2, 2] = 1.0
    depth = np.full(H * W, 5.0, np.float32)
    centre = CentreSample(np.zeros((H * W, 4), np.float32), position.reshape(-1, 4), normal.reshape(-1, 4), depth)
    glossy = np.zeros((H * W, 4), np.float32)
    glossy[(position[..., 3] > 0.5).reshape(-1), :3] = 5.0
    return centre, glossy, position, normal


def test_a_sample_past_the_silhouette_takes_its_surfaces_light():
    centre, glossy, position, normal = _centre()
    sub_pos, sub_nrm = position.copy(), normal.copy()
    # The subframe sees the plane reach into column 2 of the middle row.
    sub_pos[1, 2] = (0.02, 0.01, 0.0, 1.0)
    sub_nrm[1, 2] = (0.0, 0.0, 1.0, 0.0)
    hit, same = subframe_surfaces(centre, sub_pos, sub_nrm)
    assert hit[1 * W + 2] and not same[1 * W + 2]
    out = subframe_glossy(glossy, centre, hit, same, sub_pos, sub_nrm, W)
    assert np.allclose(out[1 * W + 2, :3], 5.0)
    # Only that pixel changed.
    changed = np.flatnonzero((out != glossy).any(axis=1))
    assert changed.tolist() == [1 * W + 2]


def test_a_sample_on_the_surface_behind_a_silhouette_leaves_the_object_light():
    """A subframe that sees a far wall (facing -x) where the centre saw the plane: no neighbour's
    surface is the wall and no normal is within FALLBACK_COS of it, so the pixel keeps its own
    light (what it did before); a subframe that sees the centre's surfaces changes nothing."""
    centre, glossy, position, normal = _centre()
    hit, same = subframe_surfaces(centre, position, normal)
    assert subframe_glossy(glossy, centre, hit, same, position, normal, W) is None
    sub_pos, sub_nrm = position.copy(), normal.copy()
    sub_pos[1, 1] = (3.0, 0.01, 0.0, 1.0)
    sub_nrm[1, 1] = (-1.0, 0.0, 0.0, 0.0)
    hit, same = subframe_surfaces(centre, sub_pos, sub_nrm)
    assert hit[1 * W + 1] and not same[1 * W + 1]
    assert subframe_glossy(glossy, centre, hit, same, sub_pos, sub_nrm, W) is None


def test_a_metal_rims_light_moves_to_the_pixels_its_subframes_see_it_in():
    """The neighbour on the sample's surface wins over one searched before it on another surface:
    a sample of the plane in a background pixel between the plane (left) and a wall (right)
    takes the plane's light."""
    centre, glossy, position, normal = _centre()
    # Column 3, row 1 of the centre becomes a wall facing -y at y = 0.5 with its own light 1.
    pos = centre.position.reshape(H, W, 4)
    nrm = centre.normal.reshape(H, W, 4)
    pos[1, 3] = (0.03, 0.5, 0.0, 1.0)
    nrm[1, 3] = (0.0, -1.0, 0.0, 0.0)
    glossy[1 * W + 3, :3] = 1.0
    sub_pos, sub_nrm = pos.copy(), nrm.copy()
    sub_pos[1, 2] = (0.02, 0.01, 0.0, 1.0)
    sub_nrm[1, 2] = (0.0, 0.0, 1.0, 0.0)
    hit, same = subframe_surfaces(centre, sub_pos, sub_nrm)
    out = subframe_glossy(glossy, centre, hit, same, sub_pos, sub_nrm, W)
    assert np.allclose(out[1 * W + 2, :3], 5.0)
