"""Tangent-space normal maps and image Bump nodes: the read (sync), the G-buffer's maths, Cycles'
bump shadowing term, the viewport, and renders through the real `hybridgi render` command
against Cycles.

The render scenes: two planes and a smooth UV sphere under a 20-degree sun, their Principled
BSDF's Normal fed by Image Texture (Non-Color, sinusoidal ridges with 50-degree flanks written
with numpy, packed) -> Normal Map (Tangent Space, Strength 1 and 0.5), or by the same ridges as
a height -> Bump (Distance 0.25, Strength 0.5 inverted). Before HybridGI read them its Diffuse
Direct was off by rel L1 0.61 and 0.55 (mean +22%, +17%): every pixel had the smooth normal.
"""

from __future__ import annotations

import importlib
import json
import logging
import math
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from hybridgi_cli import blender_compat, exr
from hybridgi_core import sh
from hybridgi_core.bump import irradiance_kernel, shadowing_term
from hybridgi_core.snapshot import BumpMap, Material, NormalMap, concat_geometry, make_snapshot
from tests.cli_renders import QUICK, layer, rendered, run_render

# --- Cycles' bump shadowing term (bpy-free) ---------------------------------------------------


def _unit(v):
    v = np.asarray(v, np.float64)
    return (v / np.linalg.norm(v, axis=-1, keepdims=True)).astype(np.float32)


def test_bump_shadowing_term_matches_cycles_closed_form():
    up = _unit([[0, 0, 1]])
    ridge = _unit([[math.sin(math.radians(50)), 0, math.cos(math.radians(50))]])
    sun = _unit([[math.cos(math.radians(20)), 0, math.sin(math.radians(20))]])
    # Unbent normal: no shadowing, whatever the light.
    assert shadowing_term(up, up, sun)[0] == 1.0
    # GGX G1(|Ns.wi|) with alpha^2 = tan^2(Ns, N) / 8 (Cycles' bsdf.h, bump map correction on).
    tan2_d = math.tan(math.radians(50)) ** 2
    tan2_i = math.tan(math.radians(70)) ** 2
    want = 2.0 / (1.0 + math.sqrt(1.0 + tan2_d / 8.0 * tan2_i))
    assert abs(float(shadowing_term(up, ridge, sun)[0]) - want) < 1e-5
    assert 0.7 < want < 0.8  # a crest facing a low sun is a quarter darker than its cosine
    # Light below the smooth surface that the bent normal would still face: none.
    below = _unit([[1.0, 0.0, -0.1]])
    assert shadowing_term(up, ridge, below)[0] == 0.0


def test_map_bend_factor_is_the_bent_lobes_share_of_the_cosine_lobe():
    """A flat map (or Strength 0) keeps all of the smooth surface's light; a map tilting every
    texel by one angle keeps the bent lobe's integral over pi at that angle (the table's), a
    stronger tilt less; larger maps are averaged over a strided subset."""
    from hybridgi_core.bump import LOBE_ANGLES, lobe_moments, map_bend_factor
    from hybridgi_core.snapshot import NormalMap

    flat = np.full((8, 8, 3), (0.5, 0.5, 1.0), np.float32)
    assert map_bend_factor(None) == 1.0
    assert map_bend_factor(NormalMap(texture=flat)) == pytest.approx(1.0, abs=2e-3)
    tilt = np.radians(40.0)
    tilted = np.full((8, 8, 3), (0.5 + 0.5 * np.sin(tilt), 0.5, 0.5 + 0.5 * np.cos(tilt)), np.float32)
    want = np.interp(40.0 / 90.0 * (LOBE_ANGLES - 1), np.arange(LOBE_ANGLES), lobe_moments()[:, 0] / np.pi)
    assert map_bend_factor(NormalMap(texture=tilted)) == pytest.approx(want, rel=2e-3)
    assert 0.5 < want < 0.95
    assert map_bend_factor(NormalMap(texture=tilted, strength=0.0)) == 1.0
    steeper = np.full((8, 8, 3), (0.5 + 0.5 * np.sin(1.2), 0.5, 0.5 + 0.5 * np.cos(1.2)), np.float32)
    assert map_bend_factor(NormalMap(texture=steeper)) < want
    big = np.tile(tilted, (64, 64, 1))
    assert map_bend_factor(NormalMap(texture=big)) == pytest.approx(want, rel=2e-3)


def test_shipped_lobe_moments_are_the_computed_ones(tmp_path, monkeypatch):
    """Renders of normal maps load `bump_lobe_moments.npz` instead of computing it: it must be
    what `compute_lobe_moments` gives now (rebuild it with `python -m hybridgi_core.bump`), and a
    file made for other sizes must be ignored, not read."""
    from hybridgi_core import bump

    bump._lobe_moments.cache_clear()
    try:
        np.testing.assert_allclose(bump._lobe_moments(), bump.compute_lobe_moments(), rtol=0, atol=1e-12)
        stale = tmp_path / "stale.npz"
        np.savez(stale, key=bump.LOBE_KEY + 1, moments=np.zeros((bump.LOBE_ANGLES, 7)))
        monkeypatch.setattr(bump, "LOBE_FILE", stale)
        bump._lobe_moments.cache_clear()
        np.testing.assert_allclose(bump._lobe_moments(), bump.compute_lobe_moments(), rtol=0, atol=1e-12)
    finally:
        bump._lobe_moments.cache_clear()


