"""A pixel ray's hit on a glossy surface reflects the cache's light through its lobes as the ray
sees them (`hit_glossy.py`): more where the mirror direction looks at the bright sky and the
view grazes (Fresnel), less where it looks at the dark ground, the same energy on average."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from hybridgi_core import hit_glossy
from hybridgi_core import specular as sp
from hybridgi_core.cache import IrradianceCache
from hybridgi_core.evaluate import HitLookup
from hybridgi_core.glossy import GlossyMaterials
from hybridgi_core.grid import CacheGrid
from hybridgi_core.outside import sky_above_horizon
from hybridgi_core.settings import CacheSettings
from hybridgi_core.snapshot import Material, World


def _system(coeffs: np.ndarray):
    """A 4^3 cache whose every cell holds the radiance SH coeffs (9, 3), read by hits of two
    materials: a default Principled BSDF's lobes (0) and a matte one (1)."""
    grid = CacheGrid.from_bounds(np.zeros(3, np.float32), np.full(3, 4.0, np.float32), 4)
    cache = IrradianceCache(grid, CacheSettings(resolution=4))
    cache.samples[:] = 1
    cache.sh_direct[:] = coeffs[None]
    materials = [Material(specular=sp.SpecularLayer(roughness=0.5)), Material()]
    surfaces = SimpleNamespace(material_index=np.array([0, 1]), filter_glossy=1.0)
    system = SimpleNamespace(glossy_materials=GlossyMaterials.from_materials(materials),
                             updater=SimpleNamespace(scene=SimpleNamespace(surfaces=surfaces)))
    return system, HitLookup(cache, bounced=False)


def _ratio(system, lookup, material, normal, to_eye):
    n = len(to_eye)
    dirs = -np.asarray(to_eye, np.float32)
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    return hit_glossy.view_ratio(system, lookup, np.full(n, material), np.full((n, 3), 2.0, np.float32),
                                 np.tile(np.asarray(normal, np.float32), (n, 1)), dirs)


def test_a_wall_reflects_the_sky_to_rays_from_below_and_the_ground_to_rays_from_above():
    """A wall under a sky over the upper hemisphere: a ray climbing onto it sees the sky in the
    lobe's mirror direction (2x the wall's irradiance / pi, which is half the sky's), a ray
    coming down sees the dark ground; a matte wall reflects the same towards both."""
    system, lookup = _system(sky_above_horizon(World(color=np.ones(3, np.float32)), 9))
    wall = (1.0, 0.0, 0.0)
    from_below, from_above = (0.6, 0.0, -0.8), (0.6, 0.0, 0.8)  # directions to the eye
    up, down = _ratio(system, lookup, 0, wall, [from_below, from_above])
    assert up.min() > 1.5 and down.max() < 0.5
    np.testing.assert_array_equal(_ratio(system, lookup, 1, wall, [from_below, from_above]), 1.0)


def test_under_a_uniform_sky_only_the_view_angle_moves_the_light_and_its_mean_is_kept():
    """Uniform radiance: the lobe reads what the irradiance does, so the factor is the Glossy
    Color's over its cosine-weighted mean: above 1 at grazing (the Fresnel), below at normal
    incidence, 1 on average over the cosine-weighted views."""
    system, lookup = _system(np.tile(np.eye(9, 1, dtype=np.float32) / 0.28209479177387814, (1, 3)))
    mu = (np.arange(256) + 0.5) / 256
    to_eye = np.stack([np.sqrt(1 - mu * mu), np.zeros_like(mu), mu], axis=1)
    ratio = _ratio(system, lookup, 0, (0.0, 0.0, 1.0), to_eye)[:, 1]
    assert ratio[0] > 2.0 * ratio[-1]
    np.testing.assert_allclose(np.mean(2.0 * mu * ratio), 1.0, atol=0.02)
