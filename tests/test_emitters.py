"""hybridgi_core/emitters.py: emissive triangles sampled as lights, against Lambert's closed form."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hybridgi_core import emitters
from hybridgi_core.emitters import MeshLights
from hybridgi_core.polygon_light import cosine_solid_angle
from hybridgi_core.shading import GLOW_FLOOR, GLOW_POINTS
from tests.test_lights import TriangleTracer, quad


def panel(centre=(0.0, 0.0, 2.0), half=0.5, radiance=(3.0, 2.0, 1.0), facing_down=True):
    tris = np.asarray(quad(centre, (half, 0.0, 0.0), (0.0, half if facing_down else -half, 0.0)), np.float32)
    positions = tris.reshape(-1, 3)
    triangles = np.arange(6).reshape(2, 3)
    return positions, triangles, np.tile(np.asarray(radiance, np.float32), (2, 1)), tris


def receivers(n=64):
    g = np.linspace(-1.5, 1.5, 8)
    x, y = np.meshgrid(g, g)
    points = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1).astype(np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (points.shape[0], 1))
    tilted = np.tile(np.array([0.6, 0.0, 0.8], np.float32), (points.shape[0], 1))
    return points, normals, tilted


@pytest.fixture
def by_power(monkeypatch):
    """Every emitter sampled by power (`MeshLights._block`), as emitters of many triangles are."""
    monkeypatch.setattr(emitters, "EXACT_TRIANGLES", 0)


@pytest.mark.parametrize("exact", [True, False])
@pytest.mark.parametrize("facing_down", [True, False])
def test_unshadowed_light_is_lamberts_closed_form(facing_down, exact, monkeypatch):
    """Both sides emit (as rays read emission): a panel facing away lights the floor the same."""
    if not exact:
        monkeypatch.setattr(emitters, "EXACT_TRIANGLES", 0)
    positions, triangles, emission, tris = panel(facing_down=facing_down)
    lights = MeshLights.from_triangles(positions, triangles, emission)
    points, up, tilted = receivers()
    polygon = np.array([tris[0][0], tris[0][1], tris[0][2], tris[1][2]], np.float64)
    for normals in (up, tilted):
        exact = cosine_solid_angle(polygon, points, normals)[:, None] * np.array([3.0, 2.0, 1.0])
        got = lights.irradiance(points, normals, None, np.random.default_rng(1), 4096, 1e-4)
        np.testing.assert_allclose(got.mean(axis=0), exact.mean(axis=0), rtol=0.02)
        np.testing.assert_allclose(got, exact, rtol=0.08, atol=0.01 * exact.max())


def test_an_occluder_casts_its_shadow_and_the_emitter_does_not_shadow_itself():
    positions, triangles, emission, tris = panel(half=0.25)
    blocker = np.asarray(quad((0.0, 0.0, 1.0), (0.3, 0.0, 0.0), (0.0, 0.3, 0.0)), np.float32)
    lights = MeshLights.from_triangles(positions, triangles, emission)
    points = np.array([[0.0, 0.0, 0.0], [1.5, 0.0, 0.0]], np.float32)
    normals = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (2, 1))
    rng = np.random.default_rng(2)
    open_light = lights.irradiance(points, normals, None, rng, 512, 1e-4)
    # The emitter's own triangles are in the scene: rays stop short of the point they aim at.
    tracer = TriangleTracer(np.concatenate([tris, blocker]))
    shadowed = lights.irradiance(points, normals, tracer, rng, 512, 1e-4)
    assert shadowed[0].max() == 0.0  # under the blocker, which hides the whole panel
    np.testing.assert_allclose(shadowed[1], open_light[1], rtol=0.1)  # off to the side: lit


def sampled_by_power(lights, points, normals, tracer, samples, seed):
    """`lights.irradiance` with its triangles sampled by power (`MeshLights._block`)."""
    saved = emitters.EXACT_TRIANGLES
    try:
        emitters.EXACT_TRIANGLES = 0
        return lights.irradiance(points, normals, tracer, np.random.default_rng(seed), samples, 1e-4)
    finally:
        emitters.EXACT_TRIANGLES = saved


def test_a_few_triangles_are_exact_where_unshadowed_and_scaled_by_their_shadow_elsewhere():
    """Emitters of a few triangles take the lamps' ratio estimator: Lambert's closed form where
    no shadow ray is blocked, to rounding with 4 samples; in a half shadow the same mean as
    the triangles sampled by power with many samples."""
    positions, triangles, emission, tris = panel(half=0.5)
    lights = MeshLights.from_triangles(positions, triangles, emission)
    points, up, _ = receivers()
    polygon = np.array([tris[0][0], tris[0][1], tris[0][2], tris[1][2]], np.float64)
    # At the receivers as their shadow rays leave them, epsilon off the surface (`_ratio_block`).
    exact = cosine_solid_angle(polygon, points + up * 1e-4, up)[:, None] * np.array([3.0, 2.0, 1.0])
    got = lights.irradiance(points, up, TriangleTracer(tris), np.random.default_rng(4), 4, 1e-4)
    np.testing.assert_allclose(got, exact, rtol=1e-5, atol=1e-7)
    # A blocker over half the panel: receivers under its edge see part of it.
    blocker = np.asarray(quad((0.25, 0.0, 1.0), (0.25, 0.0, 0.0), (0.0, 0.6, 0.0)), np.float32)
    tracer = TriangleTracer(np.concatenate([tris, blocker]))
    at = np.array([[x, 0.0, 0.0] for x in (-0.6, -0.2, 0.0, 0.2, 0.6)], np.float32)
    up5 = up[: at.shape[0]]
    ratio = np.mean([lights.irradiance(at, up5, tracer, np.random.default_rng(s), 16, 1e-4) for s in range(40)], axis=0)
    sampled = sampled_by_power(lights, at, up5, tracer, 8192, 5)
    assert (sampled[:, 0] < 0.95 * cosine_solid_angle(polygon, at, up5) * 3.0).any()  # some are in shadow
    np.testing.assert_allclose(ratio, sampled, rtol=0.04, atol=0.01 * sampled.max())


def box_triangles(centre, half, inward=False):
    """(12, 3, 3) the faces of an axis-aligned box, wound to face out (or in)."""
    c, h = np.asarray(centre, np.float64), np.asarray(half, np.float64)
    faces = []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u, v = np.eye(3)[(axis + 1) % 3] * h, np.eye(3)[(axis + 2) % 3] * h
            if sign < 0:
                u, v = v, u  # keep the winding's normal pointing out of the box
            faces += quad(c + sign * np.eye(3)[axis] * h, u, v)
    tris = np.asarray(faces, np.float64)
    return tris[:, ::-1] if inward else tris


def test_a_closed_emitter_lights_only_by_its_outer_faces():
    """An LED strip (a thin closed box) emits from both sides of its faces as rays read them, but
    its inner side is never seen: its faces count on their outer side (`_sides`), so a receiver
    that sees it whole is exact, and what it gets agrees with the triangles sampled by power and
    shadowed by the strip itself."""
    tris = box_triangles((0.0, 0.0, 1.0), (1.5, 0.05, 0.025)).astype(np.float32)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    assert (np.einsum("ij,ij->i", n, tris.mean(axis=1) - [0.0, 0.0, 1.0]) > 0).all()  # the helper's winding
    emission = np.tile(np.array([5.0, 4.0, 3.0], np.float32), (12, 1))
    positions, triangles = tris.reshape(-1, 3), np.arange(36).reshape(12, 3)
    one = np.zeros(12, np.int64)  # one object
    lights = MeshLights.from_triangles(positions, triangles, emission, objects=one)
    assert (lights.side == 1).all()
    inward = box_triangles((0.0, 0.0, 1.0), (1.5, 0.05, 0.025), inward=True).astype(np.float32)
    assert (MeshLights.from_triangles(inward.reshape(-1, 3), triangles, emission, objects=one).side == -1).all()
    open_box = MeshLights.from_triangles(positions[:30], triangles[:10], emission[:10], objects=one[:10])
    assert (open_box.side == 0).all()  # an end missing: both sides of every face
    # Receivers on a wall behind the strip and a ceiling above it, facing it.
    points = np.array([[x, 0.2, 1.0] for x in (-1.0, 0.0, 0.7)] + [[x, 0.0, 1.3] for x in (-0.5, 0.4)], np.float32)
    normals = np.array([[0, -1, 0]] * 3 + [[0, 0, -1]] * 2, np.float32)
    tracer = TriangleTracer(tris)
    got = lights.irradiance(points, normals, tracer, np.random.default_rng(6), 4, 1e-4)
    seen = lights.exact(points + normals * 1e-4, normals) @ emission.astype(np.float64)
    np.testing.assert_allclose(got, seen, rtol=1e-5)
    np.testing.assert_allclose(got, sampled_by_power(lights, points, normals, tracer, 20000, 7), rtol=0.03)


def test_a_point_on_an_emitter_gets_no_light_from_its_own_face():
    """The panel's own pixels, or a probe ray's hit on it: a rounding error off the face's plane
    to either side. Behind the face (emitters are two-sided) Lambert's form saw its back fill the
    hemisphere, pi L, at every other such point; Cycles' Diffuse Direct there is 0."""
    positions, triangles, emission, tris = panel(half=0.5)
    lights = MeshLights.from_triangles(positions, triangles, emission)
    on = np.array([[x, y, 2.0 + dz] for x, y in ((0.1, 0.2), (-0.3, -0.1)) for dz in (-3e-7, 0.0, 3e-7)], np.float32)
    for facing in (-1.0, 1.0):
        normals = np.tile(np.array([0.0, 0.0, facing], np.float32), (on.shape[0], 1))
        for tracer in (None, TriangleTracer(tris)):
            got = lights.irradiance(on, normals, tracer, np.random.default_rng(2), 4, 1e-4)
            np.testing.assert_allclose(got, 0.0, atol=1e-3)


