"""Probe-hit shading inputs: the packed surface table and the update's two shading layouts."""

import numpy as np
import pytest

from hybridgi_core import update
from hybridgi_core.settings import CacheSettings
from hybridgi_core.shading import SurfaceTable
from hybridgi_core.snapshot import Material, World, concat_geometry, geometry_from_arrays, make_snapshot
from hybridgi_core.system import GISystem
from tests.shapes import box
from tests.test_lights import sun_light

QUAD = [[0, 0, 0], [2, 0, 0], [2, 1, 0], [0, 1, 0]]


def floor_quads():
    """Two unit-UV quads on z = 0: x in [0, 2] textured (material 0), x in [3, 5] plain (1)."""
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], np.float32)
    up = np.tile([[0, 0, 1.0]], (4, 1))
    textured = geometry_from_arrays(QUAD, [[0, 1, 2], [0, 2, 3]], 0, normals=up, uvs=uv)
    plain = geometry_from_arrays(np.add(QUAD, [3, 0, 0]), [[0, 1, 2], [0, 2, 3]], 1, normals=up, uvs=uv)
    return concat_geometry([textured, plain])


def test_probe_hits_read_texture_base_colour_emission_and_misses():
    tex = np.zeros((1, 2, 3), np.float32)
    tex[0, 0] = (1.0, 0.0, 0.0)  # u < 0.5 red
    tex[0, 1] = (0.0, 1.0, 0.0)  # u > 0.5 green
    mats = [
        Material("tex", np.full(3, 0.5, np.float32), tex),
        Material("lamp", np.array([0.2, 0.4, 0.6], np.float32), None, np.array([3.0, 2.0, 1.0], np.float32)),
    ]
    table = SurfaceTable(floor_quads(), mats)
    # Rays straight down onto x = 0.25 (red texel), x = 1.75 (green), the plain quad, and a miss.
    prim = np.array([0, 0, 2, -1], np.int32)
    u = np.array([0.125, 0.875, 0.5, 0.0], np.float32)  # triangle (0, 1, 2): u weights vertex 1
    v = np.array([0.0, 0.0, 0.25, 0.0], np.float32)
    down = np.tile([[0, 0, -1.0]], (4, 1)).astype(np.float32)
    h = table.probe_hits(prim, u, v, down)
    inv_pi = 1.0 / np.pi
    texel_blend = 0.5 * np.array([[0.75, 0.25, 0], [0.25, 0.75, 0]])  # bilinear across the 2 texels
    np.testing.assert_allclose(h.brdf[:2], texel_blend * inv_pi, atol=1e-6)
    np.testing.assert_allclose(h.brdf[2], mats[1].base_color * inv_pi, atol=1e-7)
    np.testing.assert_allclose(h.emission[2], mats[1].emission)
    np.testing.assert_allclose(h.normal[:3], np.tile([0, 0, 1.0], (3, 1)), atol=1e-6)
    assert not h.backface[:3].any()
    # A miss reads the zero record: no light, no normal, no NaN.
    assert (h.brdf[3] == 0).all() and (h.emission[3] == 0).all() and (h.normal[3] == 0).all()
    # From below the floor the normal turns to the ray and the hit counts as a back face.
    up = table.probe_hits(prim[:1], u[:1], v[:1], -down[:1])
    np.testing.assert_allclose(up.normal[0], [0, 0, -1.0], atol=1e-6)
    assert up.backface[0]


def test_a_metallic_textures_hits_take_their_texels_glossy_albedo():
    """A Metallic texture (left texel metal, right dielectric): a hit's glossy albedo and brdf are
    its texel's (`shading._metal_glossy`: the lobes' weights are linear in the metallic), not the
    material's mean for every hit; the mean texel gives the mean. Before, every hit of the floor
    took half a metal's glossy albedo."""
    from hybridgi_core import specular as sp

    metal_map = np.array([[1.0, 0.0]], np.float32)
    base = np.full((1, 2, 3), 0.8, np.float32) * (1.0 - metal_map)[..., None]  # the diffuse base per texel
    layer = sp.SpecularLayer(roughness=0.4, metallic=0.5, weight=0.5, metal_color=np.float32([0.9, 0.6, 0.3]))
    mats = [Material("metal", np.ones(3, np.float32), base, specular=layer, metallic_map=metal_map), Material()]
    table = SurfaceTable(floor_quads(), mats)
    lo = sp.hemispherical_glossy_albedo(sp.SpecularLayer(roughness=0.4, metallic=0.0, weight=1.0))
    hi = sp.hemispherical_glossy_albedo(sp.SpecularLayer(roughness=0.4, metallic=1.0, weight=0.0,
                                                         metal_color=np.float32([0.9, 0.6, 0.3])))
    np.testing.assert_allclose(0.5 * (lo + hi), table.glossy[0], rtol=1e-5)  # linear in the metallic
    assert hi[0] > 5 * lo[0]
    # Hits at the centres of the metal and the dielectric texel (triangle (0, 1, 2): u weighs vertex 1).
    prim = np.array([0, 0], np.int32)
    u = np.array([0.125, 0.875], np.float32)
    v = np.zeros(2, np.float32)
    down = np.tile([[0, 0, -1.0]], (2, 1)).astype(np.float32)
    texel = np.array([0.75, 0.25], np.float32)[:, None]  # the metal's share of each hit's bilinear taps
    glossy = lo + texel * (hi - lo)
    np.testing.assert_allclose(table.glossy_brdf(prim, u, v), glossy / np.pi, rtol=1e-5)
    np.testing.assert_allclose(table.glossy_brdf(prim), np.tile(table.glossy[0], (2, 1)) / np.pi, rtol=1e-6)
    hits = table.probe_hits(prim, u, v, down)
    diffuse = table.albedo[0] * (0.8 * (1.0 - texel))
    np.testing.assert_allclose(hits.brdf, (diffuse + glossy) / np.pi, rtol=1e-5)


