"""addon/sync.py: depsgraph -> SceneSnapshot, on scenes built with bpy.data in each test."""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np
import pytest

from hybridgi_cli import blender_compat
from hybridgi_core.errors import EmptySceneError


@pytest.fixture
def scene(empty_scene):
    return empty_scene


def snapshot(sync, bpy, dynamic_names=frozenset()):
    return sync.snapshot_from_depsgraph(bpy.context.evaluated_depsgraph_get(), dynamic_names)


CUBE_VERTS = [(x, y, z) for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]
CUBE_FACES = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]


def add_mesh(bpy, scene, name, verts, faces, mesh=None, collection=None):
    if mesh is None:
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata(verts, [], faces)
        mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    (collection or scene.collection).objects.link(obj)
    return obj


def add_cube(bpy, scene, name="cube", **kwargs):
    return add_mesh(bpy, scene, name, CUBE_VERTS, CUBE_FACES, **kwargs)


def principled(bpy, name, color=(0.8, 0.8, 0.8)):
    mat = blender_compat.new_material(bpy, name)
    bsdf = mat.node_tree.nodes["Principled BSDF"]
    bsdf.inputs["Base Color"].default_value = (*color, 1.0)
    return mat, bsdf


def test_transformed_subdivided_cube(bpy_module, scene, sync):
    bpy = bpy_module
    cube = add_cube(bpy, scene)
    cube.location = (1.0, 2.0, 3.0)
    cube.rotation_euler = (0.0, 0.0, math.pi / 2)
    cube.scale = (2.0, 1.0, 0.5)
    cube.modifiers.new("subsurf", "SUBSURF").levels = 1

    snap = snapshot(sync, bpy)

    assert snap.geometry.triangle_count == 6 * 4 * 2  # 24 quads after one Catmull-Clark level
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = cube.evaluated_get(depsgraph)
    matrix = np.array(evaluated.matrix_world)
    local = np.array([v.co for v in evaluated.data.vertices])
    expected = local @ matrix[:3, :3].T + matrix[:3, 3]
    got = snap.geometry.positions[np.unique(snap.geometry.triangles)]
    # Every snapshot vertex is a transformed evaluated vertex, and every one is used.
    dist = np.linalg.norm(got[:, None, :] - expected[None, :, :], axis=2)
    assert dist.min(axis=1).max() < 1e-5 and dist.min(axis=0).max() < 1e-5
    # Outward shading normals survive the non-uniform scale and rotation.
    centroid = snap.geometry.positions[snap.geometry.triangles].mean(axis=1)
    tri_normal = snap.geometry.normals[snap.geometry.triangles].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", tri_normal, centroid - matrix[:3, 3]) > 0)
    assert np.allclose(np.linalg.norm(snap.geometry.normals, axis=1), 1.0, atol=1e-5)
    assert snap.objects[0].name == "cube" and snap.objects[0].dynamic is False


def test_mirrored_object_keeps_outward_winding(bpy_module, scene, sync):
    bpy = bpy_module
    add_cube(bpy, scene).scale = (-1.0, 1.0, 1.0)
    geo = snapshot(sync, bpy).geometry
    centroid = geo.positions[geo.triangles].mean(axis=1)
    # Geometric normals from the winding agree with the outward shading normals.
    assert np.all(np.einsum("ij,ij->i", geo.face_normals(), centroid) > 0)
    assert np.all(np.einsum("ij,ij->i", geo.normals[geo.triangles[:, 0]], centroid) > 0)


def test_material_slots_map_to_deduplicated_materials(bpy_module, scene, sync):
    bpy = bpy_module
    red, _ = principled(bpy, "red", (1.0, 0.0, 0.0))
    green, _ = principled(bpy, "green", (0.0, 1.0, 0.0))
    verts = [(x, y, z) for z in (0, 1) for (x, y) in ((0, 0), (1, 0), (1, 1), (0, 1))]
    two = add_mesh(bpy, scene, "two", verts, [(0, 1, 2, 3), (4, 5, 6, 7)])  # quads at z = 0 and z = 1
    two.data.materials.append(red)
    two.data.materials.append(green)
    two.data.polygons[1].material_index = 1
    other = add_mesh(bpy, scene, "other", [(3, 0, 0), (4, 0, 0), (4, 1, 0)], [(0, 1, 2)])
    other.data.materials.append(green)

    snap = snapshot(sync, bpy)

    names = [m.name for m in snap.materials]
    assert sorted(names) == ["green", "red"]
    geo = snap.geometry
    tri_z = geo.positions[geo.triangles][:, :, 2].mean(axis=1)
    tri_x = geo.positions[geo.triangles][:, :, 0].mean(axis=1)
    tri_mat = np.array(names)[geo.material_index]
    assert set(tri_mat[(tri_z < 0.5) & (tri_x < 2)]) == {"red"}
    assert set(tri_mat[tri_z > 0.5]) == {"green"}
    assert set(tri_mat[tri_x > 2]) == {"green"}
    red_mat = snap.materials[names.index("red")]
    np.testing.assert_allclose(red_mat.base_color, [1.0, 0.0, 0.0])


def test_image_texture_is_linearized_rgb_with_row0_at_v0(bpy_module, scene, sync):
    bpy = bpy_module
    image = bpy.data.images.new("tex", 4, 2)
    assert image.colorspace_settings.name == "sRGB" and not image.is_float
    pixels = np.full((2, 4, 4), 0.5, np.float32)
    pixels[0, :, :3] = 1.0  # bottom row (v = 0) white
    image.pixels.foreach_set(pixels.ravel())
    mat, bsdf = principled(bpy, "textured")
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    add_cube(bpy, scene).data.materials.append(mat)

    material = snapshot(sync, bpy).materials[0]

    assert material.texture.shape == (2, 4, 3) and material.texture.dtype == np.float32
    np.testing.assert_allclose(material.texture[0], 1.0, atol=1e-3)
    np.testing.assert_allclose(material.texture[1], 0.214, atol=2e-3)  # sRGB 0.5 -> linear
    np.testing.assert_allclose(material.base_color, 1.0)