def test_inside_a_closed_emitter_every_face_lights_by_its_inner_side():
    """A room whose closed walls glow (a furnace; every face emits both ways, as Cycles' emission
    does): a receiver inside sees every wall by its inner side, whichever way they are wound, so
    the closed form gives the whole sphere's light, pi L on any normal."""
    one = np.zeros(12, np.int64)
    emission = np.tile(np.array([2.0, 1.0, 0.5], np.float32), (12, 1))
    points = np.array([[0.1, -0.2, 0.3], [-0.4, 0.3, -0.1]], np.float32)
    normals = np.array([[0, 0, 1], [0.6, 0.0, -0.8]], np.float32)
    for inward in (False, True):
        tris = box_triangles((0.0, 0.0, 0.0), (1.0, 1.0, 1.0), inward=inward).astype(np.float32)
        lights = MeshLights.from_triangles(tris.reshape(-1, 3), np.arange(36).reshape(12, 3), emission, objects=one)
        assert (lights.side != 0).all()
        got = lights.irradiance(points, normals, TriangleTracer(tris), np.random.default_rng(3), 4, 1e-4)
        np.testing.assert_allclose(got, np.pi * np.tile(emission[0], (2, 1)), rtol=1e-4)
    # Outside it the same box still lights by its outer faces alone (no double count).
    outside = lights.exact(np.array([[0.0, 0.0, 3.0]]), np.array([[0.0, 0.0, -1.0]])) @ emission.astype(np.float64)
    square = np.array([[-1.0, -1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, 1.0], [-1.0, 1.0, 1.0]])
    face = cosine_solid_angle(square, np.array([[0.0, 0.0, 3.0]]), np.array([[0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(outside[0], face[0] * emission[0], rtol=1e-6)


def test_triangles_are_chosen_by_power_and_nothing_emitting_is_none():
    positions, triangles, emission, _ = panel()
    emission[1] *= 3.0
    lights = MeshLights.from_triangles(positions, triangles, emission)
    np.testing.assert_allclose(lights.choose, [0.25, 0.75])
    assert MeshLights.from_triangles(positions, triangles, np.zeros_like(emission)) is None
    assert MeshLights.from_triangles(positions, triangles, emission, skip=np.array([True, True])) is None


@pytest.mark.parametrize("gap", [0.02, 0.002])
def test_receivers_next_to_an_emitter_get_its_light_without_fireflies(gap, by_power):
    """A panel a few mm from a ceiling lights it by its back (both sides emit). Sampled by area,
    the points right next to a receiver weigh 1 / d^2: fireflies. Near triangles are sampled in
    their solid angle: the estimate stays within a few % with 128 samples."""
    positions, triangles, emission, tris = panel(centre=(0.0, 0.0, 2.0), half=0.3)
    lights = MeshLights.from_triangles(positions, triangles, emission)
    g = np.linspace(-0.25, 0.25, 6)
    x, y = np.meshgrid(g, g)
    points = np.stack([x.ravel(), y.ravel(), np.full(x.size, 2.0 + gap)], axis=1).astype(np.float32)
    down = np.tile(np.array([0.0, 0.0, -1.0], np.float32), (points.shape[0], 1))
    polygon = np.array([tris[0][0], tris[0][1], tris[0][2], tris[1][2]], np.float64)
    exact = cosine_solid_angle(polygon, points, down)[:, None] * np.array([3.0, 2.0, 1.0])
    got = lights.irradiance(points, down, None, np.random.default_rng(3), 128, 1e-5)
    # Unbiased over the receivers; each within the spread the choice between the two triangles
    # leaves (their solid angles differ a lot from a point this close).
    np.testing.assert_allclose(got.mean(axis=0), exact.mean(axis=0), rtol=0.05)
    worst = float(np.abs(got / exact - 1.0).max())
    monkeypatch_angle = emitters.NEAR_SOLID_ANGLE
    try:
        emitters.NEAR_SOLID_ANGLE = np.inf  # every triangle sampled by area
        by_area = lights.irradiance(points, down, None, np.random.default_rng(3), 128, 1e-5)
    finally:
        emitters.NEAR_SOLID_ANGLE = monkeypatch_angle
    worst_by_area = float(np.abs(by_area / exact - 1.0).max())
    print(f"gap {gap}: worst relative error {worst:.2f} (by area {worst_by_area:.2f})")
    assert worst < 0.5 and worst < 0.5 * worst_by_area, (worst, worst_by_area)


def test_a_subdivided_emitter_is_sampled_by_clusters_near_receivers():
    """A panel cut into 128 triangles and a small bright one apart: receivers choose clusters of
    triangles by their power over their distance (`Clusters`). Unbiased (the mean of many
    estimates is Lambert's exact sum) and far less noisy than triangles chosen by power alone
    next to the panel and beside the small one."""
    g = np.linspace(-0.3, 0.3, 9)
    tris = []
    for i in range(8):
        for j in range(8):
            q = [np.array([x, y, 2.98]) for x, y in ((g[i], g[j]), (g[i + 1], g[j]), (g[i + 1], g[j + 1]), (g[i], g[j + 1]))]
            tris += [[q[0], q[2], q[1]], [q[0], q[3], q[2]]]
    tris.append([np.array([1.0, 1.0, 1.0]), np.array([1.2, 1.0, 1.0]), np.array([1.0, 1.2, 1.0])])
    tris = np.asarray(tris, np.float32)
    k = tris.shape[0]
    emission = np.tile(np.array([5.0, 4.0, 3.0], np.float32), (k, 1))
    emission[-1] = 50.0
    owner = np.zeros(k, np.int64)
    owner[-1] = 1
    lights = MeshLights.from_triangles(tris.reshape(-1, 3), np.arange(3 * k).reshape(k, 3), emission, objects=owner)
    assert lights.clusters is not None and lights.clusters.start.size - 1 > 8
    by_power = replace(lights, clusters=None)
    points = np.array([[0.4, 0.0, 2.97], [1.5, 1.5, 0.0], [1.1, 1.1, 0.95], [0.0, 0.0, 1.0]], np.float32)
    normals = np.array([[0, 0, 1], [0, 0, 1], [0, 0, 1], [0, 0, 1]], np.float32)
    exact = lights.exact(points + normals * 1e-4, normals) @ emission.astype(np.float64)
    spread = {}
    for name, sampled in (("clusters", lights), ("power", by_power)):
        runs = np.array([sampled.irradiance(points, normals, None, np.random.default_rng(s), 4, 1e-4)
                         for s in range(1500)])
        spread[name] = runs.std(axis=0)[:, 0] / exact[:, 0]
        # Within 4 standard errors of the mean of 1500 estimates.
        np.testing.assert_allclose(runs.mean(axis=0)[:, 0], exact[:, 0],
                                   rtol=float(4.0 * spread[name].max() / np.sqrt(runs.shape[0])))
    print(spread)
    assert (spread["clusters"][:3] < 0.6 * spread["power"][:3]).all(), spread


def test_pixels_sample_the_emitters_only_where_they_light_the_scene():
    from hybridgi_core.snapshot import Light

    positions, triangles, emission, _ = panel()  # 1 m^2 of radiance (3, 2, 1): ~13 W of flux
    lights = MeshLights.from_triangles(positions, triangles, emission)
    lamp = lambda kind, power: Light(kind=kind, color=np.ones(3, np.float32), power=power, matrix=np.eye(4))  # noqa: E731
    assert emitters.worth_sampling(lights, [])
    assert emitters.worth_sampling(lights, [lamp("AREA", 50.0)])
    assert not emitters.worth_sampling(lights, [lamp("AREA", 500.0)])  # a few % of the light: rays
    assert not emitters.worth_sampling(lights, [lamp("SUN", 3.0)])
    assert not emitters.worth_sampling(None, [])


def test_a_compact_emitter_is_sampled_through_its_bounding_sphere():
    """A glowing ball (one object) on a floor: receivers sample its bounding sphere's cone, each
    ray that meets the ball bringing its radiance. Against the closed form of a sphere above the
    horizon (E = pi L r^3 / d^3 on the floor, d the distance to the centre) the light agrees, and
    its noise at 16 samples is a fraction of the triangles' (points chosen by power on the ball,
    half of them on its far side, weighed 1 / d^2 next to it)."""
    from blend_scenes.procedural import _placement, transformed, uv_sphere
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.snapshot import Material, World, concat_geometry, geometry_from_arrays, make_snapshot
    from hybridgi_core.system import GISystem

    r, radiance = 0.25, 4.0
    ball = transformed(uv_sphere(r, 64, 32), _placement((0.0, 0.0, r)))
    ball = geometry_from_arrays(ball.positions, ball.triangles, 1, 1)
    floor = geometry_from_arrays([[-4, -4, 0], [4, -4, 0], [4, 4, 0], [-4, 4, 0]], [[0, 1, 2], [0, 2, 3]], 0, 0)
    mats = [Material("floor", np.full(3, 0.5, np.float32)),
            Material("glow", np.full(3, 0.8, np.float32), emission=np.full(3, radiance, np.float32))]
    scene = make_snapshot(concat_geometry([floor, ball]), mats, [], World(color=np.zeros(3, np.float32)))
    rho = np.array([0.05, 0.15, 0.4, 1.0])
    points = np.stack([rho, np.zeros_like(rho), np.zeros_like(rho)], axis=1).astype(np.float32)
    up = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (rho.size, 1))
    exact = np.pi * radiance * r**3 / (rho**2 + r**2) ** 1.5
    with GISystem(scene, CacheSettings(resolution=8, rays_per_cell=8)) as gi:
        cone = gi.surfaces.emitters
        assert cone.spheres.shape[0] == 1  # the ball is compact
        tris = MeshLights.from_packed(gi.surfaces._positions, gi.surfaces.records[:-1, 6:9])  # one object per triangle
        assert tris.spheres.shape[0] == 0
        eps = float(gi.tracer.epsilon)
        got = cone.irradiance(points, up, gi.tracer, np.random.default_rng(1), 8192, eps)[:, 0]
        np.testing.assert_allclose(got, exact, rtol=0.02)
        runs = {name: np.array([m.irradiance(points, up, gi.tracer, np.random.default_rng(seed), 16, eps)[:, 0]
                                for seed in range(100)]) for name, m in (("cone", cone), ("triangles", tris))}
    rms = {name: np.sqrt(((v - exact) ** 2).mean(axis=0)) / exact for name, v in runs.items()}
    assert (rms["cone"] < rms["triangles"] / 3).all(), rms


def half_lit_panel(cuts: int = 1):
    """A 1 m panel 2 m above the floor (in cuts x cuts quads) whose emission texture glows over
    x < 0 only, as `MeshLights` sees it (glows, texture), and the untextured half it equals."""
    tris = np.concatenate([quad((x, y, 2.0), (0.5 / cuts, 0.0, 0.0), (0.0, 0.5 / cuts, 0.0))
                           for x in (np.arange(cuts) + 0.5) / cuts - 0.5
                           for y in (np.arange(cuts) + 0.5) / cuts - 0.5]).astype(np.float32)
    radiance = np.array([3.0, 2.0, 1.0], np.float32)

    def texture(prims, u, v):
        t = tris[prims]
        x = t[:, 0, 0] + u * (t[:, 1, 0] - t[:, 0, 0]) + v * (t[:, 2, 0] - t[:, 0, 0])
        return np.where((x < 0.0)[:, None], radiance, np.float32(0.0)).astype(np.float32)

    k, m = tris.shape[0], GLOW_POINTS.shape[0]
    texels = texture(np.repeat(np.arange(k), m), np.tile(GLOW_POINTS[:, 0], k), np.tile(GLOW_POINTS[:, 1], k))
    mean = texels.reshape(k, m, 3).mean(axis=1) + np.float32(GLOW_FLOOR) * radiance  # `SurfaceTable._glowing_means`
    lights = MeshLights.from_triangles(tris.reshape(-1, 3), np.arange(3 * k).reshape(k, 3), mean,
                                       glows=np.ones(k, bool), texture=texture)
    half = np.array([[-0.5, -0.5, 2.0], [0.0, -0.5, 2.0], [0.0, 0.5, 2.0], [-0.5, 0.5, 2.0]])
    return lights, tris, half, radiance


@pytest.mark.parametrize("cuts", [1, 4])
def test_a_textured_emitter_lights_by_its_texels(cuts):
    """A textured emitter's samples read their texel (`MeshLights.texture`): a panel glowing over
    half of it lights the floor as that half alone does (Lambert's closed form), whether its two
    triangles (each half lit) take the ratio estimator or its 32 are sampled by their means'
    power (a mean of the floor's share where none of a triangle glows); under a blocker over the lit half's
    centre the light falls, as the half's own samples say."""
    lights, tris, half, radiance = half_lit_panel(cuts)
    assert lights.glows.all() and lights.ratio == (cuts == 1)
    points, up, tilted = receivers()
    for normals in (up, tilted):
        exact = cosine_solid_angle(half, points, normals)[:, None] * radiance
        got = np.mean([lights.irradiance(points, normals, TriangleTracer(tris), np.random.default_rng(s), 64, 1e-4)
                       for s in range(8)], axis=0)
        np.testing.assert_allclose(got.mean(axis=0), exact.mean(axis=0), rtol=0.03)
        np.testing.assert_allclose(got, exact, rtol=0.15, atol=0.02 * exact.max())
    blocker = np.asarray(quad((-0.25, 0.0, 1.0), (0.15, 0.0, 0.0), (0.0, 0.15, 0.0)), np.float32)
    at, up1 = np.array([[-0.25, 0.0, 0.0]], np.float32), up[:1]
    shaded = np.mean([lights.irradiance(at, up1, TriangleTracer(np.concatenate([tris, blocker])),
                                        np.random.default_rng(s), 64, 1e-4) for s in range(16)], axis=0)
    whole = MeshLights.from_triangles(half[[0, 1, 2, 0, 2, 3]].astype(np.float32), np.arange(6).reshape(2, 3),
                                      np.tile(radiance, (2, 1)))
    truth = sampled_by_power(whole, at, up1, TriangleTracer(blocker), 20000, 9)
    assert shaded[0, 0] < 0.9 * cosine_solid_angle(half, at, up1)[0] * radiance[0]  # the blocker shades it
    np.testing.assert_allclose(shaded, truth, rtol=0.05)
