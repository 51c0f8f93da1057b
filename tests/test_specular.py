"""The Principled BSDF's specular layer (hybridgi_core/specular.py): its tables against Monte-Carlo
integrals of the GGX BRDF that share no code path with the quadrature, and the diffuse weight's
limits that Cycles' layering implies."""

from __future__ import annotations

import numpy as np
import pytest

from hybridgi_core import specular as sp
from hybridgi_core.shading import SurfaceTable
from hybridgi_core.snapshot import Geometry, Material


def _setup(rough, mu, n, seed):
    """GGX alpha^2 of a roughness, the incoming direction at cosine mu, and n directions uniform
    over the upper hemisphere (z = cosine uniform in [0, 1))."""
    rng = np.random.default_rng(seed)
    alpha2 = (max(rough, 1e-4) ** 2) ** 2
    wi = np.array([np.sqrt(1.0 - mu * mu), 0.0, mu])
    z = rng.random(n)
    phi = 2.0 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - z * z)
    return alpha2, wi, np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)


def _monte_carlo(rough, mu, n=400_000, eta=None, seed=0):
    """(mean, standard error) of the GGX (F = 1) directional albedo, or with eta of the lobe-
    weighted remapped Fresnel: outgoing directions uniform over the hemisphere, the BRDF evaluated
    in closed form (D, height-correlated Smith G2)."""
    alpha2, wi, wo = _setup(rough, mu, n, seed)
    z = wo[:, 2]
    h = wo + wi
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    c = h[:, 2]
    d = alpha2 / (np.pi * (c * c * (alpha2 - 1.0) + 1.0) ** 2)
    lam = lambda x: 0.5 * (np.sqrt(1.0 + alpha2 * (1.0 / (x * x) - 1.0)) - 1.0)  # noqa: E731
    g2 = 1.0 / (1.0 + lam(mu) + lam(z))
    f = d * g2 / (4.0 * mu) * 2.0 * np.pi  # brdf x cos(o) / pdf(o)
    if eta is None:
        return f.mean(), f.std() / np.sqrt(n)
    f0 = sp.f0_from_ior(eta)
    remap = np.clip((sp.fresnel_dielectric(h @ wi, eta) - f0) / (1.0 - f0), 0.0, 1.0)
    return (f * remap).mean() / f.mean(), None


@pytest.mark.parametrize("rough, mu", [(0.5, 1.0), (0.5, 0.3), (0.5, 0.08), (0.8, 0.15), (1.0, 0.5), (0.3, 0.6)])
def test_ggx_albedo_table_matches_monte_carlo(rough, mu):
    e_table = sp.tables()[0]
    mean, err = _monte_carlo(rough, mu)
    # Between grid points the table interpolates: check at the grid's own samples too.
    exact = sp._lobe_samples(rough, mu)[0].sum()
    assert abs(exact - mean) < 4 * err + 2e-3, (exact, mean, err)
    assert abs(sp._lerp_table(e_table, [rough, mu]) - exact) < 0.01


def _visible_normal_mean(rough, mu, g, n=400_000, seed=1):
    """Monte-Carlo mean of g(cos(h, i)) over GGX visible normals, a normal whose reflection
    goes below the horizon counting 0 (how Cycles' precompute averages its Fresnel tables):
    half vectors uniform over the hemisphere, weighted by the visible-normal density
    G1(i) max(0, h.i) D(h) / cos(i)."""
    alpha2, wi, h = _setup(rough, mu, n, seed)
    z = h[:, 2]
    cos_hi = h @ wi
    d = alpha2 / (np.pi * (z * z * (alpha2 - 1.0) + 1.0) ** 2)
    g1 = 1.0 / (1.0 + sp._lambda(alpha2, mu))
    density = g1 * np.maximum(cos_hi, 0.0) * d / mu
    valid = (2.0 * cos_hi * z - mu) > 0
    return float(np.mean(density * valid * g(np.clip(cos_hi, 0, 1))) * 2.0 * np.pi)


@pytest.mark.parametrize("i, j, k", [(8, 8, 7), (6, 3, 7), (14, 11, 10), (10, 1, 5)])
def test_fresnel_table_matches_cycles_definition(i, j, k):
    """Grid entries of the remapped-Fresnel table against an independent Monte-Carlo mean."""
    rough, mu, z = i / 15, j / 15, min(max(k / 15, 1e-4), 0.99)
    eta = sp.ior_from_f0(z**4)
    f0 = sp.f0_from_ior(eta)
    table = sp.tables()[2][k, i, j]
    mean = _visible_normal_mean(rough, mu, lambda c: np.clip((sp.fresnel_dielectric(c, eta) - f0) / (1 - f0), 0, 1))
    assert abs(table - mean) < 0.05 * mean + 2e-3, (table, mean)
    schlick = _visible_normal_mean(rough, mu, lambda c: (1.0 - c) ** 5)
    assert abs(sp.schlick_table()[i, j] - schlick) < 0.05 * schlick + 2e-3


