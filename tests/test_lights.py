"""Direct lighting from lamps against closed forms (Cycles' conventions)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from hybridgi_core import lights as lights_mod
from hybridgi_core.lights import direct_irradiance, light_position_samples, spot_attenuation, spread_attenuation
from hybridgi_core.snapshot import Light
from hybridgi_core.trace import Hits

WHITE = np.ones(3, np.float32)


# ------------------------------------------------------------------------------------------
# Helpers: a brute-force test tracer and light constructors
# ------------------------------------------------------------------------------------------


class TriangleTracer:
    """Brute-force Moller-Trumbore over a handful of triangles: (T, 3, 3) float64 corners."""

    def __init__(self, tris):
        self.tris = np.asarray(tris, np.float64).reshape(-1, 3, 3)
        self.calls = 0
        self.rays = 0

    def _t(self, origins, dirs):
        o = np.asarray(origins, np.float64)
        d = np.broadcast_to(np.asarray(dirs, np.float64), o.shape)  # (1, 3): one direction for all
        best = np.full(o.shape[0], np.inf)
        prim = np.full(o.shape[0], -1, np.int32)
        for i, (a, b, c) in enumerate(self.tris):
            e1, e2 = b - a, c - a
            pv = np.cross(d, e2)
            det = pv @ e1
            ok = np.abs(det) > 1e-12
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            tv = o - a
            u = (tv * pv).sum(1) * inv
            qv = np.cross(tv, e1)
            v = (d * qv).sum(1) * inv
            t = (qv @ e2) * inv
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0) & (t < best)
            best[hit] = t[hit]
            prim[hit] = i
        return best, prim

    def intersect(self, origins, directions, tfar=np.inf, trusted=False):
        t, prim = self._t(origins, directions)
        miss = t >= tfar
        t[miss], prim[miss] = np.inf, -1
        z = np.zeros(t.shape, np.float32)
        return Hits(t.astype(np.float32), prim, z, z)

    def occluded(self, origins, directions, tfar=np.inf, trusted=False):
        assert origins.dtype == np.float32 and directions.dtype == np.float32
        assert directions.shape in (origins.shape, (1, 3))
        assert np.allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-5)
        self.calls += 1
        self.rays += origins.shape[0]
        t, _ = self._t(origins, directions)
        return t < tfar


def quad(centre, half_x, half_y):
    """Two triangles of the parallelogram centre +- half_x +- half_y."""
    c, hx, hy = (np.asarray(v, np.float64) for v in (centre, half_x, half_y))
    p = [c - hx - hy, c + hx - hy, c + hx + hy, c - hx + hy]
    return [[p[0], p[1], p[2]], [p[0], p[2], p[3]]]


def translation(x, y, z):
    m = np.eye(4)
    m[:3, 3] = (x, y, z)
    return m


def rot_x(angle):
    c, s = np.cos(angle), np.sin(angle)
    m = np.eye(4)
    m[1:3, 1:3] = [[c, -s], [s, c]]
    return m


def point_light(pos, power=100.0, radius=0.0, color=WHITE, soft_falloff=True):
    return Light("POINT", color, power, translation(*pos), radius=radius, soft_falloff=soft_falloff)


def spot_light(pos, size, blend, power=100.0, matrix=None):
    m = translation(*pos) if matrix is None else matrix
    return Light("SPOT", WHITE, power, m, spot_size=size, spot_blend=blend)


def sun_light(direction, strength=3.0, angle=0.0):
    """Sun shining along `direction` (its local -Z)."""
    d = np.asarray(direction, np.float64)
    d /= np.linalg.norm(d)
    z = -d
    x = np.cross([0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0], z)
    x /= np.linalg.norm(x)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2] = x, np.cross(z, x), z
    return Light("SUN", WHITE, strength, m, angle=angle)


def area_light(matrix, power=100.0, shape="SQUARE", size=1.0, size_y=1.0):
    return Light("AREA", WHITE, power, matrix, shape=shape, size=size, size_y=size_y)


def receivers(points, normals):
    p = np.asarray(points, np.float32).reshape(-1, 3)
    n = np.asarray(normals, np.float32).reshape(-1, 3)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    return p, np.broadcast_to(n, p.shape).astype(np.float32)


def irradiance(lights, p, n, tracer=None, seed=0, samples=1):
    e = direct_irradiance(lights, p, n, tracer, np.random.default_rng(seed), samples=samples)
    assert e.dtype == np.float32 and e.shape == (p.shape[0], 3)
    assert np.isfinite(e).all()
    return e.astype(np.float64)


def rect_irradiance(radiance, a, b, h):
    """On-axis irradiance at distance h below the centre of a parallel a x b Lambertian rectangle.

    Four corner rectangles of (a/2) x (b/2), each with the classic form factor
    F = 1/(2 pi) [X/sqrt(1+X^2) atan(Y/sqrt(1+X^2)) + Y/sqrt(1+Y^2) atan(X/sqrt(1+Y^2))].
    """
    x, y = a / (2 * h), b / (2 * h)
    f = (x / np.sqrt(1 + x * x) * np.arctan(y / np.sqrt(1 + x * x))
         + y / np.sqrt(1 + y * y) * np.arctan(x / np.sqrt(1 + y * y))) / (2 * np.pi)
    return 4 * np.pi * radiance * f


def polygon_irradiance(radiance, verts, p, n):
    """Exact E at p (normal n) from a planar Lambertian polygon, one-sided by vertex winding.

    Lambert's contour formula E = L/2 sum_i angle(u_i, u_i+1) n . unit(u_i x u_i+1) after clipping
    the polygon to the receiver's upper half-space. verts : (k, 3) wound counter-clockwise seen
    from the lit side.
    """
    u = np.asarray(verts, np.float64) - p
    if np.cross(u[1] - u[0], u[2] - u[0]) @ (-u[0]) <= 0:
        return 0.0  # p is behind the emitting side
    h = u @ n
    clipped = []
    for i in range(len(u)):
        a, b, ha, hb = u[i], u[(i + 1) % len(u)], h[i], h[(i + 1) % len(u)]
        if ha >= 0:
            clipped.append(a)
        if (ha >= 0) != (hb >= 0):
            clipped.append(a + (b - a) * (ha / (ha - hb)))
    if len(clipped) < 3:
        return 0.0
    c = np.asarray(clipped)
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    d = np.roll(c, -1, axis=0)
    cross = np.cross(c, d)
    angle = np.arctan2(np.linalg.norm(cross, axis=1), (c * d).sum(1))
    total = (angle * (cross @ n) / np.maximum(np.linalg.norm(cross, axis=1), 1e-300)).sum()
    return abs(0.5 * radiance * total)


def lamp_polygon(light, k=None):
    """World vertices of an AREA lamp (a k-gon for round shapes), wound to emit along local -Z."""
    m = light.matrix
    sy = light.size if light.shape in ("SQUARE", "DISK") else light.size_y
    if light.shape in ("SQUARE", "RECTANGLE"):
        a = np.array([-0.5, 0.5, 0.5, -0.5])
        b = np.array([-0.5, -0.5, 0.5, 0.5])
    else:
        t = np.linspace(0, 2 * np.pi, k, endpoint=False)
        a, b = 0.5 * np.cos(t), 0.5 * np.sin(t)
    pts = m[:3, 3] + np.outer(a * light.size, m[:3, 0]) + np.outer(b * sy, m[:3, 1])
    # Counter-clockwise around +local Z; the lit side is -Z, so reverse.
    return pts[::-1]


# ------------------------------------------------------------------------------------------
# Point and spot
# ------------------------------------------------------------------------------------------


class TestPoint:
    def test_inverse_square(self):
        d = np.array([0.5, 1.0, 2.0, 4.0, 16.0])
        p, n = receivers(np.stack([np.zeros(5), np.zeros(5), -d], 1), [0, 0, 1])
        e = irradiance([point_light((0, 0, 0), power=100.0)], p, n)[:, 0]
        np.testing.assert_allclose(e * d**2, 100.0 / (4 * np.pi), rtol=1e-5)

    def test_cosine_law_and_colour(self):
        theta = np.radians([0.0, 30.0, 60.0, 89.0, 91.0, 180.0])
        normals = np.stack([np.sin(theta), np.zeros(6), np.cos(theta)], 1)
        p, n = receivers(np.tile([0.0, 0.0, -2.0], (6, 1)), normals)
        colour = np.array([1.0, 0.5, 0.0], np.float32)
        e = irradiance([point_light((0, 0, 0), power=40.0, color=colour)], p, n)
        expect = 40.0 / (4 * np.pi) * np.maximum(np.cos(theta), 0.0) / 4.0
        np.testing.assert_allclose(e, expect[:, None] * colour[None, :], rtol=1e-5, atol=1e-9)
        assert (e[4:] == 0).all()

    def test_lights_add_and_dark_lights_skipped(self):
        p, n = receivers([[0, 0, 0]], [0, 0, 1])
        one = irradiance([point_light((0, 0, 1))], p, n)
        two = irradiance([point_light((0, 0, 1)), point_light((0, 0, 1)), point_light((0, 0, 1), power=0.0)], p, n)
        np.testing.assert_allclose(two, 2 * one, rtol=1e-6)

    def test_radius_falloff_of_disc_and_sphere(self):
        # Cycles (kernel/light/point.h): "Soft Falloff" emits from a disc facing the receiver,
        # pi L r^2 / (d^2 + r^2) with L = P / (4 pi^2 r^2); without it a sphere, whose vector
        # irradiance is that of the point lamp while the sphere is above the horizon.
        p, n = receivers([[0.3, 0.1, -2.0]], [0, 0, 1])
        hard = irradiance([point_light((0, 0, 0))], p, n)
        d2, r = 0.3**2 + 0.1**2 + 2.0**2, 0.5
        disc = irradiance([point_light((0, 0, 0), radius=r)], p, n, samples=16)
        np.testing.assert_allclose(disc, hard * d2 / (d2 + r * r), rtol=1e-5)
        sphere = irradiance([point_light((0, 0, 0), radius=r, soft_falloff=False)], p, n, samples=16)
        np.testing.assert_allclose(sphere, hard, rtol=1e-5)


def emitter_irradiance(points, normals, p, n, radiance):
    """Irradiance at p (normal n) from Lambertian patches at points (k, 3) with outward normals
    (k, 3) and areas folded into radiance (k,): sum L dA cos_r cos_e / t^2, both cosines clamped."""
    d = points - p
    t2 = (d * d).sum(axis=1)
    t = np.sqrt(t2)
    cos_r = np.maximum(d @ n / t, 0.0)
    cos_e = np.maximum(-(d * normals).sum(axis=1) / t, 0.0)
    return float((radiance * cos_r * cos_e / t2).sum())


def sphere_patches(centre, r, k=800):
    """(k^2, 3) midpoints and normals of a (theta, phi) grid on a sphere, and their areas."""
    th = (np.arange(k) + 0.5) * np.pi / k
    ph = (np.arange(2 * k) + 0.5) * np.pi / k
    th, ph = np.meshgrid(th, ph, indexing="ij")
    nrm = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1).reshape(-1, 3)
    area = (r * r * np.sin(th) * (np.pi / k) ** 2).ravel()
    return np.asarray(centre) + r * nrm, nrm, area


def disc_patches(centre, axis, r, k=600):
    """Midpoints of a polar grid on the disc of radius r facing `axis` (unit), and their areas."""
    rho = (np.arange(k) + 0.5) * r / k
    ph = (np.arange(2 * k) + 0.5) * np.pi / k
    rho, ph = np.meshgrid(rho, ph, indexing="ij")
    t1 = np.cross(axis, [1.0, 0, 0] if abs(axis[0]) < 0.9 else [0, 1.0, 0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(axis, t1)
    pts = np.asarray(centre) + (rho * np.cos(ph)).reshape(-1, 1) * t1 + (rho * np.sin(ph)).reshape(-1, 1) * t2
    return pts, np.broadcast_to(axis, pts.shape), (rho * (r / k) * (np.pi / k)).ravel()


class TestRadius:
    """POINT/SPOT lamps with a radius against the integrals Cycles' samplers estimate
    (kernel/light/point.h, spot.h): L = P / (4 pi^2 r^2) over a sphere, or over a disc facing the
    receiver with Soft Falloff."""

    P, R = 100.0, 0.5

    def radiance(self):
        return self.P / (4 * np.pi**2 * self.R**2)

    @pytest.mark.parametrize("tilt", [0.0, 1.2, 1.5, 1.75])
    def test_sphere_across_the_horizon(self, tilt):
        # Receiver 1 m from the centre; from tilt ~1.05 rad the sphere (30 degrees) dips below it.
        p = np.array([0.0, 0.0, -1.0])
        n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
        pts, nrm, area = sphere_patches((0, 0, 0), self.R)
        exact = emitter_irradiance(pts, nrm, p, n, self.radiance() * area)
        pp, nn = receivers([p], n)
        # Unshadowed, the closed form (the horizon's cut included) makes 4 samples as good as 4096.
        for samples in (4, 4096):
            e = irradiance([point_light((0, 0, 0), self.P, self.R, soft_falloff=False)], pp, nn, samples=samples)[0, 0]
            np.testing.assert_allclose(e, exact, rtol=0.01, atol=1e-3 * self.P / (4 * np.pi))

    @pytest.mark.parametrize("tilt", [0.0, 1.2, 1.5, 1.75])
    def test_soft_falloff_disc_across_the_horizon(self, tilt):
        p = np.array([0.0, 0.0, -0.6])
        n = np.array([np.sin(tilt), 0.0, np.cos(tilt)])
        pts, nrm, area = disc_patches((0, 0, 0), np.array([0.0, 0.0, -1.0]), self.R)
        exact = emitter_irradiance(pts, nrm, p, n, self.radiance() * area)
        pp, nn = receivers([p], n)
        for samples in (4, 4096):
            e = irradiance([point_light((0, 0, 0), self.P, self.R)], pp, nn, samples=samples)[0, 0]
            np.testing.assert_allclose(e, exact, rtol=0.01, atol=1e-3 * self.P / (4 * np.pi))

    @pytest.mark.parametrize("normal", [[0, 0, 1], [0, 0, -1], [1, 0, 0]])
    def test_inside_the_sphere_sees_pi_radiance_whatever_its_facing(self, normal):
        p, n = receivers([[0.1, 0.05, -0.2]], normal)
        e = irradiance([point_light((0, 0, 0), self.P, self.R, soft_falloff=False)], p, n, samples=16)
        np.testing.assert_allclose(e, np.pi * self.radiance(), rtol=1e-5)

    def test_the_cone_edge_gets_the_penumbra_sample_count_and_the_horizon_does_not(self):
        # No shadows anywhere, yet a spot's cone edge makes these receivers' samples differ like a
        # penumbra's; a lamp cut by the receiver's horizon does not (its light is in closed form:
        # `clipped_cone_irradiance`). Receivers: facing the lamp, the lamp cut by their horizon,
        # at a spot's cone edge.
        p, n = receivers([[0, 0, -2.0], [0.0, 0.0, -0.6], [np.tan(0.5), 0, -1.0]], [[0, 0, 1], [1, 0, 0], [0, 0, 1]])
        lamps = [point_light((0, 0, 0), self.P, self.R),
                 Light("SPOT", WHITE, self.P, np.eye(4), radius=0.2, spot_size=1.0, spot_blend=0.1)]
        for lamp, want in zip(lamps, ([False, False, False], [False, False, True]), strict=True):
            partial = np.zeros(3, bool)
            direct_irradiance([lamp], p, n, TriangleTracer(quad((0, 0, 50), (1, 0, 0), (0, 1, 0))),
                              np.random.default_rng(0), samples=8, partial=partial)
            assert partial.tolist() == want

    def test_few_samples_near_a_soft_spots_edge_stay_unbiased(self):
        """A spot of radius 0.3 m (blend 0.4) 0.5 m above receivers where its cone's blend crosses
        the disc they see: 2 samples each average to the 256-sample light. The ratio to the
        closed form there was a mean of the cone factor over the same 2 samples: 4-7% low."""
        lamp = Light("SPOT", WHITE, 100.0, translation(0, 0, 0.5), radius=0.3, spot_size=1.2, spot_blend=0.4)
        xs = np.array([0.35, 0.45])
        p, n = receivers(np.repeat(np.stack([xs, np.zeros(2), np.zeros(2)], 1), 16000, 0), [0, 0, 1])
        few = irradiance([lamp], p, n, samples=2)[:, 0].reshape(2, -1).mean(1)
        many = irradiance([lamp], p, n, samples=256, seed=5)[:, 0].reshape(2, -1).mean(1)
        np.testing.assert_allclose(few, many, rtol=0.025)

    def test_spot_cone_is_averaged_over_the_disc(self):
        # Receiver on the floor at the cone's edge: each disc sample sees its own cone factor.
        size, blend, h = np.radians(60.0), 0.2, 1.0
        lamp = Light("SPOT", WHITE, self.P, translation(0, 0, h), radius=0.3, spot_size=size, spot_blend=blend)
        p = np.array([h * np.tan(size / 2), 0.0, 0.0])
        n = np.array([0.0, 0.0, 1.0])
        axis = (p - [0, 0, h]) / np.linalg.norm(p - [0, 0, h])
        pts, nrm, area = disc_patches((0, 0, h), axis, 0.3)
        to_p = p - pts
        cone = cycles_spot(-to_p[:, 2] / np.linalg.norm(to_p, axis=1), size, blend)
        exact = emitter_irradiance(pts, nrm, p, n, self.P / (4 * np.pi**2 * 0.09) * area * cone)
        pp, nn = receivers([p], n)
        e = irradiance([lamp], pp, nn, samples=4096)[0, 0]
        np.testing.assert_allclose(e, exact, rtol=0.01)
        # The centre's cone factor is 0 there: the disc's samples inside the cone light it.
        assert cycles_spot(np.cos(size / 2), size, blend) == 0.0 and e > 0.05 * emitter_irradiance(
            pts, nrm, p, n, self.P / (4 * np.pi**2 * 0.09) * area)


def cycles_spot(cos_axis, size, blend):
    """Cycles 4+: smoothstep((cos - cos_half) / ((1 - cos_half) * blend)), written out."""
    cos_half = np.cos(size / 2)
    x = np.clip((cos_axis - cos_half) / ((1 - cos_half) * blend), 0.0, 1.0)
    return 3 * x**2 - 2 * x**3


class TestSpot:
    def test_cone_profile(self):
        size, blend, h = np.radians(60.0), 0.3, 2.0
        # Receivers on the floor z = 0 at angles 0..40 degrees off the axis of a lamp above.
        ang = np.radians(np.linspace(0.0, 40.0, 81))
        p, n = receivers(np.stack([h * np.tan(ang), np.zeros_like(ang), np.zeros_like(ang)], 1), [0, 0, 1])
        lamp = spot_light((0, 0, h), size, blend)
        e = irradiance([lamp], p, n)[:, 0]
        d2 = h**2 + (h * np.tan(ang)) ** 2
        point = 100.0 / (4 * np.pi) * np.cos(ang) / d2
        atten = cycles_spot(np.cos(ang), size, blend)
        np.testing.assert_allclose(e, point * atten, rtol=1e-4, atol=1e-7)
        cos_half = np.cos(size / 2)
        inner = np.cos(ang) >= cos_half + (1 - cos_half) * blend
        outside = ang > size / 2
        np.testing.assert_allclose(e[inner], point[inner], rtol=1e-5)  # full inside
        assert (e[outside] == 0).all()  # nothing outside
        band = ~inner & ~outside
        assert band.sum() >= 5 and (np.diff(e[band]) < 0).all()  # smooth fall-off in the band
        assert 0 < e[band].min() and e[band].max() < point[band].max()

    def test_zero_blend_is_a_hard_cut(self):
        size = np.radians(40.0)
        ang = np.radians([0.0, 10.0, 19.5, 20.5, 30.0])
        p, n = receivers(np.stack([np.tan(ang), np.zeros(5), np.zeros(5)], 1), [0, 0, 1])
        e = irradiance([spot_light((0, 0, 1), size, 0.0)], p, n)[:, 0]
        point = 100.0 / (4 * np.pi) * np.cos(ang) ** 3
        np.testing.assert_allclose(e, np.where(ang < size / 2, point, 0.0), rtol=1e-5)

    def test_nonuniform_scale_squashes_the_cone_like_cycles(self):
        # Scale x by 2: in the lamp's frame a direction (x, y, -z) becomes (x/2, y, -z).
        m = translation(0, 0, 1) @ np.diag([2.0, 1.0, 1.0, 1.0])
        lamp = spot_light(None, np.radians(60.0), 0.2, matrix=m)
        dirs = np.array([[0.8, 0.0, -1.0], [0.0, 0.8, -1.0], [0.3, 0.3, -1.0]], np.float32)
        got = spot_attenuation(lamp, dirs)
        local = dirs * np.array([0.5, 1.0, 1.0])
        cos_axis = -local[:, 2] / np.linalg.norm(local, axis=1)
        np.testing.assert_allclose(got, cycles_spot(cos_axis, np.radians(60.0), 0.2), atol=1e-5)
        assert got[0] > got[1]  # wider along the stretched axis


# ------------------------------------------------------------------------------------------
# Sun
# ------------------------------------------------------------------------------------------


class TestSun:
    def test_strength_times_cosine(self):
        theta = np.radians([0.0, 25.0, 60.0, 90.0, 120.0])
        normals = np.stack([np.sin(theta), np.zeros(5), np.cos(theta)], 1)
        p, n = receivers(np.random.default_rng(1).normal(size=(5, 3)) * 100, normals)
        e = irradiance([sun_light((0, 0, -1), strength=3.0)], p, n)[:, 0]
        np.testing.assert_allclose(e, 3.0 * np.maximum(np.cos(theta), 0.0), rtol=1e-6, atol=1e-6)

    def test_disc_keeps_strength_as_facing_irradiance(self):
        # 10 degree disc: its mean cosine (1 + cos 5deg) / 2 = 0.9981 would read 0.19% low unless divided out.
        theta = np.radians([0.0, 30.0, 60.0])
        normals = np.stack([np.sin(theta), np.zeros(3), np.cos(theta)], 1)
        p, n = receivers(np.zeros((3, 3)), normals)
        p, n = np.repeat(p, 200, 0), np.repeat(n, 200, 0)
        e = irradiance([sun_light((0, 0, -1), strength=2.0, angle=np.radians(10.0))], p, n, samples=64)
        mean = e[:, 0].reshape(3, 200).mean(1)
        np.testing.assert_allclose(mean, 2.0 * np.cos(theta), rtol=5e-4)

    def test_disc_directions_lie_inside_the_cone(self):
        class Recorder:
            dirs = []

            def occluded(self, o, d, tfar=np.inf, trusted=False):
                assert np.isinf(tfar)
                self.dirs.append(d.copy())
                return np.zeros(o.shape[0], bool)

        angle = np.radians(8.0)
        sun = sun_light((0.3, 0.2, -1.0), angle=angle)
        p, n = receivers(np.zeros((500, 3)), [0, 0, 1])
        rec = Recorder()
        irradiance([sun], p, n, tracer=rec, samples=4)
        d = np.concatenate(rec.dirs)
        cos = d @ (-sun.direction)
        assert d.shape == (2000, 3) and cos.min() >= np.cos(angle / 2) - 1e-6
        # Uniform in solid angle: the mean of 1 - cos is half of 1 - cos(half angle).
        np.testing.assert_allclose((1 - cos).mean(), 0.5 * (1 - np.cos(angle / 2)), rtol=0.03)

    def test_soft_shadow_edge_is_half_lit(self):
        # Half-plane blocker x < 0 at z = 1 over a receiver at the origin; sun straight down.
        blocker = TriangleTracer(quad((-50, 0, 1), (50, 0, 0), (0, 50, 0)))
        p, n = receivers(np.zeros((400, 3)), [0, 0, 1])
        e = irradiance([sun_light((0, 0, -1), strength=1.0, angle=np.radians(5.0))], p, n, blocker, samples=16)
        assert abs(e[:, 0].mean() - 0.5) < 0.03


# ------------------------------------------------------------------------------------------
# Area
# ------------------------------------------------------------------------------------------


class TestArea:
    def test_disk_on_axis(self):
        radius, power = 0.75, 50.0
        radiance = power / (np.pi * np.pi * radius**2)
        h = np.array([0.05, 0.3, 1.0, 3.0])
        lamp = area_light(translation(0, 0, 0), power=power, shape="DISK", size=2 * radius)
        p, n = receivers(np.repeat(np.stack([np.zeros(4), np.zeros(4), -h], 1), 64, 0), [0, 0, 1])
        e = irradiance([lamp], p, n, samples=256)[:, 0].reshape(4, 64)
        exact = np.pi * radiance * radius**2 / (h**2 + radius**2)
        np.testing.assert_allclose(e.mean(1), exact, rtol=3e-3)  # MC + stratification
        np.testing.assert_allclose(e, np.broadcast_to(exact[:, None], e.shape), rtol=0.03)

    @pytest.mark.parametrize("h", [0.05, 1.0])
    def test_single_sample_is_unbiased(self, h):
        # Close to the lamp too, where area sampling's 1/d^2 made single samples useless.
        lamp = area_light(translation(0, 0, h), power=10.0, shape="RECTANGLE", size=1.0, size_y=0.5)
        p, n = receivers(np.zeros((40000, 3)), [0, 0, 1])
        e = irradiance([lamp], p, n, samples=1)[:, 0]
        exact = rect_irradiance(10.0 / (np.pi * 0.5), 1.0, 0.5, h)
        assert abs(e.mean() - exact) < 4 * e.std() / np.sqrt(e.size)
        assert e.std() < 0.6 * exact  # solid-angle sampling: noise only from the receiver cosine

    def test_spread_lamp_samples_only_what_can_reach_the_receiver(self):
        """A 1.5 m soft box of spread 60 degrees 2 m above a floor: 8 samples per receiver stay
        unbiased against a 600 x 600 quadrature of the lamp across its pool of light and beyond
        its edge, with the noise of samples drawn where the cone reaches (`spread_reach`; over
        the whole lamp the relative spread was 0.22 at 1.4 m and 1.7 at 1.8 m)."""
        h, size = 2.0, 1.5
        lamp = dataclasses.replace(area_light(translation(0, 0, h), power=100.0, size=size), spread=np.radians(60.0))
        xs = np.array([0.0, 0.6, 1.0, 1.4, 1.8])
        p, n = receivers(np.repeat(np.stack([xs, np.zeros(5), np.zeros(5)], 1), 4000, 0), [0, 0, 1])
        e = irradiance([lamp], p, n, samples=8)[:, 0].reshape(5, 4000)
        g = (np.arange(600) + 0.5) / 600 * size - size / 2
        qx, qy = np.meshgrid(g, g)
        radiance = 100.0 / (np.pi * size * size)
        exact = []
        for x in xs:
            d2 = (x - qx) ** 2 + qy**2 + h * h
            cos = h / np.sqrt(d2)  # at the lamp and at the receiver alike (parallel planes)
            cone = spread_attenuation(lamp, cos, np.sqrt((x - qx) ** 2 + qy**2) / h)
            exact.append((radiance * cone * cos * cos / d2).sum() * (size / 600) ** 2)
        exact = np.array(exact)
        np.testing.assert_allclose(e.mean(1), exact, rtol=0.01)
        assert (e.std(1) / exact < [0.03, 0.1, 0.12, 0.15, 0.4]).all(), e.std(1) / exact

    def test_far_square_is_a_point_of_intensity_la_cos(self):
        # Lamp tilted 40 degrees about x, 60 m away; receiver normal 20 degrees off.
        tilt = np.radians(40.0)
        lamp = area_light(translation(0, 0, 0) @ rot_x(tilt), power=80.0, size=1.0)
        d = 60.0
        normal = np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])
        p, n = receivers([[0.0, 0.0, -d]], normal)
        e = irradiance([lamp], p, n, samples=64)[0, 0]
        to_lamp = np.array([0.0, 0.0, 1.0])
        intensity = 80.0 / np.pi * np.cos(tilt)  # L * A * cos(theta_l), with L A = P / pi
        np.testing.assert_allclose(e, intensity * (normal @ to_lamp) / d**2, rtol=1e-3)

    def test_one_sided(self):
        lamp = area_light(translation(0, 0, 1), size=2.0)
        p, n = receivers([[0, 0, 2], [0, 0, 3], [0.5, 0.5, 1.5], [0, 0, 0]], [[0, 0, -1], [0, 0, -1], [0, 0, -1], [0, 0, -1]])
        e = irradiance([lamp], p, n, samples=16)
        assert (e[:3] == 0).all()  # above the lamp: its back side
        assert (e[3] == 0).all()  # below, but the receiver faces away
        p2, n2 = receivers([[0, 0, 0]], [0, 0, 1])
        assert irradiance([lamp], p2, n2, samples=16)[0, 0] > 0

    @pytest.mark.parametrize("scale", [(2.0, 3.0, 1.0), (0.5, 0.25, 4.0)])
    def test_matrix_scale_scales_the_area(self, scale):
        # size 1 lamp scaled by (sx, sy) and rotated upside down == an sx x sy rectangle above.
        sx, sy, sz = scale
        m = translation(0, 0, 0.4) @ rot_x(np.pi) @ np.diag([sx, sy, sz, 1.0])
        lamp = area_light(m, power=30.0, size=1.0)
        p, n = receivers(np.zeros((64, 3)), [0, 0, -1])  # lamp faces +z now: receiver looks down
        p[:, 2] = 0.8
        e = irradiance([lamp], p, n, samples=256)[:, 0]
        exact = rect_irradiance(30.0 / (np.pi * sx * sy), sx, sy, 0.4)
        np.testing.assert_allclose(e.mean(), exact, rtol=3e-3)

    def test_ellipse_on_axis_and_at_its_face(self):
        # On-axis E = L * int_0^2pi R(phi)^2 / (2 (R(phi)^2 + h^2)) dphi (radial integral done).
        semi_a, semi_b, power = 1.0, 0.5, 7.0
        lamp = area_light(translation(0, 0, 0), power=power, shape="ELLIPSE", size=2 * semi_a, size_y=2 * semi_b)
        radiance = power / (np.pi * np.pi * semi_a * semi_b)
        phi = (np.arange(20000) + 0.5) * (2 * np.pi / 20000)
        r2 = 1.0 / (np.cos(phi) ** 2 / semi_a**2 + np.sin(phi) ** 2 / semi_b**2)
        for h, rtol in ((0.3, 3e-3), (1e-3, 3e-3)):
            exact = radiance * (r2 / (2 * (r2 + h * h))).mean() * 2 * np.pi
            p, n = receivers(np.zeros((64, 3)) + [0, 0, -h], [0, 0, 1])
            e = irradiance([lamp], p, n, samples=256)[:, 0]
            np.testing.assert_allclose(e.mean(), exact, rtol=rtol)
        assert exact == pytest.approx(np.pi * radiance, rel=2e-3)  # at its face: a hemisphere of L

    @pytest.mark.parametrize("shape", ["SQUARE", "RECTANGLE", "DISK", "ELLIPSE"])
    def test_random_receivers_match_the_exact_polygon_formula(self, shape):
        # Tilted, scaled lamp; receivers all around it with random normals (many partly below their
        # horizon), against Lambert's formula with horizon clipping.
        m = translation(0.2, -0.1, 1.0) @ rot_x(0.7) @ np.diag([1.5, 0.8, 1.0, 1.0])
        lamp = area_light(m, power=20.0, shape=shape, size=1.0, size_y=0.6)
        shape_area = 1.5 * 0.8 * (0.6 if shape in ("RECTANGLE", "ELLIPSE") else 1.0)
        shape_area *= np.pi / 4 if shape in ("DISK", "ELLIPSE") else 1.0
        radiance = 20.0 / (np.pi * shape_area)
        rng = np.random.default_rng(11)
        pts = rng.uniform(-1.5, 1.5, size=(24, 3)) + [0.2, -0.1, 1.0]
        nrm = rng.normal(size=(24, 3))
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        poly = lamp_polygon(lamp, k=720)
        exact = np.array([polygon_irradiance(radiance, poly, p, n) for p, n in zip(pts, nrm, strict=True)])
        reps = 32
        p, n = receivers(np.repeat(pts, reps, 0), np.repeat(nrm, reps, 0))
        e = irradiance([lamp], p, n, samples=64)[:, 0].reshape(24, reps).mean(1)
        assert (exact > 0).sum() >= 8 and (exact == 0).sum() >= 3  # both cases exercised
        np.testing.assert_allclose(e, exact, rtol=0.01, atol=2e-3 * radiance)

    def test_sheared_lamp_falls_back_to_area_sampling(self):
        m = translation(0, 0, 1.0) @ np.array([[1.0, 0.5, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 0], [0, 0, 0, 1.0]])
        lamp = area_light(m, power=10.0, size=1.0)  # a parallelogram of area 1
        poly = lamp_polygon(lamp)
        p, n = receivers(np.zeros((64, 3)) + [0.3, 0.1, 0.0], [0.2, 0.0, 1.0])
        exact = polygon_irradiance(10.0 / np.pi, poly, p[0].astype(np.float64), n[0].astype(np.float64))
        e = irradiance([lamp], p, n, samples=256)[:, 0]
        np.testing.assert_allclose(e.mean(), exact, rtol=3e-3)

    def test_receiver_on_the_light_is_finite(self):
        lamp = area_light(translation(0, 0, 1), size=1.0)  # L = 100 / pi
        pts = [[0, 0, 1], [0.2, 0.1, 1], [0, 0, 1 - 1e-7], [0.5, 0.5, 1], [0.5, 0.5, 1 - 1e-9]]
        p, n = receivers(pts, [0, 0, 1])
        e = irradiance([lamp, point_light((0, 0, 1))], p, n, samples=4)
        assert np.isfinite(e).all() and (e >= 0).all()
        # Just in front of the light a receiver sees a hemisphere of L: E = pi L = P / A, and a
        # single solid-angle sample (L * S * cos) is bounded by 2 pi L.
        p, n = receivers(np.zeros((4000, 3)) + [0.1, 0.2, 1 - 1e-6], [0, 0, 1])
        e = irradiance([lamp], p, n, samples=1)[:, 0]
        assert e.max() <= 200.0 + 1e-3
        np.testing.assert_allclose(e.mean(), 100.0, rtol=0.03)

    def test_position_samples_cover_the_scaled_shape(self):
        m = translation(1, 2, 3) @ np.diag([2.0, 1.0, 1.0, 1.0])
        pts = light_position_samples(area_light(m, shape="DISK", size=1.0), 4096, np.random.default_rng(0))
        assert pts.dtype == np.float32 and pts.shape == (4096, 3)
        q = pts - [1, 2, 3]
        assert np.allclose(q[:, 2], 0) and ((q[:, 0] / 1.0) ** 2 + (q[:, 1] / 0.5) ** 2).max() <= 1 + 1e-5
        np.testing.assert_allclose((q[:, 0] ** 2).mean(), 1.0 / 4, rtol=0.02)  # uniform ellipse: a^2 / 4
        with pytest.raises(ValueError):
            light_position_samples(sun_light((0, 0, -1)), 4, np.random.default_rng(0))


# ------------------------------------------------------------------------------------------
# Shadows
# ------------------------------------------------------------------------------------------


class TestShadows:
    LAMPS = {
        "point": lambda: point_light((0, 0, 2)),
        "soft point": lambda: point_light((0, 0, 2), radius=0.2),
        "spot": lambda: spot_light((0, 0, 2), np.radians(90.0), 0.1),
        "sun": lambda: sun_light((0, 0, -1), angle=np.radians(3.0)),
        "area": lambda: area_light(translation(0, 0, 2), shape="DISK", size=0.5),
    }

    @pytest.mark.parametrize("kind", list(LAMPS))
    def test_blocker_between_casts_shadow(self, kind):
        lamp = self.LAMPS[kind]()
        p, n = receivers([[0, 0, 0], [3.0, 0, 0]], [0, 0, 1])
        between = TriangleTracer(quad((0, 0, 1), (1, 0, 0), (0, 1, 0)))
        lit = irradiance([lamp], p, n, samples=8)
        shadowed = irradiance([lamp], p, n, between, samples=8)
        assert lit[0, 0] > 0 and shadowed[0, 0] == 0
        assert between.calls >= 1

    @pytest.mark.parametrize("kind", ["point", "soft point", "spot", "area"])
    def test_blocker_behind_the_light_does_not(self, kind):
        lamp = self.LAMPS[kind]()
        p, n = receivers([[0, 0, 0], [0.3, -0.2, 0]], [0, 0, 1])
        behind = TriangleTracer(quad((0, 0, 3), (5, 0, 0), (0, 5, 0)))
        np.testing.assert_array_equal(irradiance([lamp], p, n, behind, samples=8), irradiance([lamp], p, n, samples=8))

    def test_surface_itself_does_not_self_shadow(self):
        # The receivers' own floor is in the scene; rays start epsilon above it.
        floor = TriangleTracer(quad((0, 0, 0), (10, 0, 0), (0, 10, 0)))
        p, n = receivers([[0.1, 0.2, 0.0], [-2.0, 1.0, 0.0]], [0, 0, 1])
        lamps = [point_light((0, 0, 2)), area_light(translation(0, 0, 2), size=1.0)]
        np.testing.assert_array_equal(irradiance(lamps, p, n, floor, samples=4), irradiance(lamps, p, n, samples=4))

    def test_soft_point_penumbra(self):
        # Half-plane blocker whose edge passes under the lamp centre: half the disc is hidden.
        blocker = TriangleTracer(quad((-50, 0, 1), (50, 0, 0), (0, 50, 0)))
        p, n = receivers(np.zeros((200, 3)), [0, 0, 1])
        e = irradiance([point_light((0, 0, 2), radius=0.3)], p, n, blocker, samples=16)[:, 0]
        full = 100.0 / (4 * np.pi) / 4.0
        assert abs(e.mean() / full - 0.5) < 0.03

    def test_only_facing_receivers_are_traced(self):
        tracer = TriangleTracer(quad((0, 0, 5), (1, 0, 0), (0, 1, 0)))
        p, n = receivers(np.zeros((10, 3)), np.tile([[0, 0, 1], [0, 0, -1]], (5, 1)))
        irradiance([point_light((0, 0, 1))], p, n, tracer)
        assert tracer.rays == 5

    def test_with_numpy_tracer(self):
        reference = pytest.importorskip("hybridgi_core.trace.reference")
        from hybridgi_core.snapshot import geometry_from_arrays

        tris = np.array(quad((0, 0, 1), (1, 0, 0), (0, 1, 0)), np.float32)
        geom = geometry_from_arrays(tris.reshape(-1, 3), np.arange(6).reshape(2, 3))
        tracer = reference.NumpyTracer(geom)
        p, n = receivers([[0, 0, 0], [4.0, 0, 0]], [0, 0, 1])
        lamps = [point_light((0, 0, 2)), area_light(translation(0, 0, 2), shape="DISK", size=0.5)]
        e = irradiance(lamps, p, n, tracer, samples=8)
        free = irradiance(lamps, p, n, samples=8)
        assert e[0, 0] == 0 and free[0, 0] > 0
        np.testing.assert_allclose(e[1], free[1], rtol=1e-6)


# ------------------------------------------------------------------------------------------
# Edge cases and determinism
# ------------------------------------------------------------------------------------------


class TestEdges:
    def test_no_lights_and_no_points(self):
        p, n = receivers(np.zeros((7, 3)), [0, 0, 1])
        assert (irradiance([], p, n) == 0).all()
        e = direct_irradiance([point_light((0, 0, 1))], np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32),
                              None, np.random.default_rng(0))
        assert e.shape == (0, 3) and e.dtype == np.float32

    def test_non_finite_receivers_get_zero(self):
        p, n = receivers([[0, 0, 0], [np.nan, 0, 0], [1, 0, 0]], [0, 0, 1])
        n = n.copy()
        n[2] = np.inf
        e = irradiance([point_light((0, 0, 1)), area_light(translation(0, 0, 1))], p, n, samples=2)
        assert e[0, 0] > 0 and (e[1:] == 0).all()

    def test_deterministic_given_rng_and_tracer_independent_stream(self):
        lamps = [area_light(translation(0, 0, 1)), sun_light((0.2, 0, -1), angle=0.1), point_light((1, 0, 1), radius=0.2)]
        rng = np.random.default_rng(3)
        p, n = receivers(rng.normal(size=(300, 3)), rng.normal(size=(300, 3)))
        a = irradiance(lamps, p, n, seed=5, samples=3)
        b = irradiance(lamps, p, n, seed=5, samples=3)
        np.testing.assert_array_equal(a, b)
        far = TriangleTracer(quad((0, 0, 100), (1, 0, 0), (0, 1, 0)))  # blocks nothing
        np.testing.assert_array_equal(irradiance(lamps, p, n, far, seed=5, samples=3), a)
        assert not np.array_equal(irradiance(lamps, p, n, seed=6, samples=3), a)

    def test_chunking_does_not_change_hard_lights(self, monkeypatch):
        lamps = [point_light((0, 0, 1)), sun_light((0, 0.5, -1)), spot_light((0, 0, 2), 1.0, 0.3)]
        rng = np.random.default_rng(4)
        p, n = receivers(rng.normal(size=(1000, 3)), rng.normal(size=(1000, 3)))
        whole = irradiance(lamps, p, n)
        monkeypatch.setattr(lights_mod, "CHUNK_RAYS", 37)
        np.testing.assert_array_equal(irradiance(lamps, p, n), whole)

    def test_rejects_bad_arguments(self):
        p, n = receivers(np.zeros((2, 3)), [0, 0, 1])
        with pytest.raises(ValueError):
            direct_irradiance([], p, n, None, np.random.default_rng(0), samples=0)
        with pytest.raises(ValueError):
            direct_irradiance([], p, n[:1], None, np.random.default_rng(0))


def test_receivers_below_the_whole_lamp_are_skipped_only_where_no_sample_lights_them():
    """`_above_horizon` drops a receiver from an area lamp's samples only where every sample of
    the lamp lies below its tangent plane: grazing receivers around the threshold, tilted so
    the lamp's nearest corner is just above, on or just below their horizon."""
    from hybridgi_core import lights

    lamp = area_light(translation(0.3, -0.2, 2.0) @ rot_x(0.4), power=100.0, size=1.0, size_y=0.6)
    shape = lights._area_shape(lamp)
    rng = np.random.default_rng(0)
    n = 3000
    p = rng.uniform(-2.0, 2.0, (n, 3)).astype(np.float32)
    p[:, 2] = rng.uniform(-1.0, 1.5, n)
    corners = shape.corner + np.array([[0, 0], [1, 0], [0, 1], [1, 1]]) @ np.stack(
        [shape.frame[0] * shape.len_u, shape.frame[1] * shape.len_v])
    # A random normal, then tilted so that the highest corner sits at a height of about +-1e-4 of its distance.
    nrm = rng.normal(size=(n, 3))
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    rel = corners[None] - p[:, None].astype(np.float64)
    top = np.argmax(np.einsum("nkc,nc->nk", rel, nrm), axis=1)
    to_top = rel[np.arange(n), top]
    to_top /= np.linalg.norm(to_top, axis=1, keepdims=True)
    nrm -= (np.einsum("nc,nc->n", nrm, to_top) - rng.uniform(-3e-4, 3e-4, n))[:, None] * to_top
    nrm = (nrm / np.linalg.norm(nrm, axis=1, keepdims=True)).astype(np.float32)
    d = [shape.corner[k] - p[:, k].astype(np.float64) for k in range(3)]
    q = tuple(np.ascontiguousarray(nrm[:, k]) for k in range(3))
    keep = lights._above_horizon(shape, d, q)
    assert 0.1 < keep.mean() < 0.9
    # The samples of the dropped receivers: none above their horizon.
    ex, ey, ez = shape.frame
    x0, y0, z0 = (d[0] * e[0] + d[1] * e[1] + d[2] * e[2] for e in (ex, ey, ez))
    u, v = lights.stratified_uv(rng, n, 64)
    xu, yv, _, _ = lights._sample_spherical_rectangle(x0, y0, z0, shape.len_u, shape.len_v, u, v)
    w = [xu * np.float32(ex[k]) + yv * np.float32(ey[k]) + z0.astype(np.float32)[:, None] * np.float32(ez[k])
         for k in range(3)]
    cos = w[0] * nrm[:, :1] + w[1] * nrm[:, 1:2] + w[2] * nrm[:, 2:3]
    front = z0 < 0
    assert (cos[~keep & front] <= 0).all()
    assert (cos[keep & front] > 0).any(axis=1).mean() > 0.2  # grazing: a sliver of the lamp above


