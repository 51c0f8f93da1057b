"""The lamps' glossy reflection (hybridgi_core/glossy.py): the lobes' BRDF integrates to the albedo
that Glossy Color and the diffuse layering use, and lamps light it as their radiometry says."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import glossy
from hybridgi_core import specular as sp
from hybridgi_core.snapshot import Light, Material


def _integrated_lobes(layer, mu, n=400_000, seed=3):
    """Monte-Carlo integral over the hemisphere of the lobes' BRDF x cos (uniform directions)."""
    mats = glossy.GlossyMaterials.from_materials([Material(specular=layer)])
    rng = np.random.default_rng(seed)
    z = rng.random(n)
    phi = 2.0 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - z * z)
    normal = np.array([[0.0, 0.0, 1.0]])
    view = np.array([[np.sqrt(1.0 - mu * mu), 0.0, mu]])
    f = glossy.lobes(mats, np.zeros(1, np.int64), normal, view, (s * np.cos(phi))[None], (s * np.sin(phi))[None], z[None])
    return f[0].mean(axis=0) * 2.0 * np.pi


@pytest.mark.parametrize("layer", [sp.SpecularLayer(), sp.SpecularLayer(roughness=0.8, level=1.0),
                                   sp.SpecularLayer(roughness=0.4, weight=0.5, metallic=0.5, metal_color=(0.9, 0.6, 0.2))])
@pytest.mark.parametrize("mu", [0.9, 0.4])
def test_lobes_integrate_to_the_glossy_color(layer, mu):
    integral = _integrated_lobes(layer, mu)
    expected = sp.glossy_color(layer, mu)
    # The tables interpolate between their samples (16 x 16): a percent or two of the albedo.
    assert np.allclose(integral, expected, rtol=0.06, atol=3e-3), (integral, expected)


def test_single_scattering_ggx_keeps_cycles_albedo_estimate():
    """Plain GGX loses the energy of its multiple bounces (the integral is E x the Fresnel
    average), while Cycles' albedo estimate (Glossy Color, the layering) assumes none is lost:
    both are kept as Cycles has them."""
    layer = sp.SpecularLayer(roughness=0.6, multiscatter=False)
    e = sp._lerp_table(sp.tables()[0], [0.6, 0.5])
    integral = _integrated_lobes(layer, 0.5)
    assert np.allclose(integral, e * sp.glossy_color(layer, 0.5), rtol=0.06)
    assert np.all(integral < 0.9 * sp.glossy_color(layer, 0.5))


def test_a_sun_lights_the_lobe_by_its_strength():
    layer = sp.SpecularLayer(roughness=0.3)
    mats = glossy.GlossyMaterials.from_materials([Material(specular=layer)])
    sun = Light(kind="SUN", color=np.array([1.0, 0.5, 0.25], np.float32), power=3.0,
                matrix=np.eye(4))  # shines along -Z: onto a floor facing +Z
    view = np.array([[0.0, 0.0, 1.0]])
    out = glossy.glossy_direct([sun], np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), view, np.zeros(1, np.int32),
                               mats, None, np.random.default_rng(0))
    f = glossy.lobes(mats, np.zeros(1, np.int64), np.array([[0.0, 0.0, 1.0]]), view,
                     np.zeros((1, 1)), np.zeros((1, 1)), np.ones((1, 1)))[0, 0]
    assert np.allclose(out[0], 3.0 * f * sun.color, rtol=1e-5)
    # Seen from behind its normal, or without a layer, nothing.
    none = glossy.glossy_direct([sun], np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), view, np.full(1, -1, np.int32),
                                mats, None, np.random.default_rng(0))
    assert not none.any()


def test_an_area_lamp_matches_its_solid_angle_integral():
    """A small square lamp straight above a rough floor, seen from above: the estimate against the
    lobe times the lamp's radiance times its solid angle."""
    layer = sp.SpecularLayer(roughness=0.6)
    mats = glossy.GlossyMaterials.from_materials([Material(specular=layer)])
    matrix = np.eye(4)
    matrix[:3, 3] = (0.0, 0.0, 5.0)
    lamp = Light(kind="AREA", color=np.ones(3, np.float32), power=100.0, matrix=matrix, size=0.2)
    out = glossy.glossy_direct([lamp], np.zeros((4, 3)), np.tile([[0.0, 0.0, 1.0]], (4, 1)),
                               np.tile([[0.0, 0.6, 0.8]], (4, 1)), np.zeros(4, np.int32), mats, None,
                               np.random.default_rng(1), samples=64)
    to_lamp = np.array([0.0, 0.0, 1.0])
    f = glossy.lobes(mats, np.zeros(1, np.int64), to_lamp[None], np.array([[0.0, 0.6, 0.8]]),
                     np.zeros((1, 1)), np.zeros((1, 1)), np.ones((1, 1)))[0, 0]
    radiance = 100.0 / (np.pi * 0.04)
    assert np.allclose(out, radiance * f * 0.04 / 25.0, rtol=0.01)