def test_missing_image_is_cycles_missing_texture_magenta(bpy_module, scene, sync, caplog, tmp_path):
    """Cycles reads an image whose file is gone as opaque magenta (TEX_IMAGE_MISSING): the artist
    sees it, and so do the passes; the base colour was used before (a monkey: Combined 0.100
    against Cycles 64 spp, now 0.015)."""
    bpy = bpy_module
    image = bpy.data.images.new("gone", 2, 2)
    image.source = "FILE"
    image.filepath = str(tmp_path / "missing.png")
    mat, bsdf = principled(bpy, "broken", (0.1, 0.2, 0.3))
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image = image
    mat.node_tree.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    add_cube(bpy, scene).data.materials.append(mat)

    with caplog.at_level(logging.WARNING):
        material = snapshot(sync, bpy).materials[0]

    colour = material.base_color * material.texture.reshape(-1, 3).mean(axis=0)
    np.testing.assert_allclose(colour, [1.0, 0.0, 1.0], atol=1e-6)
    assert material.alpha is None
    assert any("could not be read" in r.getMessage() and "missing.png" in r.getMessage() for r in caplog.records)


def test_a_non_finite_roughness_or_ior_is_named_and_replaced(bpy_module, scene, sync, caplog):
    """A NaN typed into a Principled BSDF's Roughness made its base colour NaN, and the log named
    the colour ("base colour [nan, ...] is not finite"); an inf IOR its Fresnel. The input itself
    is named and takes Blender's default, and the colour stays the artist's."""
    bpy = bpy_module
    mat, bsdf = principled(bpy, "odd", (0.2, 0.4, 0.6))
    bsdf.inputs["Roughness"].default_value = float("nan")
    bsdf.inputs["IOR"].default_value = float("inf")
    add_cube(bpy, scene).data.materials.append(mat)

    with caplog.at_level(logging.WARNING):
        material = snapshot(sync, bpy).materials[0]

    messages = [r.getMessage() for r in caplog.records]
    assert any("'odd'" in m and "Roughness" in m and "not finite" in m for m in messages), messages
    assert any("'odd'" in m and "IOR" in m and "not finite" in m for m in messages), messages
    assert not any("base colour" in m for m in messages), messages
    assert np.isfinite(material.base_color).all() and material.base_color[2] > material.base_color[0] > 0
    assert material.specular is None or np.isfinite(material.specular.roughness)


