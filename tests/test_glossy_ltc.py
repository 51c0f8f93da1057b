"""The glossy lobes' area-lamp light in closed form (hybridgi_core/ltc.py, glossy_ltc.py): the fitted
LTC integrates to what the lobe integrates to over a lamp, the closed form agrees with unshadowed
lamp sampling of the same materials, and the diffuse light's visibility shadows it."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import glossy, glossy_ltc, ltc
from hybridgi_core import specular as sp
from hybridgi_core.snapshot import Light, Material


def _lobe_over_rectangle(rough, mu, polygon, n=300_000, seed=5):
    """The GGX lobe (a white metal: F = 1, single scattering) x cos over a lamp rectangle, by
    uniform area samples, divided by the lobe's albedo (its integral over the hemisphere)."""
    mats = glossy.GlossyMaterials.from_materials([Material(specular=sp.SpecularLayer(roughness=rough, metallic=1.0,
                                                                                     metal_color=(1.0, 1.0, 1.0),
                                                                                     multiscatter=False))])
    rng = np.random.default_rng(seed)
    normal = np.array([[0.0, 0.0, 1.0]])
    view = np.array([[np.sqrt(1.0 - mu * mu), 0.0, mu]])

    def lobe(wi):
        return glossy.lobes(mats, np.zeros(1, np.int64), normal, view, wi[None, :, 0], wi[None, :, 1], wi[None, :, 2])[0]

    u = rng.random((n, 2))
    e1, e2 = polygon[1] - polygon[0], polygon[3] - polygon[0]
    q = polygon[0] + u[:, :1] * e1 + u[:, 1:] * e2
    d2 = (q * q).sum(1)
    wi = q / np.sqrt(d2)[:, None]
    area_normal = np.cross(e1, e2)
    area = np.linalg.norm(area_normal)
    cos_l = np.abs(wi @ area_normal) / area
    over_lamp = (lobe(wi) * (cos_l / d2)[:, None]).mean(axis=0) * area
    z = rng.random(n)
    phi = 2.0 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - z * z)
    hemi = np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)
    albedo = lobe(hemi).mean(axis=0) * 2.0 * np.pi
    return float((over_lamp / albedo).mean())


def _square(centre, size, tilt=0.0):
    c = np.asarray(centre, np.float64)
    u = np.array([size, 0.0, 0.0])
    v = np.array([0.0, size * np.cos(tilt), size * np.sin(tilt)])
    return np.stack([c - u - v, c + u - v, c + u + v, c - u + v])


@pytest.mark.parametrize(("rough", "mu", "centre", "size"), [
    (0.5, 0.9, (0.0, 0.0, 2.0), 0.8),   # above, near normal view: the lamp off the lobe's peak
    (0.5, 0.6, (-1.6, 0.0, 2.0), 0.7),  # in the mirror direction of the view
    (0.3, 0.5, (-1.7, 0.3, 2.0), 0.4),  # smoother lobe, small lamp near its peak
    (0.8, 0.3, (0.5, 1.0, 1.0), 1.0),   # rough, grazing view, the lamp to the side
])
def test_the_fitted_cosine_integrates_as_the_lobe_over_a_lamp(rough, mu, centre, size):
    _assert_lobe_integral(rough, mu, _square(centre, size, tilt=0.2))


@pytest.mark.parametrize(("rough", "mu", "centre", "size", "tilt"), [
    (0.5, 0.6, (-1.5, 0.0, 0.2), 0.6, 1.2),   # in the mirror direction, a third below the horizon: 12% high unclipped
    (0.4, 0.7, (-1.0, 0.5, 0.1), 0.5, 1.4),   # beside it, half below
    (0.3, 0.6, (-1.2, 0.0, 0.25), 0.5, 1.3),  # smoother lobe, a quarter below
])
def test_a_lamp_the_horizon_cuts_counts_only_its_part_above(rough, mu, centre, size, tilt):
    """The lobe is 0 below the surface's horizon and the fitted cosine below its own, tilted one:
    the lamp is clipped to both, so the part between them no longer counts (a lamp a curved
    surface cuts: two thirds of bunny_npm's lit pixels took lamp samples for want of it)."""
    polygon = _square(centre, size, tilt=tilt)
    assert polygon[:, 2].min() < 0.0 < polygon[:, 2].max()
    _assert_lobe_integral(rough, mu, polygon, absolute=1e-4)


def _assert_lobe_integral(rough, mu, polygon, absolute=0.003):
    got = ltc.polygon_integral(polygon, np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]),
                               np.array([[np.sqrt(1.0 - mu * mu), 0.0, mu]]), np.array([rough]))[0][0]
    expected = _lobe_over_rectangle(rough, mu, polygon)
    # Within a few percent: the fit's own L1 distance to the lobe (up to ~0.1 at these angles,
    # scripts/fit_ltc.py) corrected at the light's mean direction (`ltc._correction`).
    assert got == pytest.approx(expected, rel=0.06, abs=absolute)


