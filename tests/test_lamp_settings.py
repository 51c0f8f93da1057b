"""Lamp and scene settings Cycles honours that HybridGI once ignored: portals, Spread, the Shadow
checkbox, ray visibility of lamp objects, lamp node trees, light/shadow linking, Cycles' diffuse
bounce limit, volumes.

Core tests (numpy only) check the physics; sync tests read tiny bpy scenes; the CLI tests render
the Cornell box with HybridGI and with Cycles in the test. Measured before -> after (64x48, Cycles
64 spp + OIDN, mean over geometry pixels):

- portal (1.2 m, 400 W area lamp marked Portal inside the box): Diffuse Direct 3.88 vs Cycles'
  0.384 -> 0.384;
- ceiling lamp with Shadow off: Diffuse Direct 0.384 vs 0.415 -> 0.417;
- Spread 30 degrees: Diffuse Direct 0.384 vs 0.199 -> 0.194 (rel L1 2.59 -> 0.14); Spread 0 (a
  collimated beam) 0.151 vs Cycles' 0.146;
- lamp node tree, Emission Strength 2, Color (1, 0.5, 0.25): 0.384 vs 0.448 -> 0.448; a
  Blackbody node at 3000 K renders as the lamp's Temperature 3000 K (Cycles: identical);
- lamp object hidden from diffuse rays: 0.384 vs 0 -> 0;
- Diffuse factor 0.5 (EEVEE's; Cycles ignores it): 0.192 vs 0.384 -> 0.384;
- Cycles diffuse bounces 0: Diffuse Indirect 0.364 vs 0 -> 0; 1: 0.364 vs 0.172 -> 0.169; the
  car under its sky, 0 bounces: Combined 0.592 vs 0.590 (Diffuse Indirect 0 as Cycles').
"""

from __future__ import annotations

import importlib
import logging
import math
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from hybridgi_core import glossy
from hybridgi_core.lights import direct_irradiance, spread_attenuation
from hybridgi_core.snapshot import Light
from tests.cli_renders import CYCLES, QUICK

# --- core: Spread and the Shadow checkbox -------------------------------------------------


def area(spread=np.pi, cast_shadow=True, power=100.0, size=1.0, z=2.0, **kw):
    m = np.eye(4)
    m[2, 3] = z  # facing down (local -Z)
    return Light(kind="AREA", color=np.ones(3, np.float32), power=power, matrix=m, size=size, size_y=size,
                 spread=spread, cast_shadow=cast_shadow, **kw)


class BlockEverything:
    """A tracer whose every shadow ray is blocked (an opaque slab between lamp and receivers)."""

    def occluded(self, origins, directions, tfar=np.inf, trusted=False):
        return np.ones(np.asarray(origins).shape[0], bool)


@pytest.mark.parametrize("degrees", [1.0, 10.0, 30.0, 90.0, 179.0])
def test_spread_keeps_the_lamps_power(degrees):
    """Cycles normalizes the soft-box attenuation so that the cosine-weighted integral over the
    hemisphere stays pi (the same power as a Lambertian lamp), and nothing leaves outside the cone."""
    lamp = area(np.radians(degrees))
    a = np.linspace(0.0, np.pi / 2, 400001)[:-1] + np.pi / 4e5  # midpoints
    att = spread_attenuation(lamp, np.cos(a), np.tan(a))
    integral = float((att * np.cos(a) * np.sin(a)).sum() * 2.0 * np.pi * (np.pi / 2 / 400000))
    assert integral == pytest.approx(np.pi, rel=2e-3)
    assert att[a > np.radians(degrees) / 2 + 1e-6].max() == 0.0
    assert spread_attenuation(area(), np.cos(a), np.tan(a)) is None  # 180 degrees: Lambertian


def brute_force(lamp, p, n, k=400):
    """Irradiance at p (normal n) by a midpoint sum over the lamp's square, spread included."""
    s = lamp.size
    g = (np.arange(k) + 0.5) / k * s - s / 2
    x, y = np.meshgrid(g, g)
    q = np.stack([x.ravel(), y.ravel(), np.full(x.size, lamp.matrix[2, 3])], 1)
    w = q - p
    d2 = (w * w).sum(1)
    d = w / np.sqrt(d2)[:, None]
    cos_l = d[:, 2]  # the lamp's normal is -Z: cos = -(d . -Z)
    cos_r = np.maximum(d @ n, 0.0)
    att = spread_attenuation(lamp, cos_l, np.sqrt(1 - cos_l**2) / cos_l)
    radiance = lamp.power / (np.pi * s * s)
    return float((radiance * att * cos_l * cos_r / d2).sum() * (s / k) ** 2)


