"""The glossy shader nodes real assets use (Glossy, Anisotropic, Metallic and Glass BSDFs; Mix and
Add Shaders with constant, Fresnel and Layer Weight factors): their closures as Cycles sets them up
(hybridgi_core/specular.py `GlossyLobe`, hybridgi_core/surface_mix.py), read from Blender
(addon/sync.py) and rendered through the real engine against Cycles rendered in the test."""

from __future__ import annotations

import importlib
import logging

import numpy as np
import pytest

from hybridgi_core import glossy, surface_mix
from hybridgi_core import specular as sp
from hybridgi_core.snapshot import Material
from tests import glossy_node_scenes
from tests.cli_renders import layer, rendered


def _integrated(surface, mu, n=400_000, seed=5):
    """Monte-Carlo integral over the hemisphere of the lobes' BRDF x cos (uniform directions)."""
    mats = glossy.GlossyMaterials.from_materials([Material(specular=surface)])
    rng = np.random.default_rng(seed)
    z = rng.random(n)
    phi = 2.0 * np.pi * rng.random(n)
    s = np.sqrt(1.0 - z * z)
    view = np.array([[np.sqrt(1.0 - mu * mu), 0.0, mu]])
    f = glossy.lobes(mats, np.zeros(1, np.int64), np.array([[0.0, 0.0, 1.0]]), view, (s * np.cos(phi))[None],
                     (s * np.sin(phi))[None], z[None])
    return f[0].mean(axis=0) * 2.0 * np.pi


LOBES = {
    "glossy": sp.GlossyLobe(weight=(0.9, 0.7, 0.4), roughness=0.4, fss=(0.9, 0.7, 0.4)),
    "f82": sp.GlossyLobe(roughness=0.35, fresnel="f82", f0=(0.9, 0.6, 0.3)),
    "conductor": sp.GlossyLobe(roughness=0.5, fresnel="conductor", n=(2.757, 2.513, 2.231), k=(3.867, 3.404, 3.009)),
    "glass": sp.GlossyLobe(weight=(1.0, 0.9, 0.8), roughness=0.45, fresnel="dielectric", ior=1.5,
                           f0=np.full(3, sp.f0_from_ior(1.5))),
}


@pytest.mark.parametrize("name", sorted(LOBES))
@pytest.mark.parametrize("mu", [0.9, 0.4])
def test_multiscatter_lobes_integrate_to_their_glossy_color(name, mu):
    """Multiscatter GGX keeps the lobe's energy, so its BRDF integrates to Cycles' albedo estimate
    (Glossy Color) whatever the Fresnel model (the conductor's BRDF is its F82 fit, its colour
    the exact Fresnel at the view angle: a percent apart)."""
    surface = sp.GlossySurface(lobes=[LOBES[name]])
    integral, expected = _integrated(surface, mu), sp.glossy_color(surface, mu)
    assert np.allclose(integral, expected, rtol=0.06, atol=3e-3), (integral, expected)


def test_a_principled_layer_as_lobes_keeps_its_glossy_color():
    """The Principled BSDF's layer through the general lobes: the dielectric layer's albedo times
    its weight plus the metallic lobe's, as `layer_albedo` and `metal_albedo` define them."""
    mu = np.linspace(0.0, 1.0, 23)
    for principled in (sp.SpecularLayer(), sp.SpecularLayer(roughness=0.3, weight=0.4, metallic=0.6, metal_color=(0.9, 0.5, 0.2)),
                  sp.SpecularLayer(ior=1.33, level=0.8, tint=(1.0, 0.6, 0.6), multiscatter=False)):
        expected = principled.weight * sp.layer_albedo(principled, mu) + principled.metallic * sp.metal_albedo(principled, mu)
        np.testing.assert_allclose(sp.glossy_color(principled, mu), expected, rtol=1e-12, atol=1e-12)
        lobes = sp.layer_lobes(principled)
        assert [lobe.fresnel for lobe in lobes] == ["dielectric"] + (["f82"] if principled.metallic else [])