def test_the_lookup_reads_the_table_at_its_cells():
    t = ltc.table()
    roughs, mus = ltc.grid(t.shape[0])
    got = ltc.lookup(np.array([roughs[3], roughs[7]]), np.array([mus[5], mus[2]]))
    np.testing.assert_allclose(got, [t[3, 5], t[7, 2]], atol=1e-6)


def _floor_lamp(power=120.0, size=0.8, height=2.0, x=0.0, shape="SQUARE", size_y=None, matrix=None):
    if matrix is None:
        matrix = np.eye(4)
        matrix[:3, 3] = (x, 0.0, height)  # local -Z emits: down onto a floor facing +Z
    return Light(kind="AREA", color=np.array([1.0, 0.8, 0.6], np.float32), power=power, matrix=matrix, size=size,
                 shape=shape, size_y=size if size_y is None else size_y)


def _mirrored_tilted():
    """A lamp whose matrix mirrors its X axis and tilts it 30 degrees about Y (its local -Z still emits)."""
    c, s = np.cos(np.radians(30)), np.sin(np.radians(30))
    matrix = np.eye(4)
    matrix[:3, :3] = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]]) @ np.diag([-1.0, 1.0, 1.0])
    matrix[:3, 3] = (0.5, 0.2, 2.2)
    return _floor_lamp(matrix=matrix, shape="RECTANGLE", size=1.2, size_y=0.5)


@pytest.mark.parametrize("layer", [sp.SpecularLayer(roughness=0.5),
                                   sp.SpecularLayer(roughness=0.35, weight=0.5, metallic=0.6,
                                                    metal_color=(0.9, 0.6, 0.2))])
@pytest.mark.parametrize("lamp", [_floor_lamp(), _floor_lamp(shape="DISK", size=1.0),
                                  _floor_lamp(shape="ELLIPSE", size=1.2, size_y=0.6), _mirrored_tilted()],
                         ids=["square", "disk", "ellipse", "mirrored_tilted_rectangle"])
def test_the_closed_form_agrees_with_unshadowed_lamp_sampling(layer, lamp):
    """The same receivers, materials and lamp: `glossy_ltc.closed_form` against
    `glossy.glossy_direct` with many samples and no shadow rays (every lamp wholly visible)."""
    mats = glossy.GlossyMaterials.from_materials([Material(specular=layer)])
    points, normals, to_eye = _floor(64)
    rows = np.zeros(len(points), np.int64)
    vis = np.ones((len(points), 1), np.float32)
    got, pairs = glossy_ltc.closed_form([lamp], mats, points, normals, to_eye, rows, vis, ~vis.astype(bool),
                                        np.zeros(len(points)))
    assert pairs.all()
    sampled = glossy.glossy_direct([lamp], points, normals, to_eye, rows.astype(np.int32), mats, None,
                                   np.random.default_rng(0), samples=4096)
    lum = np.array([0.2126, 0.7152, 0.0722])
    # Per receiver within a few percent (the fit corrected at the light's mean direction: 8% over
    # the floor and 2-3 x in the lobe's tail without); no bias over the floor.
    np.testing.assert_allclose(got @ lum, sampled @ lum, rtol=0.05, atol=0.01 * float((sampled @ lum).max()))
    assert abs(float((got @ lum).sum() / (sampled @ lum).sum()) - 1.0) < 0.02


def _floor(n, eye=(3.0, -1.0, 2.5)):
    """n receivers on the floor z = 0 under `_floor_lamp`, seen from `eye`: points, normals, to_eye."""
    rng = np.random.default_rng(2)
    points = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), np.zeros(n)])
    to_eye = np.asarray(eye) - points
    return points, np.tile([0.0, 0.0, 1.0], (n, 1)), to_eye / np.linalg.norm(to_eye, axis=1, keepdims=True)