def test_shipped_tables_are_the_computed_ones(tmp_path):
    """The render loads `specular_tables.npz` instead of computing; it must be what
    `compute_tables` gives now (rebuild it with `python -m hybridgi_core.specular`), and a file
    made for other grid sizes must be ignored, not read."""
    for shipped, computed in zip(sp.tables(), sp.compute_tables(), strict=True):
        np.testing.assert_allclose(shipped, computed, rtol=0, atol=1e-12)
    sp.schlick_table.cache_clear()
    np.testing.assert_allclose(sp.schlick_table(), sp.compute_schlick_table(), rtol=0, atol=1e-12)
    stale = tmp_path / "stale.npz"
    sp.write_tables(stale)
    with np.load(stale) as data:
        np.savez(stale, key=data["key"] + 1, e=data["e"] * 0, e_avg=data["e_avg"], s=data["s"])
    old = sp.TABLES_FILE
    try:
        sp.TABLES_FILE = stale
        sp.tables.cache_clear()
        sp.schlick_table.cache_clear()
        np.testing.assert_allclose(sp.tables()[0], sp.compute_tables()[0], rtol=0, atol=1e-12)
        np.testing.assert_allclose(sp.schlick_table(), sp.compute_schlick_table(), rtol=0, atol=1e-12)
    finally:
        sp.TABLES_FILE = old
        sp.tables.cache_clear()
        sp.schlick_table.cache_clear()


def test_average_albedo_falls_with_roughness():
    _, e_avg, _ = sp.tables()
    assert e_avg[0] == pytest.approx(1.0, abs=2e-3)  # a mirror loses nothing to masking
    assert np.all(np.diff(e_avg) <= 1e-6)
    assert 0.4 < e_avg[-1] < 0.6  # Kulla & Conty: about half the energy at roughness 1


def test_diffuse_weight_limits():
    mu = np.linspace(0.0, 1.0, 11)
    default = sp.diffuse_weight(sp.SpecularLayer(), mu)
    # Specular IOR Level 0 removes the layer (Cycles allocates no closure at eta 1).
    assert np.all(sp.diffuse_weight(sp.SpecularLayer(level=0.0), mu) == 1.0)
    assert np.all(sp.diffuse_weight(None, mu) == 1.0)
    # A smooth dielectric facing the camera reflects its F0, 0.04 at IOR 1.5.
    smooth = sp.diffuse_weight(sp.SpecularLayer(roughness=0.0), 1.0)
    assert smooth == pytest.approx(1.0 - sp.f0_from_ior(1.5), abs=2e-3)
    # Fresnel: the layer takes more at grazing angles; a stronger layer takes more everywhere.
    assert default[0] < default[5] < default[-1] < 1.0
    assert np.all(sp.diffuse_weight(sp.SpecularLayer(level=1.0), mu) < default)
    assert np.all(sp.diffuse_weight(sp.SpecularLayer(ior=1.45), mu) > default)
    # Specular IOR Level 1 doubles F0.
    doubled = sp.SpecularLayer(roughness=0.0, level=1.0)
    assert sp.f0_from_ior(doubled.eta) == pytest.approx(2 * sp.f0_from_ior(1.5), rel=1e-6)
    # A tinted layer weighs the base by its strongest channel, as closure_layering_weight does.
    tinted = sp.SpecularLayer(tint=(1.0, 0.0, 0.0))
    assert np.allclose(sp.diffuse_weight(tinted, mu), default, atol=1e-6)
    hemi = sp.hemispherical_diffuse_weight(sp.SpecularLayer())
    assert default.min() < hemi < default.max()


def test_bad_layer_inputs_are_clamped():
    layer = sp.SpecularLayer(roughness=np.nan, ior=-3.0, level=np.inf, tint=(np.nan, -1.0, 2.0))
    weight = sp.diffuse_weight(layer, np.linspace(0, 1, 5))
    assert np.isfinite(weight).all() and (weight >= 0).all() and (weight <= 1).all()
    assert layer.roughness == 0.5 and np.all(layer.tint >= 0)


