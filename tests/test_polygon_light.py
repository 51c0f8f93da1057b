"""The closed-form unshadowed irradiance of area lamps and the ratio estimator built on it."""

from __future__ import annotations

import numpy as np

from hybridgi_core.lights import direct_irradiance
from hybridgi_core.polygon_light import cosine_solid_angle, lamp_polygon, vector_form_factor
from tests.test_lights import TriangleTracer, area_light, quad, rot_x, translation


def _mc_cosine_solid_angle(polygon, point, normal, n=400_000, seed=3):
    """Monte-Carlo reference: uniform points on the (convex, planar) polygon, area measure."""
    rng = np.random.default_rng(seed)
    k = polygon.shape[0]
    # Fan triangles from vertex 0, picked by area.
    tri = [(polygon[0], polygon[i], polygon[i + 1]) for i in range(1, k - 1)]
    areas = np.array([0.5 * np.linalg.norm(np.cross(b - a, c - a)) for a, b, c in tri])
    pick = rng.choice(len(tri), size=n, p=areas / areas.sum())
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = (np.stack([t[j] for t in tri])[pick] for j in range(3))
    x = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    lamp_n = np.cross(polygon[1] - polygon[0], polygon[2] - polygon[0])
    lamp_n /= np.linalg.norm(lamp_n)
    w = x - point
    d2 = (w * w).sum(1)
    w /= np.sqrt(d2)[:, None]
    g = np.maximum(w @ normal, 0) * np.abs(w @ lamp_n) / d2
    return g.mean() * areas.sum()


def test_square_overhead_matches_the_disc_formula_limit_and_monte_carlo():
    poly = lamp_polygon(np.array([0.0, 0.0, 1.0]), np.array([0.5, 0, 0]), np.array([0, 0.5, 0]), False)
    got = cosine_solid_angle(poly, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))[0]
    assert abs(got - _mc_cosine_solid_angle(poly, np.zeros(3), np.array([0.0, 0.0, 1.0]))) < 3e-3 * got
    # Far away a lamp is a point: A cos / d^2.
    far = lamp_polygon(np.array([0.0, 0.0, 50.0]), np.array([0.5, 0, 0]), np.array([0, 0.5, 0]), False)
    tiny = cosine_solid_angle(far, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))[0]
    assert abs(tiny - 1.0 / 2500.0) < 1e-3 / 2500.0


def test_lamp_straddling_the_horizon_is_clipped():
    # A vertical square whose lower half is below the receiver's tangent plane.
    poly = lamp_polygon(np.array([0.0, 1.0, 0.0]), np.array([0.5, 0, 0]), np.array([0, 0, 0.5]), False)
    normal = np.array([0.0, 0.0, 1.0])
    got = cosine_solid_angle(poly, np.zeros((1, 3)), normal[None])[0]
    want = _mc_cosine_solid_angle(poly, np.zeros(3), normal)
    assert want > 0 and abs(got - want) < 5e-3 * want
    below = lamp_polygon(np.array([0.0, 1.0, -1.0]), np.array([0.5, 0, 0]), np.array([0, 0, 0.4]), False)
    assert cosine_solid_angle(below, np.zeros((1, 3)), normal[None])[0] == 0.0


