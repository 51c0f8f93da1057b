"""Point clouds as spheres (`hybridgi_core.points`): bpy-free."""

from __future__ import annotations

import numpy as np

from hybridgi_core import points


def test_spheres_wind_outwards_at_each_points_radius():
    centres = np.array([(0, 0, 0), (3, 0, 0)], np.float32)
    s = points.spheres(centres, np.array([0.5, 0.25], np.float32))
    assert s.thinned == 1 and s.triangles.shape == (2 * 80, 3) and s.source.tolist() == [0] * 80 + [1] * 80
    p = s.positions[s.triangles].astype(np.float64)
    facet = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    assert (np.einsum("ij,ij->i", facet, p.mean(axis=1) - centres[s.source]) > 0).all()
    corner_point = np.repeat(np.arange(2), 42)
    np.testing.assert_allclose(np.linalg.norm(s.positions - centres[corner_point], axis=1),
                               np.repeat([0.5, 0.25], 42), rtol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(s.normals, axis=1), 1.0, rtol=1e-5)


def test_points_without_a_finite_positive_radius_or_position_give_nothing():
    centres = np.zeros((4, 3), np.float32)
    centres[3] = np.nan
    s = points.spheres(centres, np.array([0.1, 0.0, np.nan, 0.1], np.float32))
    assert set(s.source.tolist()) == {0} and np.isfinite(s.positions).all()


def test_too_many_points_get_fewer_faces_then_are_thinned_and_widened():
    centres = np.zeros((100, 3), np.float32)
    assert points.spheres(centres, np.full(100, 0.1), budget=2000).triangles.shape[0] == 2000
    s = points.spheres(centres, np.full(100, 0.1), budget=500)
    assert s.thinned == 4 and s.triangles.shape[0] <= 500
    np.testing.assert_allclose(np.linalg.norm(s.positions, axis=1).max(), 0.2, rtol=1e-5)  # sqrt(4) x 0.1