def test_the_cache_reflects_the_sky_as_direct_and_nothing_as_bounced():
    """An open glossy floor under a uniform sky of radiance L: its lobes reflect L (the split-sum
    light before Glossy Color), all of it from the sky (Glossy Direct's share), none bounced."""
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.snapshot import World, geometry_from_arrays, make_snapshot
    from hybridgi_core.system import GISystem

    floor = geometry_from_arrays([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], [[0, 1, 2], [0, 2, 3]])
    snap = make_snapshot(floor, [Material(specular=sp.SpecularLayer())], [], World(np.full(3, 0.5, np.float32)))
    with GISystem(snap, CacheSettings(resolution=8, rays_per_cell=256, hysteresis=0.0)) as gi:
        gi.warm_up(1)
        pts = np.array([[0, 0, 0], [1, 2, 0], [-3, 1, 0]], np.float32)
        up = np.tile([[0, 0, 1.0]], (3, 1)).astype(np.float32)
        eye = np.tile([[0.0, -0.6, 0.8]], (3, 1)).astype(np.float32)
        sky, bounced = glossy.cache_reflection(gi.cache, pts, up, eye, np.full(3, 0.5))
    np.testing.assert_allclose(sky, 0.5, rtol=0.04)
    assert bounced.max() < 0.01


@pytest.mark.parametrize("kind", ["POINT", "SPOT"])
def test_a_lamp_with_radius_and_without_soft_falloff_lights_the_lobes(kind):
    """A sphere lamp (Soft Falloff off) 1.5 m above a glossy floor: one weight per receiver, one
    per sample. Its samples' weights came out (n, 1) and `glossy_direct` raised on them (every
    render of such a lamp failed); far from the lamp it lights the lobes as the soft-falloff disc
    does (both subtend the same small solid angle)."""
    layer = sp.SpecularLayer(roughness=0.5)
    mats = glossy.GlossyMaterials.from_materials([Material(specular=layer)])
    matrix = np.eye(4)
    matrix[:3, 3] = (0.0, 0.0, 1.5)
    out = {}
    for soft in (True, False):
        lamp = Light(kind, np.ones(3, np.float32), 100.0, matrix, radius=0.05, soft_falloff=soft,
                     spot_size=2.5, spot_blend=0.0)
        out[soft] = glossy.glossy_direct([lamp], np.zeros((6, 3)), np.tile([[0.0, 0.0, 1.0]], (6, 1)),
                                         np.tile([[0.0, 0.6, 0.8]], (6, 1)), np.zeros(6, np.int32), mats, None,
                                         np.random.default_rng(2), samples=16)
    assert out[False].shape == (6, 3) and (out[False] > 0).all()
    np.testing.assert_allclose(out[False], out[True], rtol=0.02)


@pytest.mark.parametrize(("kind", "soft"), [("POINT", True), ("POINT", False), ("SPOT", True), ("SPOT", False)])
def test_lamp_samples_of_a_lamp_with_radius_give_the_diffuse_irradiance(kind, soft):
    """The glossy lobes see the emitter the diffuse pass does (`lights._radius_chunk`): the
    samples' weights times their cosine add up to its irradiance, across the horizon and inside
    the sphere too."""
    from hybridgi_core.lights import direct_irradiance

    matrix = np.eye(4)
    matrix[:3, 3] = (0.0, 0.0, 1.0)
    lamp = Light(kind, np.ones(3, np.float32), 100.0, matrix, radius=0.4, soft_falloff=soft,
                 spot_size=1.4, spot_blend=0.5)
    tilt = np.array([0.0, 0.8, 1.5, 1.7, 2.5])
    p = np.array([[0.3, 0.0, 0.0]] * 5 + [[0.1, 0.1, 0.8]] * 5)
    n = np.concatenate([np.stack([np.sin(tilt), 0 * tilt, np.cos(tilt)], 1)] * 2)
    dirs, weight, _targets = glossy._lamp_samples(lamp, p, np.random.default_rng(0), 8192)
    glossy_e = (weight * np.maximum((dirs * n[:, None, :]).sum(-1), 0.0)).sum(1)
    diffuse_e = direct_irradiance([lamp], p.astype(np.float32), n.astype(np.float32), None,
                                  np.random.default_rng(1), samples=8192)[:, 0]
    np.testing.assert_allclose(glossy_e, diffuse_e, rtol=0.02, atol=0.02 * diffuse_e.max())
    assert (diffuse_e > 0).sum() >= 7