def _budget_floor():
    """(tracer, points, normals): a 24 x 24 floor over [-3, 3]^2 under a small blocker."""
    tracer = TriangleTracer(quad((0.0, 0.0, 1.0), (0.6, 0, 0), (0, 0.6, 0)))
    ys, xs = np.meshgrid(np.linspace(-3, 3, 24), np.linspace(-3, 3, 24), indexing="ij")
    pts = np.column_stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)]).astype(np.float32)
    return tracer, pts, np.tile(np.float32([0, 0, 1]), (pts.shape[0], 1))


def _budget_means(lamps, pts, nrm, tracer, samples, budget, runs=96):
    """(mean light of every lamp, mean with lamp_budget=budget, their shadow rays) over `runs` seeds."""
    full, picked = np.zeros((pts.shape[0], 3)), np.zeros((pts.shape[0], 3))
    tracer.rays = 0
    for seed in range(runs):
        full += direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(seed), samples=samples)
    full_rays, tracer.rays = tracer.rays, 0
    for seed in range(runs):
        picked += direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(seed), samples=samples,
                                    lamp_budget=budget)
    return full / runs, picked / runs, full_rays, tracer.rays


def test_lamp_budget_picks_lamps_without_bias_and_traces_fewer_rays():
    """direct_irradiance(lamp_budget=k): each receiver shades k of the sampled lamps, drawn in
    proportion to their rough light and weighted by one over their probability: the mean over
    many seeds is every lamp's light (unbiased), with about k / lamps of the shadow rays; a budget
    of at least the lamp count changes nothing."""
    spot = Light("SPOT", np.ones(3), 80.0, translation(1.0, -1.0, 2.0), radius=0.1, spot_size=0.8)
    lamps = [point_light((x, y, 1.9), radius=0.05) for x in (-1.5, 0.5) for y in (-1.0, 1.0)]
    lamps += [spot, area_light(translation(-1.0, 1.5, 2.0), power=150.0),
              sun_light((0.3, 0.2, -1.0), strength=2.0, angle=0.05),
              sun_light((-0.2, 0.1, -1.0), strength=1.0)]  # axial: always shaded
    tracer, pts, nrm = _budget_floor()
    full, picked, full_rays, picked_rays = _budget_means(lamps, pts, nrm, tracer, samples=2, budget=2)
    assert picked_rays < 0.45 * full_rays, (picked_rays, full_rays)
    assert abs(picked.sum() / full.sum() - 1.0) < 0.01
    assert np.abs(picked - full).sum() / full.sum() < 0.03
    rng = np.random.default_rng(3)
    # A budget so large that every lamp's share reaches 1 / budget shades all of them, as none does.
    np.testing.assert_array_equal(direct_irradiance(lamps, pts, nrm, tracer, np.random.default_rng(3), samples=2),
                                  direct_irradiance(lamps, pts, nrm, tracer, rng, samples=2, lamp_budget=10**9))
    with pytest.raises(ValueError, match="lamp_budget"):
        direct_irradiance(lamps, pts, nrm, tracer, rng, samples=2, lamp_budget=2, partial=np.zeros(pts.shape[0], bool))