def test_irradiance_kernel_is_cycles_bent_lobe_over_the_sh():
    """`irradiance_kernel`: sum_k kernel_k L_k = int L(w) max(0, N.w) term(Ns, N, w) dw for any
    L2 SH radiance (a Monte Carlo reference over the sphere); exactly the cosine convolution
    where the normal is not bent; nothing of light from below the smooth surface."""
    rng = np.random.default_rng(5)
    smooth = _unit(rng.normal(size=(3, 3)))
    np.testing.assert_array_equal(irradiance_kernel(smooth, smooth, 2), sh.basis(smooth, 2) * sh.cosine_scale(2))
    tilt = np.radians([20.0, 50.0, 75.0])
    bent = np.stack([np.sin(tilt), np.zeros(3), np.cos(tilt)], axis=1).astype(np.float32)
    up = np.tile(np.array([[0.0, 0.0, 1.0]], np.float32), (3, 1))
    kernel = irradiance_kernel(up, bent, 2)
    w = _unit(rng.normal(size=(200000, 3)))
    y = sh.basis(w, 2).astype(np.float64)
    for i in range(3):
        lobe = np.maximum(w @ bent[i], 0.0) * shadowing_term(np.broadcast_to(up[i], w.shape),
                                                            np.broadcast_to(bent[i], w.shape), w)
        want = (y * lobe[:, None]).mean(axis=0) * 4.0 * np.pi
        np.testing.assert_allclose(kernel[i], want, atol=0.02)
    # Light only from below the smooth surface (radiance 1 there: L = (1 - z-sign) / 2 in L1 ~)
    # reaches a 75-degree bend's cosine lobe, but not Cycles' bent lobe.
    below = np.zeros(9, np.float32)
    below[0], below[2] = 0.5 / sh.C0, -0.75 / sh.C1  # 0.5 - 0.75 z: brighter below the plane
    plain = float(sh.basis(bent[2:], 2)[0] * sh.cosine_scale(2) @ below)
    assert float(kernel[2] @ below) < 0.5 * plain


# --- the G-buffer applies the map as Cycles' svm_node_normal_map -------------------------------


@pytest.fixture(scope="module")
def gbuffer(gpu_context):
    from hybridgi_core.raster.gbuffer import GBufferPass
    from tests.test_raster import H, W

    gb = GBufferPass()
    gb.create()
    gb.resize(W, H)
    yield gb
    gb.free()