def test_tabulated_glossy_color_follows_the_exact_one_per_material():
    """The per-pixel Glossy Color is read from each material's table over the view cosine: the
    exact value of its own material (rows -1 and materials without lobes: 0), grazing to normal."""
    layers = [sp.SpecularLayer(roughness=0.02, ior=2.5, metallic=0.5), None, sp.SpecularLayer(roughness=0.9),
              sp.SpecularLayer(roughness=0.3, metallic=1.0, metal_color=(0.9, 0.6, 0.2))]
    mats = glossy.GlossyMaterials.from_materials([Material(specular=layer) for layer in layers])
    rng = np.random.default_rng(4)
    mu = np.concatenate([[0.0, 1e-6, 0.5, 1.0, 1.2, -0.1], rng.random(5000)]).astype(np.float32)
    rows = rng.integers(-1, len(layers), mu.size)
    got = glossy.glossy_color(mats, rows, mu)
    assert got.dtype == np.float32 and got.shape == (mu.size, 3)
    for m, layer in enumerate(layers):
        sel = rows == m
        want = np.zeros((sel.sum(), 3)) if layer is None else sp.glossy_color(layer, np.clip(mu[sel], 0.0, 1.0))
        np.testing.assert_allclose(got[sel], want, atol=5e-4, err_msg=str(layer))
    assert not got[rows < 0].any()


def test_a_metallic_texture_picks_each_pixels_lobes_by_its_texel():
    """A material with a Metallic texture gets METALLIC_STEPS variant rows after the materials;
    the G-buffer's material texel (index + 1 + metallic / 2) picks the nearest one."""
    from hybridgi_core.glossy_image import material_rows

    layer = sp.SpecularLayer(roughness=0.4, weight=0.5, metallic=0.5, metal_color=np.full(3, 0.8, np.float32))
    plain = Material(name="plain", specular=sp.SpecularLayer(roughness=0.4))
    mapped = Material(name="mapped", texture=np.full((4, 4, 3), 0.4, np.float32), specular=layer,
                      metallic_map=np.tile(np.float32([0.0, 1.0]), (4, 2)))
    mats = glossy.GlossyMaterials.from_materials([plain, mapped])
    assert mats.variants.tolist() == [-1, 2] and len(mats.layers) == 2 + glossy.METALLIC_STEPS
    assert [mats.layers[2 + i].metallic for i in range(glossy.METALLIC_STEPS)] == [0.0, 0.25, 0.5, 0.75, 1.0]
    texels = np.float32([0.0, 1.0, 2.0, 2.0 + 0.5 * 0.3, 2.5, 1.0 + 0.5])
    assert material_rows(texels).tolist() == [-1, 0, 1, 1, 1, 0]  # without variants: the material's own row
    assert material_rows(texels, mats).tolist() == [-1, 0, 2, 3, 6, 0]
    # The metal variant reflects the base colour at normal incidence; the dielectric one ~4%.
    colour = glossy.glossy_color(mats, np.array([2, 6]), np.array([1.0, 1.0]))
    assert colour[1].mean() > 0.7 > 0.1 > colour[0].mean()