def test_a_principled_transmission_reflects_as_its_glass_closure():
    """Transmission 1: no specular layer (its weight is 0) but the glass closure's reflection,
    the real Fresnel of the IOR (not the level-adjusted one) times the tint."""
    glass = sp.SpecularLayer(roughness=0.3, ior=1.5, level=1.0, weight=0.0, transmission=1.0)
    (lobe,) = sp.layer_lobes(glass)
    assert lobe.fresnel == "dielectric" and lobe.ior == 1.5
    np.testing.assert_allclose(lobe.f0, sp.f0_from_ior(1.5))
    mu = np.array([0.2, 0.6, 1.0])
    same = sp.GlossySurface(lobes=[sp.GlossyLobe(roughness=0.3, distribution="GGX", fresnel="dielectric", ior=1.5,
                                                 f0=np.full(3, sp.f0_from_ior(1.5)))])
    np.testing.assert_allclose(sp.glossy_color(glass, mu), sp.glossy_color(same, mu))
    assert np.all(sp.hemispherical_glossy_albedo(glass) > 0.04)
    half_metal = sp.SpecularLayer(weight=0.0, metallic=0.5, metal_color=(0.9, 0.9, 0.9), transmission=1.0)
    np.testing.assert_allclose(sp.layer_lobes(half_metal)[0].weight, 0.5)


def test_beckmann_and_single_scattering_ggx_lose_their_multiple_bounces():
    """Without Multiscatter GGX's compensation the lobe reflects less than Cycles' albedo
    estimate, which counts none lost (Glossy Color = the colour for a bare Glossy BSDF)."""
    for distribution in ("GGX", "BECKMANN"):
        surface = sp.GlossySurface(lobes=[sp.GlossyLobe(weight=(0.8, 0.8, 0.8), roughness=0.7,
                                                        distribution=distribution)])
        integral = _integrated(surface, 0.5)
        np.testing.assert_allclose(sp.glossy_color(surface, 0.5), 0.8)
        assert np.all(integral < 0.95 * 0.8) and np.all(integral > 0.6 * 0.8), (distribution, integral)


def test_conductor_fit_and_f82_tint_follow_cycles_definitions():
    n, k = np.array([2.757, 2.513, 2.231]), np.array([3.867, 3.404, 3.009])
    lobe = sp.GlossyLobe(fresnel="conductor", n=n, k=k)
    c = np.linspace(0.0, 1.0, 101)
    s = 1.0 - c
    fit = lobe.f0 + (1.0 - lobe.f0) * s[:, None] ** 5 - lobe.b * (c * s**6)[:, None]
    exact = sp.fresnel_conductor(c, n, k)
    # Exact at normal incidence and at cos = 1/7 (the fit's two points), close between.
    np.testing.assert_allclose(lobe.f0, sp.fresnel_conductor(1.0, n, k))
    c7 = 1.0 / 7.0
    at82 = lobe.f0 + (1.0 - lobe.f0) * (1.0 - c7) ** 5 - lobe.b * c7 * (1.0 - c7) ** 6
    np.testing.assert_allclose(at82, sp.fresnel_conductor(c7, n, k), rtol=1e-6)
    assert np.abs(fit - exact).max() < 0.03
    # F82-tint: Schlick x tint at cos = 1/7; a white tint is plain Schlick.
    f0, tint = np.array([0.9, 0.6, 0.3]), np.array([0.5, 0.8, 1.0])
    b = sp.f82_b_from_tint(f0, tint)
    schlick = f0 + (1.0 - f0) * (1.0 - c7) ** 5
    np.testing.assert_allclose(schlick - b * c7 * (1.0 - c7) ** 6, schlick * tint)
    assert b[2] == 0.0
    # Cycles' albedo estimate (Glossy Color) ignores B but for the average Fresnel of the
    # multiscatter darkening; the BRDF does not: a tinted edge reflects less.
    tinted = sp.GlossySurface(lobes=[sp.GlossyLobe(roughness=0.35, fresnel="f82", f0=f0, b=b)])
    plain = sp.GlossySurface(lobes=[sp.GlossyLobe(roughness=0.35, fresnel="f82", f0=f0)])
    np.testing.assert_allclose(sp.glossy_color(tinted, 0.4), sp.glossy_color(plain, 0.4), rtol=0.01)
    assert np.all(_integrated(tinted, 0.4)[:2] < _integrated(plain, 0.4)[:2] - 0.01)