@pytest.mark.blender
def test_gbuffer_normal_follows_tangent_frame_sign_and_strength(gbuffer):
    from tests.test_raster import interior, look_at, perspective, quad

    # Constant tangent-space normal, stored as (n + 1) / 2.
    n_ts = _unit([0.3, -0.4, 0.85])
    texel = np.broadcast_to((n_ts + 1.0) / 2.0, (2, 2, 3)).astype(np.float32)
    uv = [[0, 0], [1, 0], [1, 1], [0, 1]]
    left = quad((-2.0, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv, material=0)
    right = quad((0.1, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv, material=1)
    geo = concat_geometry([left, right])
    # A tangent turned 30 degrees in the plane, bitangent sign -1 (a mirrored UV island).
    theta = math.radians(30)
    tangent = np.array([math.cos(theta), math.sin(theta), 0.0], np.float32)
    geo.tangents = np.tile(np.array([*tangent, -1.0], np.float32), (geo.positions.shape[0], 1))
    materials = [Material(name="full", normal_map=NormalMap(texel, strength=1.0)),
                 Material(name="half", normal_map=NormalMap(texel, strength=0.5))]
    snap = make_snapshot(geo, materials)
    view = look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    gbuffer.upload(snap)
    gbuffer.execute(view, perspective(30.0))
    normal = gbuffer.read("normal")[..., :3]
    side = np.where(gbuffer.read("position")[..., 3] > 0.5,
                    (gbuffer.read("position")[..., 0] > 0.0).astype(np.int32), -1)

    n = np.array([0.0, 0.0, 1.0])
    bitangent = -1.0 * np.cross(n, tangent)
    mapped = _unit(n_ts[0] * tangent + n_ts[1] * bitangent + n_ts[2] * n)
    half = _unit(n + (mapped - n) * 0.5)
    inner = interior(side)
    for label, want in ((0, mapped), (1, half)):
        got = normal[inner & (side == label)]
        assert got.shape[0] > 20
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=3e-3)


@pytest.mark.blender
def test_gbuffer_keeps_the_smooth_surface_under_the_bent_normal(gbuffer):
    """The material target's gba hold the interpolated normal before the map bends it
    (`read_surface`): the surface that edge tests, filter guides and the bump term compare.
    Without a normal map the shading normal is that surface, and no read-back is made."""
    from tests.test_raster import look_at, perspective, quad

    n_ts = _unit([0.6, 0.0, 0.8])
    texel = np.broadcast_to((n_ts + 1.0) / 2.0, (2, 2, 3)).astype(np.float32)
    uv = [[0, 0], [1, 0], [1, 1], [0, 1]]
    geo = concat_geometry([quad((-2.0, -1.0, 0.0), (4.0, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv, material=0)])
    geo.tangents = np.tile(np.array([1.0, 0.0, 0.0, 1.0], np.float32), (geo.positions.shape[0], 1))
    view = look_at((0.0, -2.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    gbuffer.upload(make_snapshot(geo, [Material(name="mapped", normal_map=NormalMap(texel))]))
    gbuffer.execute(view, perspective(30.0))
    normal = gbuffer.read("normal")
    surface = gbuffer.read_surface(normal)
    on = gbuffer.read("position")[..., 3] > 0.5
    assert on.sum() > 100 and surface.shape == normal.shape
    np.testing.assert_allclose(surface[on][:, :3], np.broadcast_to([0.0, 0.0, 1.0], (on.sum(), 3)), atol=1e-5)
    assert (surface[on][:, 3] > 0.5).all() and (surface[~on][:, :3] == 0).all()
    assert (normal[on][:, 0] > 0.4).all()  # bent (towards the view where the reflection needs it)
    np.testing.assert_array_equal(gbuffer.read("material")[..., 0][on], 1.0)  # the index stays in r
    gbuffer.upload(make_snapshot(geo, [Material(name="plain")]))
    gbuffer.execute(view, perspective(30.0))
    normal = gbuffer.read("normal")
    assert gbuffer.read_surface(normal) is normal


@pytest.mark.blender
def test_gbuffer_bump_follows_the_height_gradient(gbuffer):
    from tests.test_raster import interior, look_at, perspective, quad

    # A height ramp along u (bilinear: an exact gradient of `rise` per unit u), UVs kept off the
    # REPEAT wrap; left quad Strength 1, right quad Strength 0.5 and inverted.
    width, rise, distance = 16, 2.0, 0.3
    ramp = np.broadcast_to(((np.arange(width) + 0.5) / width * rise)[None, :], (4, width)).astype(np.float32)
    uv = [[0.1, 0.1], [0.9, 0.1], [0.9, 0.9], [0.1, 0.9]]
    left = quad((-2.0, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv, material=0)
    right = quad((0.1, -1.0, 0.0), (1.9, 0.0, 0.0), (0.0, 2.0, 0.0), uv=uv, material=1)
    materials = [Material(name="bump", normal_map=NormalMap(bump=BumpMap(ramp, 1.0, distance))),
                 Material(name="half", normal_map=NormalMap(bump=BumpMap(ramp, 0.5, -distance)))]
    snap = make_snapshot(concat_geometry([left, right]), materials)
    gbuffer.upload(snap)
    gbuffer.execute(look_at((0.0, 0.0, 5.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)), perspective(30.0))
    normal = gbuffer.read("normal")[..., :3]
    position = gbuffer.read("position")
    side = np.where(position[..., 3] > 0.5, (position[..., 0] > 0.0).astype(np.int32), -1)

    slope = distance * rise * 0.8 / 1.9  # distance x dh/dx in metres: u spans 0.8 over 1.9 m
    n = np.array([0.0, 0.0, 1.0])
    bent = _unit([-slope, 0.0, 1.0])
    half = _unit(0.5 * _unit([slope, 0.0, 1.0]) + 0.5 * n)
    inner = interior(side, margin=2)
    for label, want in ((0, bent), (1, half)):
        got = normal[inner & (side == label)]
        assert got.shape[0] > 20
        np.testing.assert_allclose(got, np.broadcast_to(want, got.shape), atol=3e-3)


# --- the read: sync gives the texture, its Strength, tangents; warns once for the rest -------


@pytest.fixture(scope="module")
def sync(bpy_module):
    from hybridgi_cli import dev_install

    return importlib.import_module(f"{dev_install.enable().__name__}.sync")


def _normal_mapped(bpy, name, image, strength=1.0, space="TANGENT"):
    from hybridgi_cli import blender_compat

    mat = blender_compat.new_material(bpy, name)
    tree = mat.node_tree
    bsdf = tree.nodes["Principled BSDF"]
    tex = tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    node = tree.nodes.new("ShaderNodeNormalMap")
    node.space = space
    node.inputs["Strength"].default_value = strength
    tree.links.new(tex.outputs["Color"], node.inputs["Color"])
    tree.links.new(node.outputs["Normal"], bsdf.inputs["Normal"])
    return mat


def _plane(bpy, scene, name, matrix, material):
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-1, -1, 0), (1, -1, 0), (1, 1, 0), (-1, 1, 0)], [], [(0, 1, 2, 3)])
    uv = mesh.uv_layers.new(name="UVMap")
    uv.uv.foreach_set("vector", [0, 0, 1, 0, 1, 1, 0, 1])
    mesh.materials.append(material)
    obj = bpy.data.objects.new(name, mesh)
    obj.matrix_world = matrix
    scene.collection.objects.link(obj)
    return obj


@pytest.mark.blender
def test_sync_reads_normal_map_tangents_and_warns_once_for_bump(bpy_module, empty_scene, sync, caplog):
    from mathutils import Matrix

    bpy = bpy_module
    image = bpy.data.images.new("ridges", 4, 2)
    image.colorspace_settings.name = "Non-Color"
    pixels = np.ones((2, 4, 4), np.float32)
    pixels[..., :3] = (0.25, 0.5, 0.9)
    image.pixels.foreach_set(pixels.ravel())
    mapped = _normal_mapped(bpy, "mapped", image, strength=0.7)
    _plane(bpy, empty_scene, "turned", Matrix.Rotation(math.radians(90), 4, "Z"), mapped)
    _plane(bpy, empty_scene, "mirrored", Matrix.Diagonal((-2.0, 1.0, 1.0, 1.0)), mapped)
    # A procedural Bump height: Blender bakes it over the material's atlas, which its bump then
    # reads (`sync.height_bakes`).
    bumpy = _normal_mapped(bpy, "bumpy", image)
    tree = bumpy.node_tree
    bump = tree.nodes.new("ShaderNodeBump")
    tree.links.new(tree.nodes.new("ShaderNodeTexNoise").outputs["Fac"], bump.inputs["Height"])
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    _plane(bpy, empty_scene, "bumped", Matrix.Translation((0, 0, -2)), bumpy)
    # Unsupported normal inputs: a procedural Bump height over a normal map (the map keeps the
    # mesh's UVs: no bake), an object-space map. They keep the smooth normal, with one warning.
    over_map = _normal_mapped(bpy, "over_map", image)
    tree = over_map.node_tree
    bump = tree.nodes.new("ShaderNodeBump")
    tree.links.new(tree.nodes.new("ShaderNodeTexNoise").outputs["Fac"], bump.inputs["Height"])
    tree.links.new(tree.nodes["Normal Map"].outputs["Normal"], bump.inputs["Normal"])
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    _plane(bpy, empty_scene, "over_map", Matrix.Translation((0, 0, -8)), over_map)
    _plane(bpy, empty_scene, "object_space", Matrix.Translation((0, 0, -4)),
           _normal_mapped(bpy, "object_space", image, space="OBJECT"))
    # A Bump over the image's luminance, inverted, on top of the normal map (its Normal input).
    chained = _normal_mapped(bpy, "chained", image)
    tree = chained.node_tree
    bump = tree.nodes.new("ShaderNodeBump")
    bump.invert = True
    bump.inputs["Distance"].default_value = 0.2
    bump.inputs["Strength"].default_value = 0.6
    tree.links.new(tree.nodes["Image Texture"].outputs["Color"], bump.inputs["Height"])
    tree.links.new(tree.nodes["Normal Map"].outputs["Normal"], bump.inputs["Normal"])
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    _plane(bpy, empty_scene, "chained", Matrix.Translation((0, 0, -6)), chained)

    with caplog.at_level(logging.WARNING):
        snap = sync.snapshot_from_depsgraph(bpy.context.evaluated_depsgraph_get())
    names = [m.name for m in snap.materials]
    material = snap.materials[names.index("mapped")]
    assert material.normal_map is not None and material.normal_map.strength == pytest.approx(0.7)
    # Non-Color: the raw values, not linearized.
    np.testing.assert_allclose(material.normal_map.texture.reshape(-1, 3), [[0.25, 0.5, 0.9]] * 8, atol=3e-3)
    baked = snap.materials[names.index("bumpy")].normal_map
    assert baked is not None and baked.texture is None and baked.bump.on_atlas
    assert 0.2 < baked.bump.height.mean() < 0.8 and baked.bump.height.std() > 0.01  # the noise's values
    assert snap.materials[names.index("over_map")].normal_map is None
    both = snap.materials[names.index("chained")].normal_map
    assert both.texture is not None and both.bump is not None
    assert both.bump.distance == pytest.approx(-0.2) and both.bump.strength == pytest.approx(0.6)
    np.testing.assert_allclose(both.bump.height, 0.2126 * 0.25 + 0.7152 * 0.5 + 0.0722 * 0.9, atol=3e-3)
    assert snap.materials[names.index("object_space")].normal_map is None

    geo = snap.geometry
    assert geo.tangents is not None and geo.tangents.shape == (geo.positions.shape[0], 4)
    objects = [o.name for o in snap.objects]

    def tangents_of(name):
        verts = np.unique(geo.triangles[geo.object_index == objects.index(name)])
        return geo.tangents[verts]

    # MikkTSpace tangent of the plane is local +X (u grows along x); the object's rotation turns
    # it to +Y; a mirroring scale flips it and the bitangent sign.
    np.testing.assert_allclose(tangents_of("turned"), np.tile([0, 1, 0, 1], (4, 1)), atol=1e-5)
    np.testing.assert_allclose(tangents_of("mirrored"), np.tile([-1, 0, 0, -1], (4, 1)), atol=1e-5)
    np.testing.assert_allclose(tangents_of("bumped"), 0.0)  # no normal map: no tangents
    # The baked bump reads the atlas: its triangles' map UVs are their texture UVs.
    verts = np.unique(geo.triangles[geo.object_index == objects.index("bumped")])
    np.testing.assert_array_equal(geo.normal_uvs[verts], geo.uvs[verts])
    assert geo.uvs[verts].min() >= 0.0 and geo.uvs[verts].max() <= 1.0
    warned = [r.getMessage() for r in caplog.records if "Bump" in r.getMessage()]
    assert len(warned) == 1 and "over_map" in warned[0] and "object space" in warned[0], warned
    assert "bumpy" not in warned[0]


@pytest.mark.blender
def test_a_procedural_bump_on_a_mesh_too_fine_for_its_atlas_keeps_the_smooth_normal(bpy_module, empty_scene, sync,
                                                                                   caplog):
    """A Noise bump on a 180x180 grid (64,800 triangles): its atlas cells would be a few texels
    wide, and differences across them read the next triangles (the Stanford dragon came out 18%
    too dark), so the height is not baked for it: the smooth normal, noted
    (`sync.MIN_BUMP_CELL_TEXELS`); the same material on a plane is bumped."""
    from mathutils import Matrix

    from hybridgi_cli import blender_compat

    bpy = bpy_module
    mat = blender_compat.new_material(bpy, "noisy")
    tree = mat.node_tree
    bump = tree.nodes.new("ShaderNodeBump")
    tree.links.new(tree.nodes.new("ShaderNodeTexNoise").outputs["Fac"], bump.inputs["Height"])
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    bpy.ops.mesh.primitive_grid_add(x_subdivisions=181, y_subdivisions=181, size=2.0)
    grid = bpy.context.active_object
    grid.data.materials.append(mat)
    _plane(bpy, empty_scene, "plain", Matrix.Translation((0, 0, -3)), mat)
    with caplog.at_level(logging.WARNING):
        snap = sync.snapshot_from_depsgraph(bpy.context.evaluated_depsgraph_get())
    maps = [m.normal_map for m in snap.materials if m.name == "noisy"]
    assert sum(m is not None and m.bump is not None and m.bump.on_atlas for m in maps) == 1  # the plane's
    assert any(m is None for m in maps)  # the grid's
    notes = [r.getMessage() for r in caplog.records if "approximated" in r.getMessage()]
    assert any("'noisy'" in n and "Bump height from ShaderNodeTexNoise" in n for n in notes), notes


@pytest.mark.blender
def test_procedural_bumps_are_baked_within_the_syncs_budget(bpy_module, empty_scene, sync, caplog, monkeypatch):
    """Mask and height bakes are optional (the factor's own value, the smooth normal, without
    them): a sync queues at most OPTIONAL_BAKE_JOBS, so a scene of many meshes under a Noise bump
    does not spend minutes of its first render baking; the rest is noted as before. Here a budget
    of one: the first plane is bumped, the next two keep the smooth normal, and an instance of the
    first plane's mesh shares its bake without spending more."""
    from mathutils import Matrix

    from hybridgi_cli import blender_compat

    bpy = bpy_module
    monkeypatch.setattr(sync, "OPTIONAL_BAKE_JOBS", 1)
    mat = blender_compat.new_material(bpy, "noisy")
    tree = mat.node_tree
    bump = tree.nodes.new("ShaderNodeBump")
    tree.links.new(tree.nodes.new("ShaderNodeTexNoise").outputs["Fac"], bump.inputs["Height"])
    tree.links.new(bump.outputs["Normal"], tree.nodes["Principled BSDF"].inputs["Normal"])
    first = _plane(bpy, empty_scene, "p0", Matrix.Translation((0, 0, 0)), mat)
    for i in (1, 2):
        _plane(bpy, empty_scene, f"p{i}", Matrix.Translation((0, 0, -3.0 * i)), mat)
    twin = bpy.data.objects.new("twin", first.data)
    twin.matrix_world = Matrix.Translation((3, 0, 0))
    empty_scene.collection.objects.link(twin)
    with caplog.at_level(logging.WARNING):
        snap = sync.snapshot_from_depsgraph(bpy.context.evaluated_depsgraph_get())
    maps = [m.normal_map for m in snap.materials if m.name == "noisy"]
    assert sum(m is not None and m.bump is not None for m in maps) == 1  # p0 and its twin share it
    objects = [o.name for o in snap.objects]
    index = snap.geometry.material_index
    bumped = {i for i, m in enumerate(snap.materials) if m.name == "noisy" and m.normal_map is not None}
    for name, expected in (("p0", True), ("twin", True), ("p1", False), ("p2", False)):
        mats = set(index[snap.geometry.object_index == objects.index(name)].tolist())
        assert bool(mats & bumped) == expected, name
    notes = [r.getMessage() for r in caplog.records if "approximated" in r.getMessage()]
    assert any("Bump height from ShaderNodeTexNoise" in n for n in notes), notes


@pytest.mark.blender
def test_ngon_fallback_tangents_agree_with_mikktspace(bpy_module, empty_scene, sync):
    bpy = bpy_module
    bpy.ops.mesh.primitive_uv_sphere_add(segments=24, ring_count=12)
    mesh = bpy.context.object.data
    mikk = sync.mesh_tangents(mesh)
    corner_vert = np.empty(len(mesh.loops), np.int32)
    mesh.attributes[".corner_vert"].data.foreach_get("value", corner_vert)
    ours = sync._ngon_tangents(mesh, mesh.uv_layers.active)
    # Rows where both have a frame (the poles' degenerate UV triangles may differ).
    both = (np.abs(mikk[:, :3]).sum(axis=1) > 0) & (np.abs(ours[:, :3]).sum(axis=1) > 0)
    assert both.mean() > 0.9
    cos = np.einsum("ij,ij->i", mikk[both, :3], ours[both, :3])
    # Area- (here) against angle-weighted (MikkTSpace) sums: a few degrees apart.
    assert np.median(cos) > 0.99 and (np.sign(mikk[both, 3]) == np.sign(ours[both, 3])).mean() > 0.99


# --- the render against Cycles ----------------------------------------------------------------

RIDGES_SCENE = textwrap.dedent("""
    import math, sys
    import numpy as np
    import bpy
    from hybridgi_cli import blender_compat
    mode, out = sys.argv[-2:]
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    size = 128
    u = (np.arange(size) + 0.5) / size
    px = np.ones((size, size, 4), np.float32)
    if mode == "normal":
        slope = 1.2 * np.cos(2 * np.pi * 6 * u)  # six ridges across u, 50-degree flanks
        n = np.stack([-slope, np.zeros_like(slope), np.ones_like(slope)], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        px[..., :3] = (n * 0.5 + 0.5)[None, :, :]
        img = bpy.data.images.new("ridges", size, size, alpha=False)
        img.filepath_raw, img.file_format = out + "_ridges.png", "PNG"
    else:  # the same ridges as a height: Distance 0.25 over the 4 m plane gives 50-degree flanks
        px[..., :3] = (0.5 + 0.5 * np.sin(2 * np.pi * 6 * u))[None, :, None]
        img = bpy.data.images.new("height", size, size, alpha=False, float_buffer=True)
        img.filepath_raw, img.file_format = out + "_height.exr", "OPEN_EXR"
    img.colorspace_settings.name = "Non-Color"
    img.pixels.foreach_set(px.ravel())
    img.save()
    img.pack()

    def material(name, strength, distance=0.25, invert=False):
        m = blender_compat.new_material(bpy, name)
        nt = m.node_tree
        bsdf = nt.nodes["Principled BSDF"]
        bsdf.inputs["Specular IOR Level"].default_value = 0.0
        tex = nt.nodes.new("ShaderNodeTexImage")
        tex.image = img
        if mode == "normal":
            nm = nt.nodes.new("ShaderNodeNormalMap")
            nm.inputs["Strength"].default_value = strength
            nt.links.new(tex.outputs["Color"], nm.inputs["Color"])
        else:
            nm = nt.nodes.new("ShaderNodeBump")
            nm.inputs["Strength"].default_value = strength
            nm.inputs["Distance"].default_value = distance
            nm.invert = invert
            nt.links.new(tex.outputs["Color"], nm.inputs["Height"])
        nt.links.new(nm.outputs["Normal"], bsdf.inputs["Normal"])
        return m

    bpy.ops.mesh.primitive_plane_add(size=4)
    bpy.context.object.data.materials.append(material("ridges", 1.0))
    bpy.ops.mesh.primitive_plane_add(size=2, location=(1.2, 2.2, 0.01), rotation=(0, 0, math.radians(90)))
    bpy.context.object.data.materials.append(material("ridges_half", 0.5, invert=True))
    bpy.ops.mesh.primitive_uv_sphere_add(radius=0.7, location=(-0.6, 0.9, 0.7), segments=32, ring_count=16)
    bpy.ops.object.shade_smooth()
    bpy.context.object.data.materials.append(material("ridges_sphere", 1.0, distance=0.05))
    bpy.ops.object.light_add(type="SUN", rotation=(math.radians(70), 0, math.radians(35)))
    bpy.context.object.data.energy = 3.0
    bpy.context.object.data.angle = math.radians(1.0)
    bpy.ops.object.camera_add(location=(0, -5.5, 4.5), rotation=(math.radians(50), 0, 0))
    scene.camera = bpy.context.object
    scene.world = blender_compat.new_world(bpy, "sky")
    scene.world.node_tree.nodes["Background"].inputs["Color"].default_value = (0.05, 0.05, 0.05, 1.0)
    bpy.ops.wm.save_as_mainfile(filepath=out + ".blend")
""")

RES = "128x96"


def _pass_error(ours, cycles, name, geometry) -> tuple[float, float]:
    """(relative L1, |mean ratio - 1|) of pass `name` over the geometry pixels, against Cycles."""
    got, want = layer(ours, name)[geometry], layer(cycles, name)[geometry]
    return (float(np.abs(got - want).sum() / np.abs(want).sum()),
            abs(float(got.mean()) / float(want.mean()) - 1.0))


def _ridges_scene(tmp_path_factory, mode):
    out = tmp_path_factory.mktemp(mode) / "ridges"
    subprocess.run([sys.executable, "-c", RIDGES_SCENE, mode, str(out)], check=True, capture_output=True)
    return out.with_suffix(".blend")


@pytest.fixture(scope="module")
def ridges(tmp_path_factory):
    return _ridges_scene(tmp_path_factory, "normal")


@pytest.fixture(scope="module")
def bumps(tmp_path_factory):
    return _ridges_scene(tmp_path_factory, "bump")


# Measured at 128x96 against Cycles 64 spp, Diffuse Direct rel L1 (mean) and Diffuse Indirect rel
# L1 (mean): normal map 0.022 (+0.2%), 0.32 (+1.6%) (0.39 (+21%) before probe hits took the map's
# bend, `bump.map_bend_factor`); smooth normals (before) 0.61 (+22%), 0.76; the
# map without Cycles' bump shadowing term 0.11 (+10%); before the smooth surface normal in the
# G-buffer (32 subframes: the GI-edge test took differently bent neighbours for other surfaces;
# the cache read over the bent cosine lobe) 0.021, 0.46 (+28%). Bump 0.019 (+0.2%), 0.29 (+9%);
# smooth normals 0.55 (+17%), 0.55; before 0.018, 0.33 (+9%). The same scene with Strength 0:
# Diffuse Indirect 0.23 (Cycles' noise).
DI_BOUNDS = {"ridges": (0.36, 0.08), "bumps": (0.31, 0.12)}


#: Cycles 4.2 shades these normal maps otherwise than 4.5 and later (the ridges' Diffuse Direct 7.6%
#: rel L1 off 4.5's at the same mean; 4.5 and 5.0 identical). HybridGI follows 4.5+ (its 4.2 render
#: is within 0.0004 of its 5.0 one): the comparisons with Cycles run there.
CYCLES_NORMAL_MAPS = pytest.mark.skipif(blender_compat.blender_version() < (4, 5),
                                        reason="Cycles before 4.5 shades normal maps otherwise (7.6% rel L1)")


@pytest.mark.blender
@pytest.mark.slow
@CYCLES_NORMAL_MAPS
@pytest.mark.parametrize("scene", ["ridges", "bumps"])
def test_normal_mapped_planes_and_sphere_match_cycles(scene, request, tmp_path):
    blend = request.getfixturevalue(scene)
    run = run_render(blend, tmp_path / "hg", RES, *QUICK)
    assert run.returncode == 0, run.stderr[-3000:]
    line = json.loads(run.stdout.strip().splitlines()[-1])
    # Differently bent neighbours are one surface: the frame takes the base 8 subframes, not 32.
    assert line["subframes"] == 8 and line["extra_pixels"] == 0, line
    ours = exr.read_channels(line["exr"])
    cycles = rendered(blend, tmp_path / "cy", RES, "--engine", "CYCLES", "--samples", "64")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    l1, mean_error = _pass_error(ours, cycles, "Diffuse Direct", geometry)
    assert l1 < 0.04 and mean_error < 0.02, (l1, mean_error)
    l1, mean_error = _pass_error(ours, cycles, "Diffuse Indirect", geometry)
    assert l1 < DI_BOUNDS[scene][0] and mean_error < DI_BOUNDS[scene][1], (l1, mean_error)
    if scene != "ridges":
        return
    # The cache path (Pixel Rays 0: the viewport's image before its pixel passes): the GPU gather
    # and SSAO read the light through the bent lobe over the smooth surface. Measured Diffuse
    # Indirect mean: the cosine of the bent normal +220%, the bent lobe in the gather +102%, SSAO
    # over the smooth surface +65%, probe hits with the map's bend +30% (the rest is the 12-cell
    # cache's).
    run = run_render(blend, tmp_path / "hg0", RES, *QUICK, "--set", "pixel_rays=0")
    assert run.returncode == 0, run.stderr[-3000:]
    cache_path = exr.read_channels(json.loads(run.stdout.strip().splitlines()[-1])["exr"])
    got, want = layer(cache_path, "Diffuse Indirect")[geometry], layer(cycles, "Diffuse Indirect")[geometry]
    mean_error = float(got.mean()) / float(want.mean()) - 1.0  # signed: too bright is the failure
    assert mean_error < 0.45, mean_error


BAKED_COLOUR = textwrap.dedent("""
    import sys
    import bpy
    src, out = sys.argv[-2:]
    bpy.ops.wm.open_mainfile(filepath=src)
    for m in bpy.data.materials:
        nt = m.node_tree
        bsdf = nt.nodes.get("Principled BSDF")
        if bsdf is None:
            continue
        noise = nt.nodes.new("ShaderNodeTexNoise")
        ramp = nt.nodes.new("ShaderNodeValToRGB")  # greys 0.6 .. 0.8: a colour the reader bakes
        ramp.color_ramp.elements[0].color = (0.6, 0.6, 0.6, 1.0)
        ramp.color_ramp.elements[1].color = (0.8, 0.8, 0.8, 1.0)
        nt.links.new(noise.outputs["Fac"], ramp.inputs["Fac"])
        nt.links.new(ramp.outputs["Color"], bsdf.inputs["Base Color"])
    bpy.ops.wm.save_as_mainfile(filepath=out)
""")


@pytest.mark.blender
@pytest.mark.slow
@CYCLES_NORMAL_MAPS
def test_normal_map_under_a_baked_colour_keeps_its_map(ridges, tmp_path):
    """A procedural Base Color is baked onto an atlas of the mesh's triangles; the normal map
    keeps reading the mesh's own UVs (`Geometry.normal_uvs`) with its tangents. It was dropped
    with a warning ("normal map on a baked colour"): Diffuse Direct rel L1 0.61, mean +22%."""
    blend = tmp_path / "baked_colour.blend"
    subprocess.run([sys.executable, "-c", BAKED_COLOUR, str(ridges), str(blend)], check=True, capture_output=True)
    run = run_render(blend, tmp_path / "hg", RES, *QUICK)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "normal map on a baked colour" not in run.stderr
    ours = exr.read_channels(json.loads(run.stdout.strip().splitlines()[-1])["exr"])
    cycles = rendered(blend, tmp_path / "cy", RES, "--engine", "CYCLES", "--samples", "64")
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    l1, mean_error = _pass_error(ours, cycles, "Diffuse Direct", geometry)
    assert l1 < 0.05 and mean_error < 0.02, (l1, mean_error)
    assert _pass_error(ours, cycles, "Diffuse Color", geometry)[0] < 0.05


@pytest.mark.blender
def test_viewport_draws_the_normal_map(bpy_module, gpu_context, ridges):
    """The viewport shares the G-buffer pass: its normals and its lamp light show the ridges."""
    from types import SimpleNamespace

    from hybridgi_cli import dev_install
    from tests.test_viewport import View

    bpy = bpy_module
    bpy.ops.wm.open_mainfile(filepath=str(ridges))
    package = dev_install.enable()
    scene = bpy.context.scene
    scene.render.engine = "HYBRIDGI"
    scene.hybridgi.resolution = 10
    scene.hybridgi.rays_per_cell = 16
    modules = SimpleNamespace(bpy=bpy, viewport=importlib.import_module(f"{package.__name__}.viewport"),
                              overlay=importlib.import_module(f"{package.__name__}.overlay"))
    view = View(modules)
    try:
        view.update()
        view.draw()
        view.converge()
        image = view.draw()
        gbuffer = view.session.gpu.pipeline.gbuffer
        normal = gbuffer.read("normal")
        floor = (gbuffer.read("position")[..., 2] < 0.005) & (normal[..., 3] > 0.5)
        # The ridges tilt the floor's normals +-50 degrees about y (the smooth normal is +z).
        assert floor.sum() > 500
        assert np.percentile(normal[floor][:, 0], 95) > 0.5 and np.percentile(normal[floor][:, 0], 5) < -0.5
        luma = image[..., :3] @ np.array([0.2126, 0.7152, 0.0722], np.float32)
        assert np.percentile(luma[floor], 90) > 3.0 * max(np.percentile(luma[floor], 10), 1e-3)
        # Turning the floor 90 degrees about z in the viewport turns its tangents with it.
        view.follow_edits()
        bpy.data.objects["Plane"].rotation_euler.z = math.radians(90)
        bpy.context.view_layer.update()
        view.draw()
        view.converge()
        view.draw()
        normal = gbuffer.read("normal")
        floor = (gbuffer.read("position")[..., 2] < 0.005) & (normal[..., 3] > 0.5)
        assert np.percentile(np.abs(normal[floor][:, 0]), 95) < 0.1
        assert np.percentile(normal[floor][:, 1], 95) > 0.5 and np.percentile(normal[floor][:, 1], 5) < -0.5
    finally:
        view.close()
        modules.overlay.close_all()