def test_hits_read_an_emission_texture_at_their_uv():
    glow = np.zeros((1, 2, 3), np.float32)
    glow[0, 0] = (8.0, 0.0, 0.0)  # u < 0.5 red
    glow[0, 1] = (0.0, 0.0, 4.0)  # u > 0.5 blue
    mats = [Material("tv", np.zeros(3, np.float32), emission_texture=glow), Material("plain")]
    np.testing.assert_allclose(mats[0].emission, [4.0, 0.0, 2.0])  # the mean stands for it without UVs
    table = SurfaceTable(floor_quads(), mats)
    assert table.emissive
    prim = np.array([0, 0, 2, -1], np.int32)
    u = np.array([0.125, 0.875, 0.5, 0.0], np.float32)
    v = np.array([0.0, 0.0, 0.25, 0.0], np.float32)
    down = np.tile([[0, 0, -1.0]], (4, 1)).astype(np.float32)
    expect = np.array([[6.0, 0.0, 1.0], [2.0, 0.0, 3.0], [0, 0, 0], [0, 0, 0]])  # bilinear across the 2 texels
    np.testing.assert_allclose(table.probe_hits(prim, u, v, down).emission, expect, atol=1e-5)
    np.testing.assert_allclose(table.emission_of(prim, u, v), expect, atol=1e-5)
    np.testing.assert_allclose(table.surface(prim[:3], u[:3], v[:3], down[:3]).emission, expect[:3], atol=1e-5)
    np.testing.assert_allclose(table.emission_of(prim), [[4.0, 0, 2.0]] * 2 + [[0, 0, 0]] * 2)


def test_probe_hits_take_the_geometric_normal_image_pixels_the_smooth_one():
    """Probe hits only feed a cell's average, so they skip normal interpolation; `surface` (image
    pixels) keeps the smooth normal. Both follow a triangle that moves (update_rows)."""
    tilt = np.array([0.6, 0.0, 0.8], np.float32)
    geo = geometry_from_arrays(QUAD, [[0, 1, 2], [0, 2, 3]], 0, normals=np.tile(tilt, (4, 1)))
    table = SurfaceTable(geo, [Material()])
    prim = np.array([0, 1], np.int32)
    u = np.array([0.25, 0.25], np.float32)
    v = np.array([0.25, 0.5], np.float32)
    down = np.tile([[0, 0, -1.0]], (2, 1)).astype(np.float32)
    np.testing.assert_allclose(table.probe_hits(prim, u, v, down).normal, [[0, 0, 1.0]] * 2, atol=1e-6)
    np.testing.assert_allclose(table.surface(prim, u, v, down).normal, [tilt] * 2, atol=1e-6)
    # Stand triangle 1 up in the xz plane: its winding now faces -y; a ray along +y meets its front.
    upright = geo.positions[:, [0, 2, 1]]
    table.update_rows(geometry_from_arrays(upright, geo.triangles, 0, normals=geo.normals), np.array([1]))
    along_y = np.array([[0, 0, -1.0], [0, 1.0, 0]], np.float32)
    h = table.probe_hits(prim, u, v, along_y)
    np.testing.assert_allclose(h.normal, [[0, 0, 1.0], [0, -1.0, 0]], atol=1e-6)
    assert not h.backface.any()
    assert table.probe_hits(prim[1:], u[1:], v[1:], -along_y[1:]).backface[0]