def test_the_diffuse_visibility_shadows_the_closed_form():
    mats = glossy.GlossyMaterials.from_materials([Material(specular=sp.SpecularLayer(roughness=0.5))])
    lamp = _floor_lamp()
    points = np.array([[0.3, 0.0, 0.0]] * 3)
    normals = np.tile([0.0, 0.0, 1.0], (3, 1))
    to_eye = np.tile([0.6, 0.0, 0.8], (3, 1))
    rows = np.zeros(3, np.int64)
    # Lit wholly, half, not at all: the diffuse light's share over its exact unshadowed light.
    exact = np.full((3, 1), 2.0)
    colour = np.asarray(lamp.color, np.float32)
    diffuse = np.stack([2.0 * colour, 1.0 * colour, 0.0 * colour])[:, None, :]
    vis = glossy_ltc.visibility(diffuse, exact, [lamp])
    np.testing.assert_allclose(vis[:, 0], [1.0, 0.5, 0.0], atol=1e-6)
    light, pairs = glossy_ltc.closed_form([lamp], mats, points, normals, to_eye, rows, vis, np.zeros((3, 1), bool),
                                          np.zeros(3))
    # The penumbra's pixel is left to lamp sampling (the lobe weighs the lamp otherwise than
    # the cosine), unless its light is dim against the pixel's diffuse light: then it is shadowed
    # by the diffuse visibility too.
    assert pairs[:, 0].tolist() == [True, False, True]
    assert light[0].min() > 0 and not light[1:].any()
    light, pairs = glossy_ltc.closed_form([lamp], mats, points, normals, to_eye, rows, vis, np.zeros((3, 1), bool),
                                          np.full(3, 1e6))
    assert pairs.all()
    np.testing.assert_allclose(light[1], 0.5 * light[0], rtol=1e-5)
    # An unknown visibility: lamp sampling.
    vis[1] = np.nan
    assert glossy_ltc.closed_form([lamp], mats, points, normals, to_eye, rows, vis, np.zeros((3, 1), bool),
                                  np.zeros(3))[1][:, 0].tolist() == [True, False, True]


def test_other_lamps_and_smooth_lobes_stay_with_lamp_sampling():
    mats = glossy.GlossyMaterials.from_materials([Material(specular=sp.SpecularLayer(roughness=0.5)),
                                                  Material(specular=sp.SpecularLayer(roughness=0.05))])
    area = _floor_lamp()
    point = Light(kind="POINT", color=np.ones(3, np.float32), power=50.0, matrix=np.eye(4))
    spread = _floor_lamp()
    spread.spread = 0.5
    hidden = _floor_lamp(power=0.0)  # hidden from diffuse rays: no diffuse visibility to borrow
    hidden.glossy_power = 100.0
    lights = [area, point, spread, hidden]
    assert list(glossy_ltc.eligible_lamps(lights)) == [True, False, False, False]
    rows = np.array([0, 1, -1])
    points, up = np.zeros((3, 3)), np.tile([0.0, 0.0, 1.0], (3, 1))
    vis = np.ones((3, 1), np.float32)
    skip = np.zeros((3, 1), bool)
    pairs = glossy_ltc.closed_form([area], mats, points, up, up, rows, vis, skip, np.zeros(3))[1]
    # The rough material's receiver only (the smooth lobe's and the background's: lamp sampling).
    assert pairs[:, 0].tolist() == [True, False, False]
    # A receiver that samples another lamp anyway keeps the area lamp with it.
    both = glossy_ltc.closed_form([area, point], mats, points, up, up, rows, np.ones((3, 2), np.float32),
                                  np.zeros((3, 2), bool), np.zeros(3))[1]
    assert not both.any()
    # The reflection rays' lamps (`skip`) and a frame without visibilities: none.
    skip[0, 0] = True
    assert not glossy_ltc.closed_form([area], mats, points, up, up, rows, vis, skip, np.zeros(3))[1].any()
    assert not glossy_ltc.closed_form([area], mats, points, up, up, rows, None, skip, np.zeros(3))[1].any()


def test_an_untrusted_closed_form_is_taken_only_where_its_light_is_dim():
    """A grazing view: the closed form only where its light is dim against the pixel's diffuse
    lamp light. A lamp the receiver's horizon cuts (a wall beside it) is trusted: it is clipped."""
    mats = glossy.GlossyMaterials.from_materials([Material(specular=sp.SpecularLayer(roughness=0.5))])
    lamp = _floor_lamp()
    side = np.tile([1.0, 0.0, 0.0], (2, 1))
    points = np.array([[0.2, 0.0, 1.9]] * 2)
    eye = np.tile([0.8, 0.0, 0.6], (2, 1))
    assert glossy_ltc.trusted([lamp], side, eye).all()
    grazing = np.tile([0.98, 0.0, 0.2], (2, 1))
    up = np.tile([0.0, 0.0, 1.0], (2, 1))
    glancing = np.tile([0.2, 0.0, 0.98], (2, 1)) / np.hypot(0.2, 0.98)  # 0.2 from grazing on the wall
    assert not glossy_ltc.trusted([lamp], side, glancing).any()
    assert not glossy_ltc.trusted([lamp], up, grazing).any()
    assert glossy_ltc.trusted([lamp], up, eye).all()
    vis = np.ones((2, 1), np.float32)
    light, pairs = glossy_ltc.closed_form([lamp], mats, points, side, glancing, np.zeros(2, np.int64), vis,
                                          np.zeros((2, 1), bool), np.array([0.0, 1e6]))
    assert pairs[:, 0].tolist() == [False, True]
    assert not light[0].any() and light[1].min() > 0