def test_a_batch_of_whole_cut_and_hidden_receivers_matches_monte_carlo():
    """One call over receivers that see a tilted lamp whole, cut by their horizon (a corner or
    an edge below it) and not at all: each row as Monte Carlo integrates it alone; and the
    vector form factor's z is the same integral for the normal +z, its direction the mean
    direction (by solid angle) of the lamp's part above the horizon."""
    poly = lamp_polygon(np.array([0.2, 0.1, 1.0]), np.array([0.6, 0.0, 0.2]), np.array([0.0, 0.5, 0.0]), False)
    points = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.05], [1.6, 0.0, 1.0], [0.0, 0.0, 2.0], [0.3, -0.2, 0.9]])
    normals = np.tile([0.0, 0.0, 1.0], (points.shape[0], 1))
    normals[4] = np.array([0.3, 0.0, 1.0]) / np.linalg.norm([0.3, 0.0, 1.0])
    got = cosine_solid_angle(poly, points, normals)
    for i in range(points.shape[0]):
        want = _mc_cosine_solid_angle(poly, points[i], normals[i])
        assert abs(got[i] - want) < 5e-3 * max(want, 1e-3), (i, got[i], want)
    assert got[3] == 0.0 and 0.0 < got[1] < 0.5 * got[0] and 0.0 < got[2] < got[0]
    rel = [poly[None, :, c] - points[:, c, None] for c in range(3)]
    vector = vector_form_factor(rel)
    np.testing.assert_allclose(vector[:4, 2], got[:4], rtol=1e-12, atol=1e-15)
    # Direction: the mean direction of the lamp's points above the horizon, by solid angle.
    rng = np.random.default_rng(7)
    u, v = rng.random((2, 200_000))
    corner = poly[0]
    x = corner + u[:, None] * (poly[1] - corner) + v[:, None] * (poly[3] - corner)
    for i in (0, 1, 2):
        w = x - points[i]
        d2 = (w * w).sum(1)
        w /= np.sqrt(d2)[:, None]
        lamp_n = np.cross(poly[1] - poly[0], poly[3] - poly[0])
        g = (w[:, 2] > 0) * np.abs(w @ lamp_n) / np.linalg.norm(lamp_n) / d2
        mean = (w * g[:, None]).mean(0)
        np.testing.assert_allclose(vector[i] / np.linalg.norm(vector[i]), mean / np.linalg.norm(mean), atol=3e-3)


def test_ellipse_polygon_keeps_the_area_and_the_cosine_integral():
    poly = lamp_polygon(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0.5, 0]), True)
    x, y = poly[:, 0], poly[:, 1]
    area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert abs(area - np.pi * 0.5) < 1e-9
    point, normal = np.array([0.3, -0.2, -0.7]), np.array([0.0, 0.6, 0.8])
    got = cosine_solid_angle(poly, point[None], normal[None])[0]
    # The true ellipse: Monte Carlo over it (rejection from its box).
    rng = np.random.default_rng(1)
    q = rng.uniform(-1, 1, (400_000, 2)) * (1.0, 0.5)
    q = q[(q[:, 0] ** 2 + (q[:, 1] / 0.5) ** 2) <= 1]
    w = np.column_stack([q, np.zeros(len(q))]) - point
    d2 = (w * w).sum(1)
    w /= np.sqrt(d2)[:, None]
    want = (np.maximum(w @ normal, 0) * np.abs(w[:, 2]) / d2).mean() * np.pi * 0.5
    assert abs(got - want) < 5e-3 * want


def test_ratio_estimator_is_exact_without_occluders_and_unbiased_in_a_penumbra():
    # A 1 m square lamp 2 m above a floor, facing down; receivers on the floor.
    lamp = area_light(translation(0.0, 0.0, 2.0), power=200.0)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(-2, 2, 4000), rng.uniform(-2, 2, 4000), np.zeros(4000)]).astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (4000, 1))
    open_tracer = TriangleTracer([])
    e4 = direct_irradiance([lamp], pts, nrm, open_tracer, np.random.default_rng(1), samples=4)
    e_ref = direct_irradiance([lamp], pts, nrm, None, np.random.default_rng(2), samples=4096)
    # Unshadowed: the 4-sample estimate is the closed form (no noise at all).
    assert np.abs(e4 - e_ref).max() < 0.01 * e_ref.max()
    # Below RATIO_MIN_SAMPLES the plain solid-angle estimate runs: it is noisy even unshadowed.
    rel_noise_plain = np.abs(direct_irradiance([lamp], pts, nrm, open_tracer, np.random.default_rng(1), samples=2)
                             - e_ref).mean() / e_ref.mean()
    assert rel_noise_plain > 5 * (np.abs(e4 - e_ref).mean() / e_ref.mean())
    # A blocker over half the lamp: the mean over many seeds matches the reference.
    blocker = quad((0.25, 0.0, 1.5), (0.25, 0, 0), (0, 1.0, 0))
    tracer = TriangleTracer(blocker)
    few = pts[:300]
    fn = nrm[:300]
    mean = np.mean([direct_irradiance([lamp], few, fn, tracer, np.random.default_rng(s), samples=4)
                    for s in range(40)], axis=0)
    ref = direct_irradiance([lamp], few, fn, tracer, np.random.default_rng(99), samples=2048)
    assert abs(mean.sum() - ref.sum()) < 0.02 * ref.sum()
    assert np.abs(mean - ref).mean() < 0.05 * ref.mean()