def test_mix_with_a_fresnel_factor_weights_diffuse_by_one_minus_f_per_view_angle():
    base = np.array([0.2, 0.4, 0.8])
    fac = surface_mix.fresnel_factor(1.45)
    mu = sp.view_grid()
    np.testing.assert_allclose(fac, sp.fresnel_dielectric(mu, 1.45))
    white = sp.GlossyLobe(weight=np.ones(3), roughness=0.3, fss=np.ones(3))
    part, notes = surface_mix.mix([surface_mix.SurfacePart(base=base), surface_mix.SurfacePart(lobes=[white])],
                                  [1.0 - fac, fac])
    surface = part.surface()
    assert not notes and isinstance(surface, sp.GlossySurface)
    probe = np.array([0.05, 0.3, 0.7, 1.0])
    # Cycles' Diffuse Color: base x (1 - F(mu)); Glossy Color: F(mu) x the lobe's albedo (1 here).
    diffuse = part.base[None, :] * sp.diffuse_weight(surface, probe)[:, None]
    f = sp.fresnel_dielectric(probe, 1.45)
    np.testing.assert_allclose(diffuse, base[None, :] * (1.0 - f)[:, None], rtol=2e-3, atol=2e-4)
    np.testing.assert_allclose(sp.glossy_color(surface, probe), np.repeat(f[:, None], 3, axis=1), rtol=5e-3, atol=1e-3)
    # Probe hits reflect the diffuse colour's hemispherical mean and the lobe's mean albedo.
    hit = Material(base_color=part.base, specular=surface)
    assert hit.hit_diffuse_weight == pytest.approx(1.0, abs=0.01)
    assert np.all(hit.hit_glossy_albedo > 0.05) and np.all(hit.hit_glossy_albedo < 0.3)


def test_layer_weight_outputs_and_constant_mixes():
    mu = sp.view_grid()
    np.testing.assert_allclose(surface_mix.layer_weight_factor(0.3, "Facing"), 1.0 - mu**0.6)
    np.testing.assert_allclose(surface_mix.layer_weight_factor(0.75, "Facing"), 1.0 - mu**2.0)
    np.testing.assert_allclose(surface_mix.layer_weight_factor(0.5, "Facing"), 1.0 - mu)
    np.testing.assert_allclose(surface_mix.layer_weight_factor(0.5, "Fresnel"), sp.fresnel_dielectric(mu, 2.0))
    # A constant factor scales the lobes' weights and the colours; no view-dependent weight remains.
    lobe = sp.GlossyLobe(weight=(0.5, 0.5, 0.5), roughness=0.4)
    part, _ = surface_mix.mix([surface_mix.SurfacePart(base=np.array([0.6, 0.6, 0.6])),
                               surface_mix.SurfacePart(lobes=[lobe])], [surface_mix.constant_factor(0.75),
                                                                        surface_mix.constant_factor(0.25)])
    np.testing.assert_allclose(part.base, 0.45, rtol=1e-6)
    assert part.diffuse is None and part.lobes[0].view is None
    np.testing.assert_allclose(part.lobes[0].weight, 0.125)
    # Two diffuse colours under a view-dependent factor are not one colour: noted.
    fac = surface_mix.fresnel_factor(1.5)
    _, notes = surface_mix.mix([surface_mix.SurfacePart(base=np.array([1.0, 0.0, 0.0])),
                                surface_mix.SurfacePart(base=np.array([0.0, 0.0, 1.0]))], [1.0 - fac, fac])
    assert notes