@pytest.mark.parametrize("solid_angle", [True, False])
def test_area_lamp_spread_narrows_the_light_as_the_integral(solid_angle):
    lamp = area(np.radians(30.0))
    up = np.array([0.0, 0.0, 1.0])
    points = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [0.9, 0.3, 0.0], [2.0, 0.0, 0.0]])
    p = np.repeat(points, 64, 0).astype(np.float32)
    e = direct_irradiance([lamp], p, np.tile(up, (p.shape[0], 1)).astype(np.float32), None,
                          np.random.default_rng(1), samples=64, solid_angle=solid_angle)[:, 0]
    mean = e.reshape(len(points), 64).mean(1)
    expected = [brute_force(lamp, q, up) for q in points]
    assert expected[3] == 0.0 and mean[3] == 0.0  # outside the cone: dark
    np.testing.assert_allclose(mean[:3], expected[:3], rtol=0.03)
    # The Lambertian lamp gives the point below 2.5x less than this 30-degree one.
    assert mean[0] > 2.0 * direct_irradiance([area()], points[:1].astype(np.float32), up[None].astype(np.float32),
                                             None, np.random.default_rng(1), samples=64)[0, 0]


def test_spread_zero_is_a_collimated_beam():
    """Spread 0: Cycles' attenuation is pi along the normal only, a beam of P / A over the lamp's
    footprint (sampling the lamp would almost never find that direction: it rendered black)."""
    lamp = area(0.0, power=100.0, size=1.0)
    p = np.float32([[0.0, 0.0, 0.0], [0.45, -0.45, 0.0], [0.55, 0.0, 0.0], [0.0, 0.0, 3.0]])
    n = np.float32([[0, 0, 1], [0, 0.6, 0.8], [0, 0, 1], [0, 0, 1]])
    e = direct_irradiance([lamp], p, n, None, np.random.default_rng(0), samples=16)[:, 0]
    np.testing.assert_allclose(e, [100.0, 80.0, 0.0, 0.0], rtol=1e-5)  # outside the footprint, behind: dark
    assert direct_irradiance([lamp], p, n, BlockEverything(), np.random.default_rng(0), samples=16).max() == 0.0
    dirs, weight, _ = glossy._lamp_samples(lamp, p.astype(np.float64), np.random.default_rng(0), 16)
    np.testing.assert_allclose(weight[:, 0], [100.0, 100.0, 0.0, 0.0])
    np.testing.assert_allclose(dirs[0, 0], [0.0, 0.0, 1.0])