def test_surface_positions_follow_moved_rows():
    geo = floor_quads()
    table = SurfaceTable(geo, [Material(), Material()])
    prim = np.array([0, 3], np.int32)
    u = np.array([0.25, 0.5], np.float32)
    v = np.array([0.25, 0.25], np.float32)
    down = np.tile([[0, 0, -1.0]], (2, 1)).astype(np.float32)
    before = table.surface(prim, u, v, down).position
    tri = geo.positions[geo.triangles[prim]]
    expected = tri[:, 0] + u[:, None] * (tri[:, 1] - tri[:, 0]) + v[:, None] * (tri[:, 2] - tri[:, 0])
    np.testing.assert_allclose(before, expected, atol=1e-6)
    moved = geometry_from_arrays(geo.positions + [0, 0, 1.0], geo.triangles, geo.material_index,
                                 normals=-geo.normals, uvs=geo.uvs)
    table.update_rows(moved, np.array([3]))
    after = table.surface(prim, u, v, down)
    np.testing.assert_allclose(after.position[0], before[0], atol=1e-6)  # row 0 kept
    np.testing.assert_allclose(after.position[1], before[1] + [0, 0, 1.0], atol=1e-6)
    assert after.backface[1] and not after.backface[0]  # row 3's normals were flipped


@pytest.mark.parametrize("scene", ["closed", "open"])
def test_compacted_and_whole_batch_shading_agree(monkeypatch, scene):
    """Hits are shaded either in place (mostly hits) or compacted (mostly misses): same cache."""
    sun = sun_light([0.3, 0.2, -1.0])
    room = box([0, 0, 0], [2, 2, 2]) if scene == "closed" else geometry_from_arrays(
        [[-4, -4, 0], [4, -4, 0], [4, 4, 0], [-4, 4, 0]], [[0, 1, 2], [0, 2, 3]])
    mat = Material("m", np.array([0.7, 0.5, 0.3], np.float32), None, np.array([0.2, 0.1, 0.0], np.float32))
    snap = make_snapshot(concat_geometry([room, box([0.6, 0.6, 0.0], [1.2, 1.2, 0.7], inward=False)]), [mat],
                         [sun], World(np.full(3, 0.4, np.float32)))
    settings = CacheSettings(resolution=6, rays_per_cell=32, threads=1)

    def run(threshold):
        monkeypatch.setattr(update, "COMPACT_BELOW", threshold)
        with GISystem(snap, settings) as gi:
            gi.warm_up(4)
            return gi.cache.sh_direct.copy(), gi.cache.sh_indirect.copy(), gi.cache.ao_sh.copy()

    whole, compact = run(0.0), run(1.01)
    assert whole[1][:, 0].max() > 0.01  # bounce light exists, so the comparison means something
    for a, b in zip(whole, compact, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


def test_a_mix_shader_weighs_an_emission_texture_and_adds_the_other_emission():
    """Mix(textured emitter, constant emitter, Fac 0.25): 0.75 x texture + 0.25 x constant per
    texel, as Cycles adds the weighted emission closures; no texture stays no texture."""
    from hybridgi_core import surface_mix  # noqa: PLC0415

    glow = np.zeros((1, 2, 3), np.float32)
    glow[0, 0], glow[0, 1] = (8.0, 0.0, 0.0), (0.0, 0.0, 4.0)
    textured = surface_mix.SurfacePart(emission=glow.reshape(-1, 3).mean(axis=0), emission_texture=glow)
    flat = surface_mix.SurfacePart(emission=np.array([0.0, 4.0, 0.0], np.float32))
    part, notes = surface_mix.mix([textured, flat], [surface_mix.constant_factor(0.75), surface_mix.constant_factor(0.25)])
    np.testing.assert_allclose(part.emission_texture, 0.75 * glow + [0.0, 1.0, 0.0], rtol=1e-5)
    assert not notes
    plain, _ = surface_mix.mix([flat, flat], [surface_mix.constant_factor(0.5)] * 2)
    assert plain.emission_texture is None
    np.testing.assert_allclose(plain.emission, [0.0, 4.0, 0.0], rtol=1e-6)


def test_emitters_seen_with_a_chance_are_left_to_the_rays():
    """An emissive quad seen with a chance (`Material.coverage` 0.5: a glowing veil of Alpha 0.5)
    is not sampled as a light (`SurfaceTable.emitters`): rays meet its emission with that chance,
    where samples would light as if it were whole. The same quad seen whole is sampled."""
    glow = np.array([3.0, 2.0, 1.0], np.float32)
    whole = SurfaceTable(floor_quads(), [Material("floor"), Material("lamp", emission=glow)])
    assert whole.emitters is not None and whole.sampled[2:4].all()
    veiled = SurfaceTable(floor_quads(), [Material("floor"), Material("lamp", emission=glow, coverage=0.5)])
    assert veiled.emitters is None and not veiled.sampled.any()
    # Its rays still bring the emission where they meet it.
    np.testing.assert_allclose(veiled.emission_of(np.array([2])), [glow])