def test_factor_nodes_follow_cycles_math_and_ramps():
    a = np.array([-0.5, 0.0, 0.5, 2.0])
    np.testing.assert_allclose(surface_mix.math_factor("DIVIDE", a, np.array([1.0, 0.0, 0.25, 4.0]), False),
                               [-0.5, 0.0, 2.0, 0.5])  # safe division: x / 0 = 0
    np.testing.assert_allclose(surface_mix.math_factor("POWER", a, 0.5, True), [0.0, 0.0, np.sqrt(0.5), 1.0])
    assert surface_mix.math_factor("SINE", a, 0.0, False) is None
    fac = np.array([0.0, 0.3, 0.5, 0.8, 1.5])
    stops, colours = [0.6, 0.2], [(1.0, 1.0, 1.0, 1.0), (0.0, 0.0, 0.0, 0.5)]
    np.testing.assert_allclose(surface_mix.ramp_factor(fac, stops, colours, "LINEAR")[:, 0], [0, 0.25, 0.75, 1, 1])
    np.testing.assert_allclose(surface_mix.ramp_factor(fac, stops, colours, "CONSTANT")[:, 3], [0.5, 0.5, 0.5, 1, 1])
    assert surface_mix.ramp_factor(fac, stops, colours, "B_SPLINE") is None


def test_bad_lobe_inputs_stay_finite():
    lobe = sp.GlossyLobe(weight=(np.nan, -1.0, 2.0), roughness=np.inf, distribution="PHONG", ior=np.nan,
                         f0=(2.0, np.nan, -1.0), view=np.array([np.nan, 0.5, 2.0]))
    assert lobe.distribution == "GGX" and lobe.roughness == 0.5 and lobe.ior == 1.5
    np.testing.assert_allclose(lobe.weight, [0.0, 0.0, 2.0])
    assert np.isfinite(sp.glossy_color(sp.GlossySurface(lobes=[lobe]), np.linspace(0, 1, 5))).all()
    with pytest.raises(ValueError):
        sp.GlossyLobe(fresnel="thin film")


# --- read from Blender --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sync(bpy_module):
    from hybridgi_cli import dev_install

    return importlib.import_module(f"{dev_install.enable().__name__}.sync")