def test_a_roughness_texture_picks_each_pixels_lobes_by_its_texel():
    """A material with a Roughness texture gets ROUGHNESS_STEPS variants over its texels' range
    (with a Metallic texture too: metallic-major, METALLIC_STEPS x ROUGHNESS_STEPS); the
    G-buffer's fraction (variant + 0.5) / variants picks one. A constant-ish texture (spread
    under 0.02) gets none: its mean serves."""
    from hybridgi_core.glossy_image import material_rows

    stripes = np.tile(np.float32([0.2, 0.8]), (8, 4))
    rough = Material(name="rough", specular=sp.SpecularLayer(roughness=0.5), roughness_map=stripes)
    both = Material(name="both", texture=np.full((8, 8, 3), 0.4, np.float32),
                    specular=sp.SpecularLayer(roughness=0.5, weight=0.5, metallic=0.5),
                    metallic_map=np.tile(np.float32([0.0, 1.0]), (8, 4)), roughness_map=stripes)
    flat = Material(name="flat", specular=sp.SpecularLayer(roughness=0.5), roughness_map=np.full((4, 4), 0.5))
    mats = glossy.GlossyMaterials.from_materials([rough, both, flat])
    r, m = glossy.ROUGHNESS_STEPS, glossy.METALLIC_STEPS
    assert mats.variants.tolist() == [3, 3 + r, -1]
    assert mats.variant_steps.tolist() == [[1, r], [m, r], [1, 1]]
    np.testing.assert_allclose([mats.layers[3 + i].roughness for i in range(r)], np.linspace(0.2, 0.8, r), atol=1e-6)
    assert mats.layers[3 + r + 2 * r + 1].metallic == 0.5  # metallic step 2, roughness step 1
    code = lambda row, variant, count: np.float32(row + 1 + (variant + 0.5) / count)  # noqa: E731
    texels = np.float32([code(0, 0, r), code(0, r - 1, r), code(1, 2 * r + 1, m * r), 3.0])
    assert material_rows(texels, mats).tolist() == [3, 3 + r - 1, 3 + r + 2 * r + 1, 2]
    assert mats.rough[3] == pytest.approx(0.2) and mats.rough[3 + r - 1] == pytest.approx(0.8)


def test_a_textured_metals_colour_is_rebuilt_from_two_coordinates():
    """`metal_tint_basis`: the mean texel and the texture's two main colour axes; a texel's
    coordinates along them rebuild it (exactly for a texture of two colours and their mixes),
    so the lobe's colour per pixel is the texel over the mean. None without a metallic lobe or
    with a Metallic texture (the colour texture is then the diffuse base)."""
    texture = np.zeros((4, 4, 3), np.float32)
    texture[:, :2] = [0.8, 0.5, 0.2]
    texture[:, 2:] = [0.8, 0.8, 0.2]
    metal = Material(name="gold", texture=texture, base_color=np.zeros(3, np.float32),
                     specular=sp.SpecularLayer(roughness=0.3, weight=0.0, metallic=1.0,
                                               metal_color=texture.reshape(-1, 3).mean(0)))
    basis = glossy.metal_tint_basis(metal)
    np.testing.assert_allclose(basis[0], [0.8, 0.65, 0.2], atol=1e-6)
    texels = np.float32([[0.8, 0.5, 0.2], [0.8, 0.8, 0.2]])
    d = texels - basis[0]
    ratio = glossy.metal_tint(basis, d @ basis[1], d @ basis[2])
    np.testing.assert_allclose(ratio, texels / basis[0], atol=1e-5)
    assert glossy.metal_tint_basis(Material(name="plastic", texture=texture, specular=sp.SpecularLayer())) is None
    mapped = dict(specular=metal.specular, metallic_map=np.ones((4, 4), np.float32))
    assert glossy.metal_tint_basis(Material(name="mapped", texture=texture * 0.0, **mapped)) is None
    # Under a Metallic texture the colour texture is the diffuse base: the metal's is its own.
    np.testing.assert_allclose(glossy.metal_tint_basis(Material(name="mapped", texture=texture * 0.0,
                                                                metal_texture=texture, **mapped)), basis)
    mats = glossy.GlossyMaterials.from_materials([Material(name="plain"), metal])
    assert list(mats.tint_bases) == [1] and mats.metal_share[1] == pytest.approx(1.0, abs=0.02)


def test_many_lamps_are_drawn_per_pixel_and_their_glossy_light_stays_unbiased(monkeypatch):
    """Over GLOSSY_LAMP_BUDGET lamps, each receiver samples GLOSSY_LAMP_BUDGET draws of them by
    their rough light, weighted by one over their probability: the mean over frames is every
    lamp's light (a floor under 24 point lamps of different powers), and far fewer lamp samples
    are taken (each frame: the budget's draws per receiver, not the 24 lamps)."""
    from hybridgi_core import system as system_module
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.system import GISystem

    snap, lamps, (pts, up, eye, rows), _ = _floor_under_point_lamps(24, 64, seed=4)
    calls = []
    with GISystem(snap, CacheSettings(resolution=4, rays_per_cell=16)) as gi:
        monkeypatch.setattr(system_module, "glossy_direct", _counting(calls))
        # 8 lamps a call (the budget): every lamp sampled at every receiver.
        every = np.mean([sum(gi.glossy(pts, up, eye, rows, f, samples=16, lights=lamps[k:k + 8]) for k in (0, 8, 16))
                         for f in range(8)], axis=0)
        calls.clear()
        picked = np.mean([gi.glossy(pts, up, eye, rows, f, samples=16) for f in range(64)], axis=0)
    assert sum(calls) <= 64 * 64 * system_module.GLOSSY_LAMP_BUDGET
    total = every.sum(axis=1)
    assert total.min() > 0
    np.testing.assert_allclose(picked.sum(axis=1).mean(), total.mean(), rtol=0.03)
    np.testing.assert_allclose(picked.sum(axis=1), total, rtol=0.25)