def test_probe_hits_see_the_layer_as_its_hemispherical_mean():
    geometry = Geometry(positions=np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32),
                        triangles=np.array([[0, 1, 2]], np.int32), normals=np.tile([[0, 0, 1]], (3, 1)).astype(np.float32),
                        uvs=np.full((3, 2), np.nan, np.float32), material_index=np.zeros(1, np.int32),
                        object_index=np.zeros(1, np.int32))
    base = np.array([0.6, 0.5, 0.4], np.float32)
    plain = SurfaceTable(geometry, [Material(base_color=base)])
    layered = SurfaceTable(geometry, [Material(base_color=base, specular=sp.SpecularLayer())])
    dirs = np.array([[0, 0, -1]], np.float32)
    hit = lambda t: t.probe_hits(np.zeros(1, np.int32), np.zeros(1, np.float32), np.zeros(1, np.float32), dirs).brdf[0]  # noqa: E731
    w = sp.hemispherical_diffuse_weight(sp.SpecularLayer())
    glossy = sp.hemispherical_glossy_albedo(sp.SpecularLayer())
    assert np.allclose(hit(plain), base / np.pi)
    assert np.allclose(hit(layered), (base * w + glossy) / np.pi, rtol=1e-5)
    # Energy: the diffuse share lost is about what the white layer reflects.
    assert 0.0 < glossy[0] < 0.15 and abs((1.0 - w) - glossy[0]) < 0.03


def test_hit_glossy_albedo_follows_cycles_filter_glossy():
    """Cycles blurs a hit's lobes after a diffuse bounce to roughness >= ~0.64 (Filter Glossy 1)
    after their setup: a smooth layer's hits reflect the blurred lobe's energy (less), a rough
    one's are untouched, and Filter Glossy 0 keeps the sharp lobe's mean albedo."""
    mu = (np.arange(64) + 0.5) / 64
    rough, weight = sp.hit_blur_roughness(1.0)
    assert 0.64 < rough.min() and rough.max() < 0.71 and weight.sum() == pytest.approx(1.0)
    for r in (0.1, 0.2, 0.5):
        layer = sp.SpecularLayer(roughness=r)
        sharp = np.mean(2.0 * sp.layer_albedo(layer, mu) * mu[:, None], axis=0)
        assert np.allclose(sp.hemispherical_glossy_albedo(layer, 0.0), sharp, rtol=1e-5)
        assert np.all(sp.hemispherical_glossy_albedo(layer) < (0.8 if r < 0.4 else 1.0) * sharp)
    rough_layer = sp.SpecularLayer(roughness=0.8)
    assert np.allclose(sp.hemispherical_glossy_albedo(rough_layer), sp.hemispherical_glossy_albedo(rough_layer, 0.0))
    # A metal loses its blurred multiple scattering too, in proportion.
    metal = sp.SpecularLayer(roughness=0.2, metallic=1.0, weight=0.0, metal_color=(0.9, 0.6, 0.3))
    assert np.all(sp.hemispherical_glossy_albedo(metal) < sp.hemispherical_glossy_albedo(metal, 0.0))
    assert np.all(sp.hemispherical_glossy_albedo(metal) > 0.5 * sp.hemispherical_glossy_albedo(metal, 0.0))


def test_a_coat_adds_its_lobe_and_weighs_what_lies_under_it():
    """Cycles' coat: a GGX lobe of weight `coat` with the dielectric Fresnel of its IOR over the
    layer; the diffuse base and the lobes under it are weighted 1 - coat x max(its albedo) at the
    view angle and tinted 1 + coat (tint - 1). Without a coat, nothing changes."""
    plain = sp.SpecularLayer(roughness=0.5, metallic=0.3, metal_color=np.float32([0.9, 0.6, 0.3]), weight=0.7)
    coated = sp.SpecularLayer(roughness=0.5, metallic=0.3, metal_color=np.float32([0.9, 0.6, 0.3]), weight=0.7,
                              coat=0.8, coat_roughness=0.05, coat_tint=np.float32([1.0, 0.5, 0.5]))
    mu = np.linspace(0.05, 1.0, 9)
    coat_albedo = sp.layer_albedo(sp.SpecularLayer(roughness=0.05, ior=1.5, multiscatter=False), mu).max(axis=-1)
    np.testing.assert_allclose(sp.diffuse_weight(coated, mu), sp.diffuse_weight(plain, mu) * (1 - 0.8 * coat_albedo),
                               rtol=1e-6)
    lobes, base = sp.layer_lobes(coated), sp.layer_lobes(plain)
    assert len(lobes) == len(base) + 1 and lobes[-1].roughness == pytest.approx(0.05)
    under = (1 - 0.8 * coat_albedo)[:, None] * np.float64([1.0, 0.6, 0.6])
    expected = under * sum(sp.lobe_color(lobe, mu) for lobe in base) + sp.lobe_color(lobes[-1], mu)
    np.testing.assert_allclose(sp.glossy_color(coated, mu), expected, rtol=2e-3, atol=1e-4)
    assert len(sp.layer_lobes(sp.SpecularLayer(coat=0.0))) == len(sp.layer_lobes(sp.SpecularLayer()))
    np.testing.assert_array_equal(sp.glossy_color(sp.SpecularLayer(coat=0.0), mu), sp.glossy_color(sp.SpecularLayer(), mu))