def _material(bpy, name, build):
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    tree = mat.node_tree
    tree.nodes.remove(tree.nodes["Principled BSDF"])
    tree.links.new(build(tree).outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    return mat


@pytest.mark.blender
def test_glossy_nodes_are_read_as_cycles_sets_them_up(bpy_module, sync, caplog):
    bpy = bpy_module

    def plastic(tree):
        mix = tree.nodes.new("ShaderNodeMixShader")
        diffuse = tree.nodes.new("ShaderNodeBsdfDiffuse")
        diffuse.inputs["Color"].default_value = (0.2, 0.4, 0.8, 1.0)
        shiny = tree.nodes.new("ShaderNodeBsdfGlossy")
        shiny.inputs["Roughness"].default_value = 0.3
        fresnel = tree.nodes.new("ShaderNodeFresnel")
        fresnel.inputs["IOR"].default_value = 1.45
        tree.links.new(diffuse.outputs[0], mix.inputs[1])
        tree.links.new(shiny.outputs[0], mix.inputs[2])
        tree.links.new(fresnel.outputs[0], mix.inputs["Fac"])
        return mix

    def brushed(tree):
        node = tree.nodes.new("ShaderNodeBsdfGlossy")
        node.name = "Brushed"
        node.inputs["Anisotropy"].default_value = 0.5
        node.distribution = "BECKMANN"
        return node

    def conductor(tree):
        node = tree.nodes.new("ShaderNodeBsdfMetallic")
        node.fresnel_type = "PHYSICAL_CONDUCTOR"
        return node

    def glass(tree):
        node = tree.nodes.new("ShaderNodeBsdfGlass")
        node.inputs["Roughness"].default_value = 0.2
        return node

    def frosted(tree):
        # Mix(Diffuse, Glass, 0.3): 30% of the light passes, under the clear threshold: the
        # glass's reflection is read as its lobe, the rest stays opaque.
        mix = tree.nodes.new("ShaderNodeMixShader")
        mix.inputs["Fac"].default_value = 0.3
        tree.links.new(tree.nodes.new("ShaderNodeBsdfDiffuse").outputs[0], mix.inputs[1])
        tree.links.new(glass(tree).outputs[0], mix.inputs[2])
        return mix

    def lacquer(tree):
        mix = tree.nodes.new("ShaderNodeMixShader")
        mix.inputs["Fac"].default_value = 0.25
        base = tree.nodes.new("ShaderNodeBsdfPrincipled")
        base.inputs["Base Color"].default_value = (0.8, 0.2, 0.1, 1.0)
        coat = tree.nodes.new("ShaderNodeBsdfGlossy")
        coat.inputs["Roughness"].default_value = 0.1
        tree.links.new(base.outputs[0], mix.inputs[1])
        tree.links.new(coat.outputs[0], mix.inputs[2])
        return mix

    def ramped(tree):
        # A tutorial's factor: Layer Weight (Facing) -> Color Ramp (0.2: black, 0.9: white) ->
        # Math (power 2) -> Fac.
        mix = tree.nodes.new("ShaderNodeMixShader")
        weight = tree.nodes.new("ShaderNodeLayerWeight")
        weight.inputs["Blend"].default_value = 0.5
        ramp = tree.nodes.new("ShaderNodeValToRGB")
        ramp.color_ramp.elements[0].position = 0.2
        ramp.color_ramp.elements[1].position = 0.9
        power = tree.nodes.new("ShaderNodeMath")
        power.operation = "POWER"
        power.inputs[1].default_value = 2.0
        tree.links.new(weight.outputs["Facing"], ramp.inputs["Fac"])
        tree.links.new(ramp.outputs["Color"], power.inputs[0])
        tree.links.new(power.outputs[0], mix.inputs["Fac"])
        tree.links.new(tree.nodes.new("ShaderNodeBsdfDiffuse").outputs[0], mix.inputs[1])
        tree.links.new(tree.nodes.new("ShaderNodeBsdfGlossy").outputs[0], mix.inputs[2])
        return mix

    def mapped(tree):
        # A Glossy BSDF whose Roughness reads a (non-colour) image directly: its mean, 0.35.
        image = bpy.data.images.new("roughness map", 2, 2, float_buffer=True)
        image.colorspace_settings.name = "Non-Color"
        rgba = np.repeat(np.array([0.1, 0.2, 0.5, 0.6], np.float32)[:, None], 4, axis=1)
        rgba[:, 3] = 1.0
        image.pixels.foreach_set(rgba.ravel())
        texture = tree.nodes.new("ShaderNodeTexImage")
        texture.image = image
        node = tree.nodes.new("ShaderNodeBsdfGlossy")
        node.name = "Mapped"
        tree.links.new(texture.outputs["Color"], node.inputs["Roughness"])
        return node

    builders = {"plastic": plastic, "brushed": brushed, "glass": glass, "frosted": frosted, "lacquer": lacquer,
                "ramped": ramped, "mapped": mapped}
    if hasattr(bpy.types, "ShaderNodeBsdfMetallic"):  # Blender 4.3 and later
        builders["conductor"] = conductor
    mats = [_material(bpy, name, build) for name, build in builders.items()]
    with caplog.at_level(logging.WARNING):
        by_name = {m.name: sync.material_from_blender(m) for m in mats}
    for m in mats:
        bpy.data.materials.remove(m)

    plastic_surface = by_name["plastic"].specular
    (lobe,) = plastic_surface.lobes
    mu = np.array([0.1, 0.5, 1.0])
    f = sp.fresnel_dielectric(mu, 1.45)
    # The lobe's colour (0.8) is its weight and, under Multiscatter GGX, its average Fresnel.
    albedo = sp.lobe_albedo(sp.GlossyLobe(roughness=0.3, fss=np.full(3, 0.8)), mu)[:, 0]
    assert albedo[0] < 0.99 and albedo[-1] == pytest.approx(1.0, abs=0.01)
    np.testing.assert_allclose(sp.glossy_color(plastic_surface, mu)[:, 0], 0.8 * f * albedo, rtol=0.01)
    np.testing.assert_allclose(by_name["plastic"].base_color[2] * sp.diffuse_weight(plastic_surface, mu),
                               0.8 * (1.0 - f), rtol=0.01)
    # Mix(Principled, Glossy, 0.25): the Principled's lobes at 0.75, the Glossy's at 0.25, and the
    # diffuse colour under the Principled's own layering, at 0.75.
    lacquer = by_name["lacquer"].specular
    alone = sp.SpecularLayer(roughness=0.5)
    assert [lobe.fresnel for lobe in lacquer.lobes] == ["dielectric", "none"]
    np.testing.assert_allclose(lacquer.lobes[0].weight, 0.75)
    np.testing.assert_allclose(lacquer.lobes[1].weight, 0.25 * 0.8, rtol=1e-6)
    np.testing.assert_allclose(by_name["lacquer"].base_color[0] * sp.diffuse_weight(lacquer, mu),
                               0.75 * 0.8 * sp.diffuse_weight(alone, mu), rtol=2e-3)
    (ramped,) = by_name["ramped"].specular.lobes
    facing = 1.0 - mu
    # Tabulated over 64 cosines: a percent off at the ramp's kink (mu = 0.1).
    np.testing.assert_allclose(sp.sample_view(ramped.view, mu), np.clip((facing - 0.2) / 0.7, 0.0, 1.0) ** 2,
                               atol=0.01)
    (mapped,) = by_name["mapped"].specular.lobes
    assert mapped.roughness == pytest.approx(0.35, abs=1e-3)
    (brushed,) = by_name["brushed"].specular.lobes
    assert brushed.distribution == "BECKMANN" and brushed.fresnel == "none"
    # A Glass BSDF on its own lets most of its light through: clear thin glass, no lobes.
    assert by_name["glass"].clear and by_name["glass"].specular is None
    np.testing.assert_allclose(by_name["glass"].base_color, 0.0)
    # Mixed under the threshold: its reflection is the Glass BSDF's lobe at the mix's weight.
    assert not by_name["frosted"].clear
    (glass_lobe,) = by_name["frosted"].specular.lobes
    assert glass_lobe.fresnel == "dielectric" and glass_lobe.ior == pytest.approx(1.5)
    np.testing.assert_allclose(glass_lobe.weight, 0.3)
    np.testing.assert_allclose(by_name["frosted"].base_color, 0.7 * 0.8, rtol=1e-6)
    if "conductor" in by_name:
        (metal,) = by_name["conductor"].specular.lobes
        assert metal.fresnel == "conductor"
        np.testing.assert_allclose(metal.f0, sp.fresnel_conductor(1.0, metal.n, metal.k))
    # What stays approximated: one warning, naming each material and node.
    notes = [r.getMessage() for r in caplog.records if "approximated" in r.getMessage()]
    assert not notes  # material_from_blender alone records; the sync warns (next test)


@pytest.mark.blender
def test_approximations_are_warned_once_per_sync_naming_material_and_node(bpy_module, sync, empty_scene, caplog):
    bpy = bpy_module

    def brushed(tree):
        node = tree.nodes.new("ShaderNodeBsdfGlossy")
        node.name = "Brushed"
        node.inputs["Anisotropy"].default_value = 0.5
        return node

    def glass(tree):
        node = tree.nodes.new("ShaderNodeBsdfGlass")
        node.name = "Pane"
        return node

    for name, build in (("steel", brushed), ("window", glass)):
        mesh = bpy.data.meshes.new(name)
        mesh.from_pydata([(0, 0, 0), (1, 0, 0), (1, 1, 0)], [], [(0, 1, 2)])
        obj = bpy.data.objects.new(name, mesh)
        obj.data.materials.append(_material(bpy, name, build))
        empty_scene.collection.objects.link(obj)
    with caplog.at_level(logging.WARNING):
        sync.snapshot_from_depsgraph(bpy.context.evaluated_depsgraph_get())
    notes = [r.getMessage() for r in caplog.records if "approximated" in r.getMessage()]
    assert len(notes) == 1, notes
    assert "'steel'" in notes[0] and "'Brushed'" in notes[0] and "anisotropy" in notes[0]
    assert "'window'" in notes[0] and "clear thin glass" in notes[0]


# --- through the real engine against Cycles ----------------------------------------------------

RES = "80x60"
SAMPLES = "256"

#: Upper bounds of the relative L1 over geometry pixels, from measurements at 80x60 and 256 spp
#: (in the comments: what was measured; before these nodes were read, the glossy light was
#: missing: Combined 0.5-1.0, Glossy Color 1.0).
BOUNDS = {
    # Glossy Direct 0.050 / 0.051 before the lamp-sampled highlight of the 0.5-rough floors was
    # filtered (`reflection.filter_lamp_glossy`), 0.035 / 0.036 after.
    "glossy": {"Glossy Color": 0.02, "Glossy Direct": 0.045, "Combined": 0.15},
    "mix_fresnel": {"Diffuse Color": 0.01, "Glossy Color": 0.05, "Glossy Direct": 0.2, "Combined": 0.08},
    "mix_layer_weight": {"Diffuse Color": 0.01, "Glossy Color": 0.05, "Glossy Direct": 0.2, "Combined": 0.12},
    "add": {"Diffuse Color": 0.01, "Glossy Color": 0.05, "Glossy Direct": 0.2, "Combined": 0.06},
    "metallic": {"Glossy Color": 0.02, "Glossy Direct": 0.045, "Combined": 0.15},
    # Principled BSDFs: a metal's Specular Tint is its F82 edge tint; the reflection of a glass
    # closure under 40% transmission (its transmitted light is not rendered below the clear
    # threshold: Combined is not compared). At transmission 1 (then 0.25 / 0.65) the ball is
    # clear glass now (`snapshot.Material.clear`); at 0.4 measured 0.133 / 0.167.
    "tinted_metal": {"Glossy Color": 0.05, "Glossy Direct": 0.22, "Combined": 0.1},
    "principled_glass": {"Glossy Color": 0.2, "Glossy Direct": 0.25},
}


def _error(mine, reference, mask):
    return float(np.abs(mine - reference)[mask].sum() / np.abs(reference)[mask].sum())


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.parametrize("kind", sorted(BOUNDS))
def test_glossy_nodes_match_cycles(kind, tmp_path):
    import bpy

    if kind == "metallic" and not hasattr(bpy.types, "ShaderNodeBsdfMetallic"):
        pytest.skip("this Blender has no Metallic BSDF")
    blend = tmp_path / f"{kind}.blend"
    glossy_node_scenes.build(kind, blend)
    ours = rendered(blend, tmp_path / "hg", RES)
    cycles = rendered(blend, tmp_path / "cy", RES, "--engine", "CYCLES", "--samples", SAMPLES)

    def passed(channels, name):
        # Before Blender 5.0 Cycles names these passes DiffCol, GlossDir ...; HybridGI 5.0's names.
        legacy = {"Diffuse Color": "DiffCol", "Glossy Direct": "GlossDir", "Glossy Color": "GlossCol"}
        return layer(channels, name if f"ViewLayer.{name}.R" in channels else legacy.get(name, name))

    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    errors = {name: _error(passed(ours, name), passed(cycles, name), geometry) for name in BOUNDS[kind]}
    share = float((passed(cycles, "Glossy Direct") * passed(cycles, "Glossy Color"))[geometry].sum()
                  / layer(cycles, "Combined")[geometry][:, :3].sum())
    assert share > (0.01 if kind == "principled_glass" else 0.05), share  # the glossy light counts
    for name, bound in BOUNDS[kind].items():
        assert errors[name] < bound, (name, errors)
    if kind == "tinted_metal":
        # The edge tint darkens the metal's grazing highlights (measured at 128x96: Glossy Direct
        # bias +0.090 without it, +0.021 with it).
        ours_gd, cycles_gd = passed(ours, "Glossy Direct")[geometry], passed(cycles, "Glossy Direct")[geometry]
        bias = float((ours_gd - cycles_gd).sum() / cycles_gd.sum())
        assert abs(bias) < 0.05, bias