def test_many_lamps_each_receiver_skipping_its_own_are_drawn_in_one_pass(monkeypatch):
    """Over GLOSSY_LAMP_BUDGET lamps, `reflection.lamp_glossy_without` draws each receiver's lamps
    among those it keeps (`_pick_lamps(allowed=)`) in one picked pass, not a picked pass per
    pattern of skipped lamps (a room lit by 50 point lamps met ~1300 patterns: 36 s of CPU in a
    47-s profiled 320x180 render): the mean over frames is the light of the kept lamps alone, a receiver
    that keeps none gets none, and the lamp samples stay within one pass's budget per frame."""
    from hybridgi_core import lights as lights_module
    from hybridgi_core import reflection
    from hybridgi_core import system as system_module
    from hybridgi_core.settings import CacheSettings
    from hybridgi_core.system import GISystem

    n = 48
    snap, lamps, (pts, up, eye, rows), rng = _floor_under_point_lamps(16, n, seed=6)
    skip = rng.random((n, 16)) < 0.5  # a pattern of its own at nearly every receiver
    skip[0] = True  # keeps none
    calls = []
    with GISystem(snap, CacheSettings(resolution=4, rays_per_cell=16)) as gi:
        # Each lamp alone at every receiver, kept where the receiver keeps it: the truth.
        each = np.stack([np.mean([gi.glossy(pts, up, eye, rows, f, samples=16, lights=[lt]) for f in range(4)], axis=0)
                         for lt in lamps], axis=1)  # (n, L, 3)
        kept = (each * (~skip)[:, :, None]).sum(axis=1)
        monkeypatch.setattr(system_module, "glossy_direct", _counting(calls))
        picked = np.mean([reflection.lamp_glossy_without(gi, pts, up, eye, rows, f, 16, skip) for f in range(64)],
                         axis=0)
    assert len(calls) <= 64 * 16  # one picked pass a frame: a call per lamp at most
    assert sum(calls) <= 64 * n * lights_module.GLOSSY_LAMP_BUDGET
    assert (picked[0] == 0).all() and kept[1:].sum(axis=1).min() > 0
    np.testing.assert_allclose(picked.sum(axis=1).mean(), kept.sum(axis=1).mean(), rtol=0.04)
    np.testing.assert_allclose(picked[1:].sum(axis=1), kept[1:].sum(axis=1), rtol=0.3)


def _floor_under_point_lamps(count: int, n: int, seed: int):
    """(snapshot, lamps, (points, normals, to_eye, rows) of n receivers on the floor, the rng
    drawn from): a floor of a rough dielectric under `count` point lamps of four powers."""
    from hybridgi_core.snapshot import geometry_from_arrays, make_snapshot

    rng = np.random.default_rng(seed)
    lamps = []
    for i in range(count):
        matrix = np.eye(4)
        matrix[:3, 3] = (rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(0.5, 2.0))
        lamps.append(Light(kind="POINT", color=np.ones(3, np.float32), power=float(5 + 10 * (i % 4)), matrix=matrix))
    floor = geometry_from_arrays([[-5, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]], [[0, 1, 2], [0, 2, 3]])
    snap = make_snapshot(floor, [Material(specular=sp.SpecularLayer(roughness=0.5))], lamps)
    pts = np.column_stack([rng.uniform(-2, 2, n), rng.uniform(-2, 2, n), np.zeros(n)]).astype(np.float32)
    receivers = (pts, np.tile([[0, 0, 1.0]], (n, 1)).astype(np.float32),
                 np.tile([[0.0, -0.6, 0.8]], (n, 1)).astype(np.float32), np.zeros(n, np.int32))
    return snap, lamps, receivers, rng


def _counting(calls: list):
    """`glossy.glossy_direct` that appends each call's lamps x receivers to `calls`."""
    real = glossy.glossy_direct

    def counted(lights, points, *args, **kwargs):
        calls.append(len(lights) * np.asarray(points).reshape(-1, 3).shape[0])
        return real(lights, points, *args, **kwargs)

    return counted