def test_glossy_lamp_samples_follow_the_spread():
    """Glossy lobes see the narrowed lamp too: a receiver outside the cone gets no lamp sample weight."""
    lamp = area(np.radians(30.0))
    p = np.array([[2.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    _, weight, _ = glossy._lamp_samples(lamp, p, np.random.default_rng(0), 16)
    assert weight[0].sum() == 0.0 and weight[1].sum() > 0.0


@pytest.mark.parametrize("kind", ["AREA", "POINT", "SUN"])
def test_lamp_with_shadow_off_traces_no_shadow_rays(kind):
    if kind == "AREA":
        lamps = [area(cast_shadow=c) for c in (True, False)]
    else:
        m = np.eye(4)
        m[2, 3] = 2.0
        lamps = [Light(kind=kind, color=np.ones(3, np.float32), power=100.0, matrix=m, cast_shadow=c, radius=0.1)
                 for c in (True, False)]
    p = np.zeros((8, 3), np.float32)
    n = np.tile(np.float32([0, 0, 1]), (8, 1))
    shadowed, free = (direct_irradiance([lt], p, n, BlockEverything(), np.random.default_rng(0), samples=4)
                      for lt in lamps)
    unblocked = direct_irradiance([lamps[1]], p, n, None, np.random.default_rng(0), samples=4)
    assert shadowed.max() == 0.0
    np.testing.assert_allclose(free, unblocked)
    assert free.min() > 0.0


def test_glossy_power_is_what_glossy_lobes_see():
    lamp = area(glossy_power=0.0)
    assert lamp.for_glossy().power == 0.0 and lamp.power == 100.0
    assert area().for_glossy() is not None and area().for_glossy().power == 100.0


# --- sync: what a Blender lamp and scene say ----------------------------------------------


def add_light(bpy, scene, name, kind="AREA", **settings):
    data = bpy.data.lights.new(name, kind)
    for key, value in settings.items():
        setattr(data, key, value)
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    return obj


def lamps(sync, bpy):
    return {lt.name: lt for lt in sync.snapshot_from_depsgraph(bpy.context.evaluated_depsgraph_get()).lights}


@pytest.mark.blender
def test_lamp_settings_are_read_as_cycles_renders_them(bpy_module, empty_scene, sync, caplog):
    bpy, scene = bpy_module, empty_scene
    portal = add_light(bpy, scene, "portal", energy=400.0)
    portal.data.cycles.is_portal = True
    add_light(bpy, scene, "no_shadow", use_shadow=False)
    add_light(bpy, scene, "spread", spread=math.radians(30))
    add_light(bpy, scene, "factors", diffuse_factor=0.5, specular_factor=0.0)  # EEVEE's: Cycles ignores them
    add_light(bpy, scene, "hidden_diffuse").visible_diffuse = False
    add_light(bpy, scene, "hidden_glossy").visible_glossy = False
    with caplog.at_level(logging.DEBUG):
        found = lamps(sync, bpy)
    assert "portal" not in found
    assert any("portal" in r.getMessage() for r in caplog.records if r.levelno == logging.DEBUG)
    assert not found["no_shadow"].cast_shadow and found["spread"].cast_shadow
    assert found["spread"].spread == pytest.approx(math.radians(30)) and found["no_shadow"].spread == pytest.approx(np.pi)
    assert found["factors"].power == pytest.approx(10.0) and found["factors"].for_glossy().power == pytest.approx(10.0)
    assert found["hidden_diffuse"].power == 0.0 and found["hidden_diffuse"].for_glossy().power == pytest.approx(10.0)
    assert found["hidden_glossy"].power == pytest.approx(10.0) and found["hidden_glossy"].for_glossy().power == 0.0


@pytest.mark.blender
def test_negative_lamps_are_switched_off_and_named(bpy_module, empty_scene, sync, caplog):
    # Cycles subtracts a negative lamp's light; HybridGI's samplers took it as positive light
    # (the lamp lit nothing, its penumbra and glossy estimates left speckles and rings).
    bpy, scene = bpy_module, empty_scene
    add_light(bpy, scene, "negative", "POINT", energy=-500.0)
    add_light(bpy, scene, "negative_area", energy=-20.0)
    tinted = add_light(bpy, scene, "negative_node", "POINT", energy=100.0)
    tinted.data.use_nodes = True
    tinted.data.node_tree.nodes["Emission"].inputs["Strength"].default_value = -1.0
    add_light(bpy, scene, "zero", "POINT", energy=0.0)
    add_light(bpy, scene, "positive", "POINT", energy=100.0)
    with caplog.at_level(logging.WARNING):
        found = lamps(sync, bpy)
    assert sorted(found) == ["positive", "zero"]
    warned = [r.getMessage() for r in caplog.records if "negative" in r.getMessage()]
    assert len(warned) == 1 and all(f"'{n}'" in warned[0] for n in ("negative", "negative_area", "negative_node"))


@pytest.mark.blender
def test_lamp_node_trees(bpy_module, empty_scene, sync, caplog):
    bpy, scene = bpy_module, empty_scene
    emission = add_light(bpy, scene, "emission", "POINT", energy=100.0)
    emission.data.use_nodes = True
    node = emission.data.node_tree.nodes["Emission"]
    node.inputs["Strength"].default_value = 2.0
    node.inputs["Color"].default_value = (1.0, 0.5, 0.25, 1.0)
    blackbody = add_light(bpy, scene, "blackbody", "POINT", energy=100.0)
    blackbody.data.use_nodes = True
    tree = blackbody.data.node_tree
    kelvin = tree.nodes.new("ShaderNodeBlackbody")
    kelvin.inputs["Temperature"].default_value = 3000.0
    tree.links.new(kelvin.outputs[0], tree.nodes["Emission"].inputs["Color"])
    textured = add_light(bpy, scene, "textured", "POINT", energy=100.0)
    textured.data.use_nodes = True
    tree = textured.data.node_tree
    tree.links.new(tree.nodes.new("ShaderNodeTexNoise").outputs["Color"], tree.nodes["Emission"].inputs["Color"])
    unlinked = add_light(bpy, scene, "unlinked", "POINT", energy=100.0)
    unlinked.data.use_nodes = True
    tree = unlinked.data.node_tree
    tree.links.remove(tree.nodes["Light Output"].inputs["Surface"].links[0])
    with caplog.at_level(logging.WARNING):
        found = lamps(sync, bpy)
    np.testing.assert_allclose(found["emission"].color * found["emission"].power, [200.0, 100.0, 50.0], rtol=1e-5)
    assert float(np.max(found["unlinked"].color)) == 0.0  # Cycles: an output with nothing linked is dark
    # A Blackbody node renders as the light's own Temperature (Cycles: identical Diffuse Direct);
    # lights have one from Blender 4.3 on.
    reference = bpy.data.lights.new("reference", "POINT")
    if hasattr(reference, "use_temperature"):
        reference.use_temperature, reference.temperature = True, 3000.0
        np.testing.assert_allclose(found["blackbody"].color, reference.temperature_color, rtol=3e-3)
    warned = [r.getMessage() for r in caplog.records if "fed by a node" in r.getMessage()]
    assert len(warned) == 1 and "'textured'" in warned[0] and "blackbody" not in warned[0]


@pytest.mark.blender
def test_linking_volumes_and_glossy_ray_visibility_are_warned_once(bpy_module, empty_scene, sync, caplog):
    """What HybridGI does not follow is named once per sync; a shadow catcher is followed by
    final renders now (`catcher.py`), so only a viewport's sync names it, as the viewport's limit."""
    bpy, scene = bpy_module, empty_scene
    from hybridgi_cli import blender_compat

    catcher = bpy.data.objects.new("catcher", bpy.data.meshes.new("plane"))
    catcher.data.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    catcher.is_shadow_catcher = True
    catcher.visible_glossy = False
    scene.collection.objects.link(catcher)
    lamp = add_light(bpy, scene, "linked_lamp")
    lamp.light_linking.receiver_collection = bpy.data.collections.new("receivers")
    lamp.light_linking.blocker_collection = bpy.data.collections.new("blockers")
    mesh = bpy.data.meshes.new("m")
    mesh.from_pydata([(0, 0, 0), (1, 0, 0), (0, 1, 0)], [], [(0, 1, 2)])
    obj = bpy.data.objects.new("fog_box", mesh)
    scene.collection.objects.link(obj)
    mat = blender_compat.new_material(bpy, "fog")
    out = next(n for n in mat.node_tree.nodes if n.type == "OUTPUT_MATERIAL")
    mat.node_tree.links.new(mat.node_tree.nodes.new("ShaderNodeVolumePrincipled").outputs[0], out.inputs["Volume"])
    obj.data.materials.append(mat)
    world = bpy.data.worlds.new("w")
    if world.node_tree is None:  # before 5.0
        world.use_nodes = True
    wout = next(n for n in world.node_tree.nodes if n.type == "OUTPUT_WORLD")
    world.node_tree.links.new(world.node_tree.nodes.new("ShaderNodeVolumeScatter").outputs[0], wout.inputs["Volume"])
    scene.world = world
    with caplog.at_level(logging.WARNING):
        lamps(sync, bpy)
    messages = [r.getMessage() for r in caplog.records]
    assert sum("light-linked" in m and "linked_lamp" in m for m in messages) == 1
    assert sum("shadow-linked" in m and "linked_lamp" in m for m in messages) == 1
    assert sum("'fog'" in m and "Volume" in m for m in messages) == 1
    # (Named here only as the viewport's limit: this depsgraph is a viewport's, not a render's.)
    assert all("final renders only" in m for m in messages if "a shadow catcher" in m)
    assert sum("catcher" in m and "hidden from glossy rays" in m for m in messages) == 1
    assert sum("world 'w'" in m and "Volume" in m for m in messages) == 1


@pytest.mark.blender
@pytest.mark.parametrize(("bounces", "quality", "bounce_light"), [(0, 1, False), (1, 1, True), (4, 2, True)])
def test_cycles_diffuse_bounce_limit_sets_the_indirect_quality(bpy_module, empty_scene, addon, bounces, quality,
                                                               bounce_light):
    pipeline = importlib.import_module(f"{addon.__name__}.pipeline")
    scene = empty_scene
    scene.cycles.diffuse_bounces = bounces
    settings = scene.hybridgi.cache_settings(scene)
    assert (settings.indirect_quality, settings.bounce_light) == (quality, bounce_light)
    notes = pipeline.unsupported_settings(scene, scene.view_layers[0])
    assert any("bounce limit" in n for n in notes) == (bounces < 2)
    scene.cycles.diffuse_bounces, scene.cycles.max_bounces = 4, 1  # Max Bounces limits the diffuse ones too
    assert scene.hybridgi.cache_settings(scene).indirect_quality == 1


@pytest.mark.blender
def test_passes_cycles_would_add_are_named_as_not_written(bpy_module, empty_scene, addon):
    """Shader AOVs, light groups and Cycles' own passes (denoising data, volume) add passes to
    Cycles' render that HybridGI does not write: each is named in the warning, none is silent."""
    pipeline = importlib.import_module(f"{addon.__name__}.pipeline")
    scene = empty_scene
    layer = scene.view_layers[0]
    assert not any("passes not written" in n for n in pipeline.unsupported_settings(scene, layer))
    layer.aovs.add().name = "mask"
    layer.lightgroups.add(name="key")
    layer.cycles.denoising_store_passes = True
    layer.cycles.use_pass_volume_direct = True
    note = next(n for n in pipeline.unsupported_settings(scene, layer) if "passes not written" in n)
    for name in ("AOV 'mask'", "Combined_key", "Denoising Data", "Volume Direct"):
        assert name in note, note


@pytest.mark.blender
def test_cycles_filter_glossy_reaches_the_cache_settings(bpy_module, empty_scene, addon):
    scene = empty_scene
    assert scene.hybridgi.cache_settings(scene).filter_glossy == pytest.approx(scene.cycles.blur_glossy)
    scene.cycles.blur_glossy = 0.0
    assert scene.hybridgi.cache_settings(scene).filter_glossy == 0.0


# --- renders against Cycles -----------------------------------------------------------------

RES = "64x48"


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    from tests.cli_renders import cornell_variants

    script = textwrap.dedent("""
        import math
        def base():
            bpy.ops.wm.open_mainfile(filepath=src)
            return next(o for o in bpy.data.objects if o.type == "LIGHT")
        def save(name):
            bpy.ops.wm.save_as_mainfile(filepath=out + "/" + name + ".blend")
        base()
        data = bpy.data.lights.new("portal", "AREA")
        data.size, data.energy, data.cycles.is_portal = 1.2, 400.0, True
        ob = bpy.data.objects.new("portal", data)
        bpy.context.scene.collection.objects.link(ob)
        ob.location = (0.0, 0.0, 1.5)
        save("portal")
        base().data.use_shadow = False
        save("no_shadow")
        base().data.spread = math.radians(30)
        save("spread")
        base().data.spread = 0.0
        save("spread0")
        base()
        bpy.context.scene.cycles.film_exposure = 2.0
        save("film_exposure")
        bpy.ops.wm.open_mainfile(filepath=out + "/car.blend")
        bpy.context.scene.cycles.diffuse_bounces = 0
        save("bounces0")
        bpy.ops.wm.open_mainfile(filepath=out + "/car.blend")
        bpy.context.scene.world.cycles_visibility.camera = False
        save("world_unseen")
        bpy.ops.wm.open_mainfile(filepath=out + "/car.blend")
        bpy.context.scene.world.cycles_visibility.diffuse = False
        save("world_unlit")
    """)
    out = tmp_path_factory.mktemp("lamp_settings")
    root = Path(__file__).resolve().parents[1]
    subprocess.run([sys.executable, str(root / "blend_scenes" / "build.py"), "--only", "car", "--out", str(out)],
                   check=True, capture_output=True)
    return cornell_variants(out, script)


# (scene, pass, extra Cycles settings, rel L1 bound). Measured after: portal DD 0.025, no_shadow
# DD 0.019, spread DD 0.14 (its cone's edge on the floor carries Cycles' 64-spp noise), spread0
# DD 0.12 (mean +3%; before the beam it was black), film_exposure (Cycles' Film > Exposure 2)
# Combined 0.071 (0.499 before: HybridGI ignored it); the car
# under its sky with 0 diffuse bounces, Combined 0.012 (AO-only quality, the first mapping, lost
# the sky's direct light: Diffuse Direct mean 0.572 vs 0.917).
@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.parametrize(("name", "pass_name", "cycles_extra", "max_l1"), [
    ("portal", "Diffuse Direct", (), 0.06),
    ("no_shadow", "Diffuse Direct", (), 0.06),
    ("spread", "Diffuse Direct", (), 0.25),
    ("spread0", "Diffuse Direct", (), 0.25),
    ("film_exposure", "Combined", (), 0.1),
    ("bounces0", "Combined", ("--set", "cycles.diffuse_bounces=0"), 0.08),
])
def test_lamp_settings_match_cycles(scenes, tmp_path, name, pass_name, cycles_extra, max_l1):
    from tests.cli_renders import layer, rendered

    ours = rendered(scenes / f"{name}.blend", tmp_path / "hg", RES, *QUICK)
    cycles = rendered(scenes / f"{name}.blend", tmp_path / "cy", RES, *CYCLES, *cycles_extra)
    geometry = layer(cycles, "Depth", "Z")[..., 0] < 1e9
    a, b = layer(ours, pass_name)[geometry], layer(cycles, pass_name)[geometry]
    mean_error = abs(float(a.mean()) / float(b.mean()) - 1.0)
    l1 = float(np.abs(a - b).sum() / np.abs(b).sum())
    assert mean_error < 0.05 and l1 < max_l1, (mean_error, l1)
    if name == "bounces0":
        assert float(np.abs(layer(ours, "Diffuse Indirect")).max()) == 0.0


def test_blackbody_table_follows_blenders_colours():
    from hybridgi_core.blackbody import blackbody_rgb

    # Blender 5.0's Light.temperature_color at temperatures between the table's samples.
    np.testing.assert_allclose(blackbody_rgb(1000.0), [4.6014, 0.039, 0.0], atol=0.01)
    np.testing.assert_allclose(blackbody_rgb(3000.0), [1.7708, 0.8443, 0.2722], rtol=3e-3)
    np.testing.assert_allclose(blackbody_rgb(6500.0), [1.0426, 0.9841, 1.0353], rtol=3e-3)
    np.testing.assert_allclose(blackbody_rgb(12000.0), [0.8263, 0.9945, 1.5663], rtol=3e-3)
    np.testing.assert_allclose(blackbody_rgb(1e6), blackbody_rgb(20000.0))  # clamped to the range


# The car under its sky, world hidden from the camera / from diffuse rays, 64x48: before, the
# background kept the sky (Combined there 0.30-0.50 vs Cycles' 0.008) and the hidden world still
# lit (Diffuse Direct mean 0.920 vs 0.573); after, background 0.008 and 0.573 (rel L1 0.004).
@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.parametrize("name", ["world_unseen", "world_unlit"])
def test_world_ray_visibility_matches_cycles(scenes, tmp_path, name):
    from tests.cli_renders import layer, rendered

    ours = rendered(scenes / f"{name}.blend", tmp_path / "hg", RES, *QUICK)
    cycles = rendered(scenes / f"{name}.blend", tmp_path / "cy", RES, *CYCLES)
    sky = layer(cycles, "Depth", "Z")[..., 0] >= 1e9
    assert sky.any() and (~sky).any()
    combined, reference = layer(ours, "Combined", "RGBA"), layer(cycles, "Combined", "RGBA")
    np.testing.assert_allclose(combined[sky].mean(0), reference[sky].mean(0), atol=0.02)
    a, b = layer(ours, "Diffuse Direct")[~sky], layer(cycles, "Diffuse Direct")[~sky]
    assert abs(float(a.mean()) / float(b.mean()) - 1.0) < 0.03


@pytest.mark.blender
def test_world_visibility_and_light_path_are_read(bpy_module, empty_scene, sync, caplog):
    bpy, scene = bpy_module, empty_scene
    world = bpy.data.worlds.new("w")
    world.color = (0.2, 0.3, 0.4)
    scene.world = world
    seen = sync.read_world(world)[0].color  # Blender 5.0's new worlds have a node tree (grey 0.05)
    assert seen.any()
    world.cycles_visibility.camera = False
    found, _ = sync.read_world(world)
    np.testing.assert_allclose(found.color, seen)
    assert not found.background_color.any()
    world.cycles_visibility.camera, world.cycles_visibility.diffuse = True, False
    with caplog.at_level(logging.WARNING):
        found, lamps = sync.read_world(world)
    assert not found.any and not lamps
    np.testing.assert_allclose(found.background_color, seen)
    assert any("hidden from diffuse rays only" in r.getMessage() for r in caplog.records)
    world.cycles_visibility.diffuse = True
    if world.node_tree is None:  # before 5.0
        world.use_nodes = True
    tree = world.node_tree
    mix = tree.nodes.new("ShaderNodeMixShader")
    # Is Camera Ray is followed (tests/test_artist_scenes.py); Is Diffuse Ray differs between
    # Cycles' lamp sampling and bounce rays: named.
    tree.links.new(tree.nodes.new("ShaderNodeLightPath").outputs["Is Diffuse Ray"], mix.inputs[0])
    caplog.clear()
    with caplog.at_level(logging.WARNING):
        sync.read_world(world)
    assert sum("Light Path" in r.getMessage() and "Is Diffuse Ray" in r.getMessage() for r in caplog.records) == 1


@pytest.mark.blender
@pytest.mark.slow
def test_a_sky_textures_sun_is_as_wide_as_the_node_draws_it(bpy_module, empty_scene, sync, tmp_path, monkeypatch):
    """A Sky Texture is baked (through Cycles) to a map of ~0.7 degree texels, in which its
    0.545 degree sun disc spreads over several: read from the map alone, the sun lamp came out
    1.56 degrees wide and its shadows three times as soft as Cycles' (sky_yard 640x360: Combined
    0.0141 -> 0.0121 with the node's size). Its direction stays the map's (within 0.1 degree)."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # the bake runs, never read from an earlier one
    world, sky = _sky_world(bpy_module, empty_scene, "sky", sun_disc=True, sun_size=math.radians(0.545),
                            sun_elevation=0.3, sun_rotation=1.0)
    _, lamps = sync.read_world(world)
    assert len(lamps) == 1
    sun = lamps[0]
    assert sun.angle == pytest.approx(math.radians(0.545), rel=1e-6)
    elevation = math.degrees(math.asin(float(sun.matrix[2, 2])))
    assert elevation == pytest.approx(math.degrees(0.3), abs=0.2)
    sky.sun_disc = False  # no disc: the node's size is not used (the glow around the sun is what the map shows)
    assert all(lamp.angle > math.radians(2.0) for lamp in sync.read_world(world)[1])


@pytest.mark.blender
@pytest.mark.slow
def test_a_final_sync_starts_its_worlds_bake_first_and_bakes_it_once(bpy_module, empty_scene, sync, tmp_path,
                                                                      monkeypatch):
    """A final render's sync starts the world's bake before it reads the meshes
    (`sync.start_world_bakes`), so Blender renders the map while the meshes are read and the
    materials baked; reading the world then waits for that bake instead of running another."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))  # the bake runs, never read from an earlier one
    world, _sky = _sky_world(bpy_module, empty_scene, "early sky", sun_elevation=0.4, sun_rotation=2.0)
    bake = sync.world_bake
    runs = []
    real_run = bake._run
    monkeypatch.setattr(bake, "_run", lambda *args: runs.append(args[-1]) or real_run(*args))
    sync.start_world_bakes(world)
    assert bake.STORE.running(bake.world_key(world, "camera"))  # a Cycles process: not done in microseconds
    _, lamps = sync.read_world(world)
    assert len(runs) == 1
    assert len(lamps) == 1  # the map's sun, from the early bake
    elevation = math.degrees(math.asin(float(lamps[0].matrix[2, 2])))
    assert elevation == pytest.approx(math.degrees(0.4), abs=0.2)
    sync.start_world_bakes(world)  # baked: nothing starts
    assert not bake.STORE.running(bake.world_key(world, "camera")) and len(runs) == 1


def _sky_world(bpy, scene, name, **properties):
    """(the world, its Sky Texture node) of a new world `name` whose Background shows a Sky
    Texture with these node properties, made the scene's world."""
    world = bpy.data.worlds.new(name)
    if world.node_tree is None:  # before 5.0
        world.use_nodes = True
    tree = world.node_tree
    sky = tree.nodes.new("ShaderNodeTexSky")
    for key, value in properties.items():
        setattr(sky, key, value)
    tree.links.new(sky.outputs["Color"], tree.nodes["Background"].inputs["Color"])
    scene.world = world
    return world, sky
