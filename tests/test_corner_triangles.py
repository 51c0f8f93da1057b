"""hybridgi_core/corner_triangles.py: Blender's corner triangles of triangle and quad meshes (numpy only).

The sync's triangles against Blender's own `loop_triangles` are in test_sync.py."""

from __future__ import annotations

import numpy as np

from hybridgi_core import corner_triangles as ct


def area(p: np.ndarray) -> float:
    """Summed area of triangles (T, 3, 2) of 2D points."""
    a, b, c = p[:, 0], p[:, 1], p[:, 2]
    return float(np.abs(np.cross(b - a, c - a)).sum() / 2)


def shoelace(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return float(abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))) / 2)


def corners_3d(points_2d) -> np.ndarray:
    p = np.asarray(points_2d, np.float32)
    return np.concatenate([p, np.zeros((p.shape[0], 1), np.float32)], axis=1)


def test_a_mesh_of_triangles_is_its_faces_corners_in_order():
    triangles, faces = ct.from_sizes(np.array([3, 3, 3]), np.zeros((9, 3), np.float32))
    assert triangles.tolist() == [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    assert faces.tolist() == [0, 1, 2]
    assert triangles.dtype == faces.dtype == np.int32
    # Three corners a face on average is not enough to tell: a face of two beside a quad.
    assert ct.from_sizes(np.array([2, 4]), np.zeros((6, 3), np.float32)) is None


def test_a_convex_quad_splits_along_its_first_diagonal():
    quad = corners_3d([(0, 0), (1, 0), (1, 1), (0, 1)])
    triangles, faces = ct.from_sizes(np.array([4]), quad)
    assert triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert faces.tolist() == [0, 0]


def test_a_concave_quad_splits_along_the_diagonal_inside_it():
    # A dart whose corner 3 points in past the 0-2 diagonal: (0 1 2) (0 2 3) would cover more
    # than the quad (the second triangle lies outside it and overlaps the first).
    dart = corners_3d([(0, 0), (2, 0), (2, 2), (1.5, 0.5)])
    triangles, _ = ct.from_sizes(np.array([4]), dart)
    assert triangles.tolist() == [[0, 1, 3], [1, 2, 3]]
    assert np.isclose(area(dart[triangles][..., :2]), shoelace(dart[:, :2]))
    # The same dart starting at another corner: the diagonal 0-2 is inside, no flip.
    turned = dart[[3, 0, 1, 2]]
    triangles, _ = ct.from_sizes(np.array([4]), turned)
    assert triangles.tolist() == [[0, 1, 2], [0, 2, 3]]
    assert np.isclose(area(turned[triangles][..., :2]), shoelace(turned[:, :2]))


def test_mixed_faces_keep_face_order_and_corner_offsets():
    rng = np.random.default_rng(3)
    sizes = np.array([3, 4, 4, 3, 4])
    positions = rng.normal(size=(sizes.sum(), 3)).astype(np.float32)
    triangles, faces = ct.from_sizes(sizes, positions)
    assert faces.tolist() == [0, 1, 1, 2, 2, 3, 4, 4]
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    for t, f in zip(triangles, faces, strict=True):
        assert starts[f] <= t.min() and t.max() < starts[f] + sizes[f]  # a face's own corners
    # Each quad's two triangles use all four of its corners and share one diagonal.
    for q in np.flatnonzero(sizes == 4):
        a, b = triangles[faces == q]
        assert set(a) | set(b) == set(range(starts[q], starts[q] + 4))
        assert len(set(a) & set(b)) == 2


def test_n_gons_and_broken_sizes_are_left_to_blender():
    positions = np.zeros((12, 3), np.float32)
    assert ct.from_sizes(np.array([3, 4, 5]), positions) is None
    assert ct.from_sizes(np.array([2, 4]), positions) is None
    assert ct.from_sizes(np.array([], np.int32), positions) is None