def test_shader_kinds(bpy_module, scene, sync, caplog):
    bpy = bpy_module
    glowing, bsdf = principled(bpy, "glowing", (0.5, 0.5, 0.5))
    bsdf.inputs["Emission Color"].default_value = (1.0, 0.5, 0.25, 1.0)
    bsdf.inputs["Emission Strength"].default_value = 4.0

    def replaced(name, node_type):
        mat = blender_compat.new_material(bpy, name)
        tree = mat.node_tree
        tree.nodes.remove(tree.nodes["Principled BSDF"])
        node = tree.nodes.new(node_type)
        tree.links.new(node.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
        return mat, node

    lamp, emission = replaced("lamp", "ShaderNodeEmission")
    emission.inputs["Color"].default_value = (1.0, 1.0, 0.5, 1.0)
    emission.inputs["Strength"].default_value = 10.0
    matte, diffuse = replaced("matte", "ShaderNodeBsdfDiffuse")
    diffuse.inputs["Color"].default_value = (0.2, 0.3, 0.4, 1.0)
    shiny, _ = replaced("shiny", "ShaderNodeBsdfGlossy")
    cube = add_cube(bpy, scene)
    for mat in (glowing, lamp, matte, shiny):
        cube.data.materials.append(mat)
    for i, poly in enumerate(cube.data.polygons):
        poly.material_index = min(i, 3)

    with caplog.at_level(logging.WARNING):
        by_name = {m.name: m for m in snapshot(sync, bpy).materials}

    np.testing.assert_allclose(by_name["glowing"].emission, [4.0, 2.0, 1.0])
    np.testing.assert_allclose(by_name["glowing"].base_color, [0.5, 0.5, 0.5])
    np.testing.assert_allclose(by_name["lamp"].emission, [10.0, 10.0, 5.0])
    np.testing.assert_allclose(by_name["lamp"].base_color, 0.0)
    np.testing.assert_allclose(by_name["matte"].base_color, [0.2, 0.3, 0.4], atol=1e-6)
    np.testing.assert_allclose(by_name["matte"].emission, 0.0)
    # A Glossy BSDF reflects no diffuse light (Cycles' Diffuse Color pass is black there): its
    # light is one glossy lobe of its colour, rendered (no warning that it is missing).
    np.testing.assert_allclose(by_name["shiny"].base_color, 0.0)
    (lobe,) = by_name["shiny"].specular.lobes
    assert lobe.fresnel == "none" and lobe.distribution == "MULTI_GGX"
    np.testing.assert_allclose(lobe.weight, [0.8, 0.8, 0.8], atol=1e-6)
    assert not any("'shiny'" in r.getMessage() for r in caplog.records)


def test_negative_emission_emits_nothing_as_in_cycles(bpy_module, scene, sync, caplog):
    """A negative Strength (or colour) is not subtracted light: Cycles renders such a surface as
    not emitting (a cube at -5 read the image's Combined mean -1.33 against Cycles' 0.55)."""
    bpy = bpy_module
    dark, bsdf = principled(bpy, "dark", (0.5, 0.5, 0.5))
    bsdf.inputs["Emission Color"].default_value = (1.0, 0.5, 0.25, 1.0)
    bsdf.inputs["Emission Strength"].default_value = -5.0
    add_cube(bpy, scene).data.materials.append(dark)
    with caplog.at_level(logging.WARNING):
        material = snapshot(sync, bpy).materials[0]
    np.testing.assert_array_equal(material.emission, 0.0)
    assert any("'dark'" in r.getMessage() and "negative emission" in r.getMessage() for r in caplog.records)


def test_principled_weights_mixes_and_constant_nodes(bpy_module, scene, sync, caplog):
    """What Cycles' Diffuse Color pass shows: base colour x (1 - metallic) x (1 - transmission),
    tinted by the coat; Mix Shader by its factor; Emission Color from an RGB or Mix node."""
    bpy = bpy_module
    metal, m_bsdf = principled(bpy, "half_metal", (0.8, 0.4, 0.2))
    m_bsdf.inputs["Metallic"].default_value = 0.75
    glass, g_bsdf = principled(bpy, "glassy", (0.5, 0.5, 0.5))
    g_bsdf.inputs["Transmission Weight"].default_value = 1.0
    coated, c_bsdf = principled(bpy, "coated", (0.5, 0.5, 0.5))
    c_bsdf.inputs["Coat Weight"].default_value = 1.0
    c_bsdf.inputs["Coat Tint"].default_value = (1.0, 0.5, 0.5, 1.0)
    panel, p_bsdf = principled(bpy, "panel", (0.1, 0.1, 0.1))
    rgb = panel.node_tree.nodes.new("ShaderNodeRGB")
    rgb.outputs[0].default_value = (1.0, 0.2, 0.1, 1.0)
    mix = panel.node_tree.nodes.new("ShaderNodeMix")
    mix.data_type = "RGBA"
    mix.inputs["Factor"].default_value = 0.5
    mix.inputs["B"].default_value = (0.0, 0.0, 1.0, 1.0)
    panel.node_tree.links.new(rgb.outputs[0], mix.inputs["A"])
    panel.node_tree.links.new(mix.outputs["Result"], p_bsdf.inputs["Emission Color"])
    p_bsdf.inputs["Emission Strength"].default_value = 2.0
    mixed = blender_compat.new_material(bpy, "mixed")
    tree = mixed.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    shader_mix = tree.nodes.new("ShaderNodeMixShader")
    shader_mix.inputs["Fac"].default_value = 0.25
    red, white = tree.nodes.new("ShaderNodeBsdfDiffuse"), tree.nodes.new("ShaderNodeBsdfDiffuse")
    red.inputs["Color"].default_value = (1.0, 0.0, 0.0, 1.0)
    white.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    tree.links.new(red.outputs[0], shader_mix.inputs[1])
    tree.links.new(white.outputs[0], shader_mix.inputs[2])
    tree.links.new(shader_mix.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    cube = add_cube(bpy, scene)
    for mat in (metal, glass, coated, panel, mixed):
        cube.data.materials.append(mat)
    for i, poly in enumerate(cube.data.polygons):
        poly.material_index = min(i, 4)
    by_name = {m.name: m for m in snapshot(sync, bpy).materials}
    np.testing.assert_allclose(by_name["half_metal"].base_color, [0.2, 0.1, 0.05], rtol=1e-5)
    np.testing.assert_allclose(by_name["glassy"].base_color, 0.0, atol=1e-7)
    assert by_name["glassy"].clear and not by_name["half_metal"].clear
    np.testing.assert_allclose(by_name["coated"].base_color, [0.5, 0.25, 0.25], rtol=1e-5)
    np.testing.assert_allclose(by_name["panel"].emission, [1.0, 0.2, 1.1], rtol=1e-5)
    np.testing.assert_allclose(by_name["mixed"].base_color, [1.0, 0.25, 0.25], rtol=1e-5)


def test_what_lets_most_light_through_is_clear_glass(bpy_module, scene, sync, caplog):
    """A surface most of whose light passes (Glass, Transparent and Refraction BSDFs, a Principled
    BSDF's transmission) is clear (`Material.clear`). A constant alpha, or a white Transparent
    BSDF mixed in by a constant factor, is the share of the light the surface stops: the surface
    is seen with that chance (`Material.coverage`), its own colour unmixed."""
    bpy = bpy_module

    def lone(name, kind):
        mat = blender_compat.new_material(bpy, name)
        tree = mat.node_tree
        tree.nodes.remove(tree.nodes["Principled BSDF"])
        tree.links.new(tree.nodes.new(kind).outputs[0], tree.nodes["Material Output"].inputs["Surface"])
        return mat

    def mixed(name, fac):
        mat = blender_compat.new_material(bpy, name)
        tree = mat.node_tree
        mix = tree.nodes.new("ShaderNodeMixShader")
        mix.inputs["Fac"].default_value = fac
        tree.links.new(tree.nodes["Principled BSDF"].outputs[0], mix.inputs[1])
        tree.links.new(tree.nodes.new("ShaderNodeBsdfTransparent").outputs[0], mix.inputs[2])
        tree.links.new(mix.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
        return mat

    see_through, half_seen = principled(bpy, "alpha 0.2"), principled(bpy, "alpha 0.7")
    see_through[1].inputs["Alpha"].default_value = 0.2
    half_seen[1].inputs["Alpha"].default_value = 0.7
    mats = [lone("glass", "ShaderNodeBsdfGlass"), lone("transparent", "ShaderNodeBsdfTransparent"),
            lone("refraction", "ShaderNodeBsdfRefraction"), see_through[0], half_seen[0],
            mixed("mostly clear", 0.8), mixed("mostly solid", 0.3)]
    cube = add_cube(bpy, scene)
    for mat in mats:
        cube.data.materials.append(mat)
    for i, poly in enumerate(cube.data.polygons):
        poly.material_index = i
    with caplog.at_level(logging.WARNING):
        by_name = {m.name: m for m in snapshot(sync, bpy).materials}
    bpy.data.objects.remove(cube)
    for mat in mats:  # material names are global: later tests make their own "glass"
        bpy.data.materials.remove(mat)
    clear = {name for name, m in by_name.items() if m.clear}
    assert clear == {"glass", "transparent", "refraction"}
    coverage = {name: m.coverage for name, m in by_name.items() if m.coverage < 1.0}
    assert coverage == pytest.approx({"alpha 0.2": 0.2, "alpha 0.7": 0.7, "mostly clear": 0.2, "mostly solid": 0.7})
    # The camera's refraction paths (`refraction.py`): a Glass BSDF's Color tints its reflection
    # too, a Refraction BSDF's only what it refracts; both at their default index.
    glass, refraction = by_name["glass"], by_name["refraction"]
    assert glass.refractive and refraction.refractive and not by_name["transparent"].refractive
    assert glass.tint_reflection and not refraction.tint_reflection
    assert glass.ior == pytest.approx(1.5, abs=0.06) and refraction.ior == pytest.approx(1.5, abs=0.06)
    # Where it is seen, the surface is the Principled BSDF's own: its diffuse colour 0.8 under its
    # specular layer's view-dependent weight, not dimmed by the mix.
    for name in ("mostly solid", "mostly clear", "alpha 0.7"):
        assert np.all((by_name[name].base_color > 0.6) & (by_name[name].base_color <= 0.8)), name
    notes = " ".join(r.getMessage() for r in caplog.records if "approximated" in r.getMessage())
    assert "'glass'" in notes and "clear thin glass" in notes
    assert "'mostly solid'" not in notes


def test_shaders_inside_node_groups_are_read_as_cycles_flattens_them(bpy_module, scene, sync, caplog):
    """A material whose surface comes out of a node group (as asset libraries ship them), nested
    groups, and group inputs that are constants, linked outside (an image) or left at the group's
    own value: read as the flattened tree Cycles compiles (they were grey 0.8, "not supported")."""
    bpy = bpy_module
    wrap = bpy.data.node_groups.new("Wrap", "ShaderNodeTree")
    wrap.interface.new_socket("Tint", in_out="INPUT", socket_type="NodeSocketColor")
    wrap.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    gin, gout = wrap.nodes.new("NodeGroupInput"), wrap.nodes.new("NodeGroupOutput")
    bsdf = wrap.nodes.new("ShaderNodeBsdfPrincipled")
    bsdf.inputs["Roughness"].default_value = 0.25
    wrap.links.new(gin.outputs["Tint"], bsdf.inputs["Base Color"])
    wrap.links.new(bsdf.outputs[0], gout.inputs["Shader"])
    outer = bpy.data.node_groups.new("Outer", "ShaderNodeTree")
    outer.interface.new_socket("Colour", in_out="INPUT", socket_type="NodeSocketColor")
    outer.interface.new_socket("Shader", in_out="OUTPUT", socket_type="NodeSocketShader")
    oin, oout = outer.nodes.new("NodeGroupInput"), outer.nodes.new("NodeGroupOutput")
    inner = outer.nodes.new("ShaderNodeGroup")
    inner.node_tree = wrap
    outer.links.new(oin.outputs["Colour"], inner.inputs["Tint"])
    outer.links.new(inner.outputs["Shader"], oout.inputs["Shader"])

    def grouped(name, group, socket, colour=None):
        mat = blender_compat.new_material(bpy, name)
        tree = mat.node_tree
        tree.nodes.remove(tree.nodes["Principled BSDF"])
        node = tree.nodes.new("ShaderNodeGroup")
        node.node_tree = group
        if colour is not None:
            node.inputs[socket].default_value = (*colour, 1.0)
        tree.links.new(node.outputs["Shader"], tree.nodes["Material Output"].inputs["Surface"])
        return mat, node

    plain, _ = grouped("grouped", wrap, "Tint", (0.1, 0.6, 0.9))
    nested, _ = grouped("nested", outer, "Colour", (0.7, 0.2, 0.1))
    imaged, node = grouped("imaged", wrap, "Tint")
    image = bpy.data.images.new("tint image", 2, 2)
    image.pixels.foreach_set(np.tile(np.array([0.5, 0.25, 1.0, 1.0], np.float32), 4))
    texture = imaged.node_tree.nodes.new("ShaderNodeTexImage")
    texture.image = image
    imaged.node_tree.links.new(texture.outputs["Color"], node.inputs["Tint"])
    cube = add_cube(bpy, scene)
    for mat in (plain, nested, imaged):
        cube.data.materials.append(mat)
    for i, poly in enumerate(cube.data.polygons):
        poly.material_index = min(i, 2)
    with caplog.at_level(logging.WARNING):
        by_name = {m.name: m for m in snapshot(sync, bpy).materials}
    bpy.data.objects.remove(cube)
    for mat in (plain, nested, imaged):
        bpy.data.materials.remove(mat)
    assert not any("not supported" in r.getMessage() for r in caplog.records)
    np.testing.assert_allclose(by_name["grouped"].base_color, [0.1, 0.6, 0.9], rtol=1e-5)
    np.testing.assert_allclose(by_name["nested"].base_color, [0.7, 0.2, 0.1], rtol=1e-5)
    for name in ("grouped", "nested", "imaged"):
        assert by_name[name].specular.roughness == pytest.approx(0.25)
    tex = by_name["imaged"].texture
    assert tex is not None and tex.shape[:2] == (2, 2)
    srgb = np.array([0.5, 0.25, 1.0])  # the image's sRGB values, read as scene-linear colour
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(tex.reshape(-1, 3).mean(axis=0), linear, atol=0.01)


def add_light(bpy, scene, kind, **settings):
    data = bpy.data.lights.new(kind.lower(), kind)
    for key, value in settings.items():
        setattr(data, key, value)
    obj = bpy.data.objects.new(kind.lower(), data)
    scene.collection.objects.link(obj)
    return obj


def test_every_light_type(bpy_module, scene, sync):
    bpy = bpy_module
    point = add_light(bpy, scene, "POINT", energy=100.0, shadow_soft_size=0.2, color=(1.0, 0.5, 0.25))
    point.location = (1.0, 2.0, 3.0)
    exposure = blender_compat.lights_have_exposure(bpy)  # Blender 4.2: no exposure, no normalize
    spot = {"energy": 50.0, "exposure": 1.0} if exposure else {"energy": 100.0}
    add_light(bpy, scene, "SPOT", spot_size=math.radians(45), spot_blend=0.3, use_soft_falloff=False, **spot)
    sun = add_light(bpy, scene, "SUN", energy=3.0, angle=math.radians(10))
    sun.rotation_euler = (0.5, 0.0, 0.0)
    rect = add_light(bpy, scene, "AREA", energy=200.0, shape="RECTANGLE", size=2.0, size_y=1.0)
    rect.scale = (2.0, 3.0, 1.0)
    square = add_light(bpy, scene, "AREA", energy=10.0, shape="SQUARE", size=1.0)
    square.scale = (1.0, 2.0, 1.0)
    square.name = "stretched"
    if exposure:
        unnormalized = add_light(bpy, scene, "AREA", energy=1.0, shape="DISK", size=2.0, normalize=False)
        unnormalized.name = "unnormalized"

    snap = snapshot(sync, bpy)
    lights = {light.name: light for light in snap.lights}
    assert len(lights) == (6 if exposure else 5)

    p = lights["point"]
    assert (p.kind, p.power, p.radius) == ("POINT", pytest.approx(100.0), pytest.approx(0.2))
    np.testing.assert_allclose(p.color, [1.0, 0.5, 0.25])
    np.testing.assert_allclose(p.position, [1.0, 2.0, 3.0])
    s = lights["spot"]
    assert s.power == pytest.approx(100.0)  # exposure 1 doubles the power
    assert s.spot_size == pytest.approx(math.radians(45)) and s.spot_blend == pytest.approx(0.3)
    # Soft Falloff (Blender's default): a facing disc; off: Cycles' sphere light.
    assert p.soft_falloff and not s.soft_falloff
    sun_light = lights["sun"]
    assert sun_light.power == pytest.approx(3.0) and sun_light.angle == pytest.approx(math.radians(10))
    np.testing.assert_allclose(sun_light.matrix, np.array(sun.matrix_world), atol=1e-6)
    np.testing.assert_allclose(sun_light.direction, -np.array(sun.matrix_world)[:3, 2], atol=1e-6)
    # Area extents as placed: Blender's size times the matrix's X/Y scale (the core's reading).
    a = lights["area"]
    assert (a.shape, a.size, a.size_y) == ("RECTANGLE", pytest.approx(2.0), pytest.approx(1.0))
    assert a.power == pytest.approx(200.0)
    np.testing.assert_allclose(np.linalg.norm(a.matrix[:3, :2], axis=0) * [a.size, a.size_y], [4.0, 3.0], rtol=1e-6)
    stretched = lights["stretched"]
    assert (stretched.shape, stretched.size, stretched.size_y) == ("SQUARE", pytest.approx(1.0), pytest.approx(1.0))
    np.testing.assert_allclose(np.linalg.norm(stretched.matrix[:3, :2], axis=0), [1.0, 2.0], rtol=1e-6)
    # Without normalization Cycles' radiance is strength / pi: power x area in the normalized formula.
    if exposure:
        disk = lights["unnormalized"]
        assert disk.shape == "DISK" and disk.power == pytest.approx(math.pi)


def test_world_radiance_and_ao_distance(bpy_module, scene, sync):
    bpy = bpy_module
    bare = snapshot(sync, bpy).world
    assert bare.color.tolist() == [0.0, 0.0, 0.0]  # no World: black
    # ... and AO reaches 10 m, as in Cycles (a World's own setting defaults to 1 m)
    assert bare.ao_distance == pytest.approx(10.0)
    assert scene.hybridgi.cache_settings(scene).ao_distance == pytest.approx(10.0)
    world = blender_compat.new_world(bpy, "sky")
    background = world.node_tree.nodes["Background"]
    background.inputs["Color"].default_value = (0.2, 0.4, 0.6, 1.0)
    background.inputs["Strength"].default_value = 2.0
    world.light_settings.distance = 3.5
    scene.world = world

    snap = snapshot(sync, bpy)

    np.testing.assert_allclose(snap.world.color, [0.4, 0.8, 1.2], rtol=1e-6)
    assert snap.world.ao_distance == pytest.approx(3.5)


def test_cache_settings_from_properties(bpy_module, scene, addon):
    scene.world = bpy_module.data.worlds.new("w")
    scene.world.light_settings.distance = 2.5
    props = scene.hybridgi
    props.sh_order = "L1"
    props.indirect_quality = "ONE_BOUNCE"
    props.hysteresis = 0.95
    settings = props.cache_settings(scene)
    assert (settings.sh_order, settings.indirect_quality) == (1, 1)
    assert settings.hysteresis == 0.95 and settings.ao_distance == 2.5
    props.blend_mode = "MIN"
    props.ssao_radius = 0.25
    raster = props.raster_settings()
    assert (raster.ao_blend, raster.ssao_radius, raster.downsample) == ("MIN", 0.25, props.downsample)


def test_instances_and_linked_duplicates(bpy_module, scene, sync):
    bpy = bpy_module
    collection = bpy.data.collections.new("props")  # not linked to the scene: only instanced
    add_mesh(bpy, scene, "plane", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [(0, 1, 2, 3)], collection=collection)
    for i in range(2):
        empty = bpy.data.objects.new(f"inst{i}", None)
        empty.instance_type = "COLLECTION"
        empty.instance_collection = collection
        empty.location = (10.0 * i, 0.0, 0.0)
        scene.collection.objects.link(empty)
    cube = add_cube(bpy, scene)
    twin = add_cube(bpy, scene, "twin", mesh=cube.data)
    twin.location = (0.0, 5.0, 0.0)

    snap = snapshot(sync, bpy, dynamic_names={"inst1"})

    assert snap.geometry.triangle_count == 2 * 2 + 2 * 12
    by_name = {o.name: o for o in snap.objects}
    assert set(by_name) == {"inst0/plane", "inst1/plane", "cube", "twin"}
    assert by_name["inst1/plane"].dynamic and not by_name["inst0/plane"].dynamic
    x = snap.geometry.positions[:, 0]
    assert x.max() == pytest.approx(11.0)  # the second instance is moved by its instancer


def test_scattered_instances_are_placed_one_by_one(bpy_module, scene, sync):
    """Consecutive instances of one mesh are transformed together (`sync.transformed`): each keeps
    its own matrix (rotation, non-uniform and mirroring scale), winding, normals and object."""
    bpy = bpy_module
    collection = bpy.data.collections.new("rocks")
    add_cube(bpy, scene, "rock", collection=collection)
    placements = [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
                  ((4.0, 0.0, 1.0), (0.3, 0.0, 1.2), (2.0, 1.0, 0.5)),
                  ((0.0, 6.0, 0.0), (0.0, 0.0, 0.0), (-1.0, 1.0, 1.0)),
                  ((-5.0, 2.0, 3.0), (1.0, 0.5, 0.2), (0.5, -2.0, 1.5))]
    for i, (loc, rot, scale) in enumerate(placements):
        empty = bpy.data.objects.new(f"scatter{i}", None)
        empty.instance_type = "COLLECTION"
        empty.instance_collection = collection
        empty.location, empty.rotation_euler, empty.scale = loc, rot, scale
        scene.collection.objects.link(empty)

    geo = snapshot(sync, bpy).geometry

    assert geo.triangle_count == 4 * 12
    for i in range(len(placements)):
        empty = bpy.data.objects[f"scatter{i}"]
        matrix = np.array(empty.matrix_world)
        tris = geo.triangles[geo.object_index == i]
        assert tris.shape[0] == 12
        corners = geo.positions[tris]
        local = (corners - matrix[:3, 3]) @ np.linalg.inv(matrix[:3, :3]).T
        np.testing.assert_allclose(np.abs(local), 1.0, atol=1e-4)  # the unit cube's corners
        centroid = corners.mean(axis=1)
        outward = centroid - corners.mean(axis=(0, 1))
        face = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        assert np.all(np.einsum("ij,ij->i", face, outward) > 0), f"instance {i}: winding"
        assert np.all(np.einsum("ij,ij->i", geo.normals[tris[:, 0]], outward) > 0), f"instance {i}: normals"


def test_alternating_instances_are_transformed_by_mesh_and_kept_in_order(bpy_module, scene, sync):
    """A collection of two objects instanced several times alternates between their meshes; every
    instance of one mesh is transformed in one batch (`sync._SnapshotBuilder._add_placed`), and the
    snapshot keeps the order they came in: object i's triangles are the i-th instance's mesh
    under its own matrix, its triangles numbered within the joined geometry."""
    bpy = bpy_module
    collection = bpy.data.collections.new("tree")
    add_cube(bpy, scene, "trunk", collection=collection)
    leaves = add_mesh(bpy, scene, "leaves", [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0)], [(0, 1, 2, 3)],
                      collection=collection)
    leaves.location = (0.0, 0.0, 2.0)
    for i in range(4):
        empty = bpy.data.objects.new(f"tree{i}", None)
        empty.instance_type = "COLLECTION"
        empty.instance_collection = collection
        empty.location, empty.rotation_euler = (3.0 * i, 0.0, 0.0), (0.0, 0.0, 0.4 * i)
        scene.collection.objects.link(empty)

    snap = snapshot(sync, bpy)
    geo = snap.geometry
    names = [o.name for o in snap.objects]
    assert sorted(names) == sorted(f"tree{i}/{part}" for i in range(4) for part in ("trunk", "leaves"))
    # Each object's triangles are contiguous and in the objects' order.
    assert np.all(np.diff(geo.object_index) >= 0)
    assert np.array_equal(np.unique(geo.object_index), np.arange(len(names)))
    for index, name in enumerate(names):
        tree, part = name.split("/")
        matrix = np.array(bpy.data.objects[tree].matrix_world) @ np.array(bpy.data.objects[part].matrix_world)
        tris = geo.triangles[geo.object_index == index]
        assert tris.shape[0] == (12 if part == "trunk" else 2)
        corners = geo.positions[tris].reshape(-1, 3)
        local = (corners - matrix[:3, 3]) @ np.linalg.inv(matrix[:3, :3]).T
        if part == "trunk":
            np.testing.assert_allclose(np.abs(local), 1.0, atol=1e-4)  # the unit cube's corners
        else:
            np.testing.assert_allclose(local[:, 2], 0.0, atol=1e-5)
            assert local[:, :2].min() > -1e-5 and local[:, :2].max() < 1.0 + 1e-5


def test_geometry_nodes_instances(bpy_module, scene, sync):
    bpy = bpy_module
    tree = bpy.data.node_groups.new("scatter", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    group_in = tree.nodes.new("NodeGroupInput")
    group_out = tree.nodes.new("NodeGroupOutput")
    cube = tree.nodes.new("GeometryNodeMeshCube")
    scatter = tree.nodes.new("GeometryNodeInstanceOnPoints")
    tree.links.new(group_in.outputs[0], scatter.inputs["Points"])
    tree.links.new(cube.outputs["Mesh"], scatter.inputs["Instance"])
    tree.links.new(scatter.outputs["Instances"], group_out.inputs[0])
    points = add_mesh(bpy, scene, "points", [(0, 0, 0), (5, 0, 0), (0, 5, 0)], [])
    points.modifiers.new("scatter", "NODES").node_group = tree

    snap = snapshot(sync, bpy)

    assert snap.geometry.triangle_count == 3 * 12
    assert len(snap.objects) == 3


def test_text_and_curves_are_counted_once(bpy_module, scene, sync):
    bpy = bpy_module
    text = bpy.data.objects.new("text", bpy.data.curves.new("text", "FONT"))
    scene.collection.objects.link(text)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = text.evaluated_get(depsgraph)
    expected = len(evaluated.to_mesh().loop_triangles)
    evaluated.to_mesh_clear()

    snap = snapshot(sync, bpy)

    assert expected > 0
    # Zero-area slivers of the glyph triangulation may be dropped, never duplicated.
    assert 0.9 * expected <= snap.geometry.triangle_count <= expected
    assert [o.name for o in snap.objects] == ["text"]


def _geometry_nodes(bpy, obj, *chain):
    """A Geometry Nodes modifier on `obj` whose tree runs its geometry through the nodes of
    `chain`, (node type, {input: value}) each, one after the other."""
    tree = bpy.data.node_groups.new("nodes", "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    out = tree.nodes.new("NodeGroupInput").outputs[0]
    for node_type, inputs in chain:
        node = tree.nodes.new(node_type)
        for name, value in inputs.items():
            node.inputs[name].default_value = value
        tree.links.new(out, node.inputs[0])
        out = node.outputs[0]
    tree.links.new(out, tree.nodes.new("NodeGroupOutput").inputs[0])
    obj.modifiers.new("nodes", "NODES").node_group = tree


def test_point_clouds_are_spheres_as_cycles_renders_them(bpy_module, scene, sync):
    # Mesh to Points gave a PointCloud instance that was dropped without a word (Cycles renders
    # each point as a sphere of its radius).
    bpy = bpy_module
    cube = add_cube(bpy, scene)
    mat, _bsdf = principled(bpy, "yellow", (0.9, 0.8, 0.1))
    _geometry_nodes(bpy, cube, ("GeometryNodeMeshToPoints", {"Radius": 0.25}),
                    ("GeometryNodeSetMaterial", {"Material": mat}))

    snap = snapshot(sync, bpy)

    assert snap.geometry.triangle_count == 8 * 80  # one 80-triangle icosphere per cube vertex
    assert [o.name for o in snap.objects] == ["cube"] and [m.name for m in snap.materials] == ["yellow"]
    distance = np.linalg.norm(snap.geometry.positions, axis=1)
    assert distance.min() > np.sqrt(3) - 0.26 and distance.max() < np.sqrt(3) + 0.26


def test_volume_objects_are_named_and_left_out(bpy_module, scene, sync, caplog):
    bpy = bpy_module
    add_cube(bpy, scene, "floor")
    fog = add_cube(bpy, scene, "fog")
    _geometry_nodes(bpy, fog, ("GeometryNodeMeshToVolume", {}))
    scene.collection.objects.link(bpy.data.objects.new("smoke", bpy.data.volumes.new("smoke")))

    with caplog.at_level(logging.WARNING):
        snap = snapshot(sync, bpy)

    assert [o.name for o in snap.objects] == ["floor"]
    warned = [r.getMessage() for r in caplog.records if "Volume objects" in r.getMessage()]
    assert len(warned) == 1 and "'fog'" in warned[0] and "'smoke'" in warned[0], caplog.text


def test_empty_scene_gives_empty_snapshot(bpy_module, scene, sync):
    snap = snapshot(sync, bpy_module)
    assert snap.geometry.triangle_count == 0 and snap.objects == []
    with pytest.raises(EmptySceneError):
        snap.bounds()


def test_mesh_without_faces_is_skipped(bpy_module, scene, sync):
    add_mesh(bpy_module, scene, "wire", [(0, 0, 0), (1, 0, 0)], [])
    assert snapshot(sync, bpy_module).objects == []


def test_nan_vertices_are_dropped(bpy_module, scene, sync):
    bpy = bpy_module
    verts = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (float("nan"), 0.0, 1.0)]
    add_mesh(bpy, scene, "bad", verts, [(0, 1, 2, 3), (0, 1, 4)])
    geo = snapshot(sync, bpy).geometry
    assert geo.triangle_count == 2
    assert np.isfinite(geo.positions).all()


def blender_triangles(mesh) -> tuple[np.ndarray, np.ndarray]:
    n = len(mesh.loop_triangles)
    triangles, faces = np.empty(3 * n, np.int32), np.empty(n, np.int32)
    mesh.loop_triangles.foreach_get("loops", triangles)
    mesh.loop_triangle_polygons.foreach_get("value", faces)
    return triangles.reshape(-1, 3), faces


@pytest.mark.parametrize("kind", ["triangles", "quads and triangles", "with an n-gon", "with a face of two corners"])
def test_the_sync_triangulates_as_blender_does(bpy_module, scene, sync, kind):
    """`mesh_arrays` makes triangle and quad meshes' triangles itself (`corner_triangles`): the
    same as Blender's loop_triangles, concave and bent quads included; n-gons are read, and so is
    a mesh a script gave a face of two corners (three a face on average with its quads)."""
    bpy = bpy_module
    rng = np.random.default_rng(7)
    sizes = {"triangles": [3] * 300, "quads and triangles": [4, 4, 3] * 200, "with an n-gon": [4, 3, 6] * 50,
             "with a face of two corners": [2, 4] * 150}[kind]
    verts, faces, at = [], [], 0
    for size in sizes:
        # Corners around a circle, jittered in and out (concave quads) and off the plane (bent).
        angles = np.sort(rng.uniform(0, 2 * np.pi, size))
        radius = rng.uniform(0.2, 1.0, size)
        centre = rng.uniform(-10, 10, 3)
        verts += [tuple(centre + (r * np.cos(a), r * np.sin(a), rng.normal(0, 0.3))) for a, r in zip(angles, radius, strict=True)]
        faces.append(tuple(range(at, at + size)))
        at += size
    mesh = bpy.data.meshes.new(kind)
    mesh.from_pydata(verts, [], faces)
    mesh.update()
    slots = rng.integers(0, 3, len(faces)).astype(np.int32)
    mesh.attributes.new("material_index", "INT", "FACE").data.foreach_set("value", slots)
    local = sync.mesh_arrays(mesh)
    triangles, tri_faces = blender_triangles(mesh)
    # (The bent quads' triangles have corners of their own, `flat_faces`: Blender's corners they copy.)
    np.testing.assert_array_equal(local.blender_corners(local.triangles), triangles)
    np.testing.assert_array_equal(local.slot, slots[tri_faces])
    if kind == "quads and triangles":
        from hybridgi_core import corner_triangles
        quads = np.flatnonzero(np.array(sizes) == 4)
        starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
        assert corner_triangles.quad_flips(local.positions, starts[quads]).any()  # some quads flip
        assert local.source is not None  # flat and bent: their triangles shaded by their own planes


def test_principled_specular_layers_are_read_and_approximations_named_once(bpy_module, scene, sync, caplog):
    bpy = bpy_module
    add_cube(bpy, scene, "bare")  # no material: Cycles' default surface, a glossy Principled BSDF
    shiny, bsdf = principled(bpy, "shiny")  # Specular IOR Level 0.5 by default
    bsdf.inputs["Roughness"].default_value = 0.3
    bsdf.inputs["IOR"].default_value = 1.45
    add_cube(bpy, scene, "painted").data.materials.append(shiny)
    matte, bsdf = principled(bpy, "matte")
    bsdf.inputs["Specular IOR Level"].default_value = 0.0
    add_cube(bpy, scene, "plain").data.materials.append(matte)
    coated, bsdf = principled(bpy, "coated")
    bsdf.inputs["Coat Weight"].default_value = 0.5
    bsdf.inputs["Coat Roughness"].default_value = 0.1
    bsdf.inputs["Sheen Weight"].default_value = 0.2
    bsdf.inputs["Anisotropic"].default_value = 0.5
    add_cube(bpy, scene, "lacquered").data.materials.append(coated)
    for name, roughness in (("rough", 0.8), ("smooth", 0.0)):
        from hybridgi_cli import blender_compat

        diffuse = blender_compat.new_material(bpy, name)
        tree = diffuse.node_tree
        node = tree.nodes.new("ShaderNodeBsdfDiffuse")
        node.inputs["Roughness"].default_value = roughness
        out = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
        tree.links.new(node.outputs[0], out.inputs["Surface"])
        add_cube(bpy, scene, f"{name}_cube").data.materials.append(diffuse)
    with caplog.at_level(logging.WARNING):
        snap = snapshot(sync, bpy)
    layers = {m.name: m.specular for m in snap.materials}
    assert layers["shiny"].roughness == pytest.approx(0.3) and layers["shiny"].ior == pytest.approx(1.45)
    assert not layers["matte"].active  # Specular IOR Level 0: no layer over the diffuse base
    assert layers["default"] is not None and layers["default"].active  # Blender's default surface
    notes = [r.getMessage() for r in caplog.records if "approximated" in r.getMessage()]
    assert len(notes) == 1, notes
    assert "'coated'" in notes[0] and "anisotropy" in notes[0] and "'Principled BSDF'" in notes[0]
    assert "sheen" not in notes[0] and "only its tint" not in notes[0]  # rendered (`sheen.py`, the coat's lobe)
    assert layers["coated"].coat == pytest.approx(0.5) and layers["coated"].coat_roughness == pytest.approx(0.1)
    assert "shiny" not in notes[0] and "matte" not in notes[0]
    coated_material = next(m for m in snap.materials if m.name == "coated")
    np.testing.assert_allclose(coated_material.sheen, 0.2)
    # A rough diffuse base (Cycles' Oren-Nayar) is rendered Lambertian: named, not silent.
    assert "rough diffuse" in notes[0] and "'rough'" in notes[0] and "'smooth'" not in notes[0]
    assert coated_material.sheen_layered
    assert not [r for r in caplog.records if "lacks the glossy part" in r.getMessage()]


def test_an_environment_maps_split_is_kept_on_disk_for_the_next_process(bpy_module, scene, sync, tmp_path,
                                                                        monkeypatch):
    """A map read from a file is split once: a later process (here: the in-memory cache emptied)
    reads the split from disk, the same, without splitting again; a file that changes is split
    again."""
    import shutil

    from hybridgi_core import environment

    bpy = bpy_module
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    path = tmp_path / "sky.exr"
    shutil.copy(Path(bpy.utils.system_resource("DATAFILES")) / "studiolights" / "world" / "forest.exr", path)
    world = bpy.data.worlds.new("hdri")
    world.use_nodes = True
    node = world.node_tree.nodes.new("ShaderNodeTexEnvironment")
    node.image = bpy.data.images.load(str(path))
    splits = []
    real = environment.split_environment
    monkeypatch.setattr(environment, "split_environment", lambda *a, **k: splits.append(1) or real(*a, **k))

    def split():
        sync._SPLITS.clear()
        return sync._environment_split(node, world.name)

    first, second = split(), split()
    assert len(splits) == 1
    np.testing.assert_array_equal(second.sky_map, first.sky_map)
    np.testing.assert_array_equal(second.sun_irradiance, first.sun_irradiance)
    assert len(list((tmp_path / "cache" / "hybridgi" / "environment").glob("*.npz"))) == 1
    os.utime(path, ns=(path.stat().st_atime_ns, path.stat().st_mtime_ns + 10**9))  # the file changed
    split()
    assert len(splits) == 2