def test_tilted_disc_lamp_matches_the_sampled_estimate():
    lamp = area_light(translation(0.0, 0.0, 1.5) @ rot_x(0.4), power=100.0, shape="DISK", size=0.8)
    pts = np.float32([[0.3, 0.1, 0.0], [-0.5, 0.4, 0.2], [1.0, -1.0, 0.0]])
    nrm = np.float32([[0, 0, 1], [0.3, 0, 0.954], [0, 0.6, 0.8]])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    got = direct_irradiance([lamp], pts, nrm, TriangleTracer([]), np.random.default_rng(0), samples=4)
    want = direct_irradiance([lamp], pts, nrm, None, np.random.default_rng(5), samples=16384)
    assert np.allclose(got, want, rtol=0.01)
    # One sample a receiver (probe hits) keeps the plain estimate: a ratio of one sample that
    # missed the disc would say nothing about the visibility.
    one = np.mean([direct_irradiance([lamp], pts, nrm, TriangleTracer([]), np.random.default_rng(s), samples=1)
                   for s in range(400)], axis=0)
    assert np.allclose(one, want, rtol=0.08)


def test_clip_below_keeps_k_plus_one_slots_and_the_clipped_polygon():
    """Polygons of k = 4 and 6 vertices cut by random planes through the origin: k + 1 slots,
    the first `count` the clipped polygon's vertices (each above the plane or on it), the rest
    repeating the last, and its vector form factor that of the polygon clipped by hand (the
    kept vertices and the edges' crossings, in boundary order)."""
    from hybridgi_core.polygon_light import clip_below

    rng = np.random.default_rng(5)
    for k in (4, 6):
        angle = np.linspace(0.0, 2 * np.pi, k, endpoint=False)
        m = 200
        centre = rng.normal(size=(m, 3)) + np.array([0.0, 0.0, 2.0])
        ring = np.stack([np.cos(angle), np.sin(angle), np.zeros(k)], axis=1)  # (k, 3) convex, planar
        poly = centre[:, None, :] + 0.8 * ring[None]  # (m, k, 3)
        plane = rng.normal(size=(m, 3))
        h = np.einsum("mkc,mc->mk", poly, plane)
        v = [poly[..., c] for c in range(3)]
        (x, y, z), count = clip_below(v, h)
        assert x.shape == (m, k + 1)
        for i in range(m):
            kept = []
            for j in range(k):
                a, b, ha, hb = poly[i, j], poly[i, (j + 1) % k], h[i, j], h[i, (j + 1) % k]
                if ha >= 0:
                    kept.append(a)
                if (ha >= 0) != (hb >= 0):
                    kept.append(a + ha / (ha - hb) * (b - a))
            assert count[i] == len(kept) <= k + 1
            got = np.stack([x[i], y[i], z[i]], axis=1)
            if kept:
                assert np.allclose(got[: count[i]], np.array(kept))
                assert np.allclose(got[count[i]:], got[count[i] - 1])
            if len(kept) >= 3:  # the repeated slots add nothing to the form factor
                own = np.array(kept)
                assert np.allclose(vector_form_factor([x[i : i + 1], y[i : i + 1], z[i : i + 1]]),
                                   vector_form_factor([own[None, :, c] for c in range(3)]), atol=1e-12)
