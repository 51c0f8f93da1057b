"""Curves (hair) as tubes (`hybridgi_core.hair`): bpy-free."""

from __future__ import annotations

import numpy as np

from hybridgi_core import hair


def strands(n=3, k=4):
    points = np.zeros((n, k, 3), np.float32)
    points[..., 0] = np.arange(n)[:, None]
    points[..., 2] = np.arange(k)[None, :] * 0.5
    return points.reshape(-1, 3), np.arange(0, n * k + 1, k), np.full(n * k, 0.1, np.float32)


def test_tubes_wind_outwards_around_each_strand():
    points, offsets, radii = strands()
    t = hair.tubes(points, offsets, radii)
    assert t.thinned == 1 and t.triangles.shape == (3 * 3 * 2 * hair.SIDES, 3)
    p = t.positions[t.triangles].astype(np.float64)
    facet = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    centre = p.mean(axis=1)
    axis = np.stack([np.round(centre[:, 0]), np.zeros(len(centre)), centre[:, 2]], 1)  # on the strand's line
    assert (np.einsum("ij,ij->i", facet, centre - axis) > 0).all()  # front faces look away from the strand
    ring = np.linalg.norm(t.positions[:, :2] - np.round(t.positions[:, :1]) * [1, 0], axis=1)
    np.testing.assert_allclose(ring, 0.1, rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(t.normals, axis=1), 1.0, rtol=1e-5)
    assert t.source.tolist() == sorted(t.source.tolist()) and set(t.source.tolist()) == {0, 1, 2}


def test_single_point_strands_and_nan_points_give_nothing():
    points, offsets, radii = strands(2, 3)
    t = hair.tubes(points[:4], np.array([0, 1, 4]), radii[:4])  # strand 0 has one point
    assert set(t.source.tolist()) == {1}
    points[1] = np.nan  # its neighbours' tangents go with it: strand 0 is dropped, strand 1 kept
    t = hair.tubes(points, offsets, radii)
    assert np.isfinite(t.positions[t.triangles]).all() and set(t.source.tolist()) == {1}
    assert t.triangles.shape[0] == 2 * 2 * hair.SIDES


def test_too_many_strands_get_fewer_sides_then_are_thinned_and_widened():
    points, offsets, radii = strands(100, 5)
    assert hair.tubes(points, offsets, radii, budget=100 * 4 * 2 * hair.MIN_SIDES).triangles.shape[0] == 2400
    t = hair.tubes(points, offsets, radii, budget=600)
    assert t.thinned == 4 and t.triangles.shape[0] <= 600
    np.testing.assert_allclose(np.linalg.norm(t.positions[:, 1:2], axis=1).max(), 0.2, rtol=1e-5)  # sqrt(4) x 0.1