def test_two_lamps_within_the_budget_are_both_shaded_at_every_hit():
    """With fewer than ROULETTE_MIN_LAMPS sampled lamps a lamp budget draws nothing: each hit is
    shaded by both lamps, the same rays and light as without a budget, even where one lamp is
    under 1 / budget of the light (the rough light per hit would cost what the skipped rays save)."""
    strong = area_light(translation(0.0, 0.0, 2.0), power=4000.0)
    dim = point_light((2.0, 2.0, 1.5), radius=0.3, power=2.0)
    assert lights_mod.ROULETTE_MIN_LAMPS > 2
    tracer, pts, nrm = _budget_floor()
    tracer.rays = 0
    plain = direct_irradiance([strong, dim], pts, nrm, tracer, np.random.default_rng(3), samples=1)
    plain_rays, tracer.rays = tracer.rays, 0
    budget = direct_irradiance([strong, dim], pts, nrm, tracer, np.random.default_rng(3), samples=1, lamp_budget=8)
    np.testing.assert_array_equal(budget, plain)
    assert tracer.rays == plain_rays


def test_lamp_budget_of_all_lamps_skips_dim_lamps_by_roulette_without_bias():
    """direct_irradiance(lamp_budget=k) with no more sampled lamps than k: a lamp whose share of
    the rough light is at least 1 / k is shaded at every receiver (weight 1), a dimmer one with
    probability k x its share and weighted by one over it: the mean over seeds is every lamp's
    light, with far fewer shadow rays to the dim lamps (a strong lamp beside four dim ones)."""
    strong = area_light(translation(0.0, 0.0, 2.0), power=4000.0)
    dim = [point_light((x, y, 1.5), radius=0.3, power=2.0) for x in (-2.0, 2.0) for y in (-2.0, 2.0)]
    lamps = [strong] + dim
    tracer, pts, nrm = _budget_floor()
    full, picked, full_rays, picked_rays = _budget_means(lamps, pts, nrm, tracer, samples=1, budget=8)
    assert picked_rays < 0.5 * full_rays, (picked_rays, full_rays)
    assert abs(picked.sum() / full.sum() - 1.0) < 0.01
    assert np.abs(picked - full).sum() / full.sum() < 0.06  # both are 96 one-sample estimates apart
    # The weights themselves: 1 for the strong lamp everywhere, and a mean of 1 (unbiased) for
    # each dim one, which is drawn at only a share of the receivers.
    weights = np.stack([lights_mod._roulette_lamps(lamps, pts, nrm, 8, np.random.default_rng(seed)) for seed in range(400)])
    assert (weights[..., 0] == 1.0).all()
    drawn = (weights[..., 1:] > 0).mean()
    assert drawn < 0.25, drawn
    np.testing.assert_allclose(weights[..., 1:].mean(axis=0).mean(axis=0), 1.0, atol=0.05)
