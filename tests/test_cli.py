"""The `hybridgi` command (run as a subprocess so each run has its own bpy), the dev install, and the
engine's error record the command relies on (in-process, with a stand-in pipeline)."""

from __future__ import annotations

import importlib
import json
import logging
import os
import struct
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from hybridgi_cli import blender_compat, exr

REPO = Path(__file__).resolve().parents[1]
SCENES = Path(__file__).resolve().parents[2] / "shared" / "scenes"
CORNELL = SCENES / "cornell_mcguire.blend"

#: Passes every engine must write, with their channels (Cycles' names).
PASSES = {
    "Combined": "RGBA",
    "Diffuse Direct": "RGB",
    "Diffuse Indirect": "RGB",
    "Diffuse Color": "RGB",
    "Ambient Occlusion": "RGB",
    "Depth": "Z",
    "Normal": "XYZ",
}


def hybridgi(*args: str, timeout: float = 120) -> subprocess.CompletedProcess:
    script = Path(sys.executable).with_name("hybridgi")
    command = [str(script)] if script.exists() else [sys.executable, "-m", "hybridgi_cli.main"]
    env = dict(os.environ)
    env.pop("BLENDER_USER_RESOURCES", None)  # the command makes (and removes) its own
    return subprocess.run([*command, *args], capture_output=True, text=True, timeout=timeout, env=env, cwd=REPO)


def png_size(path: Path) -> tuple[int, int]:
    header = path.read_bytes()[:24]
    assert header[:8] == b"\x89PNG\r\n\x1a\n"
    return struct.unpack(">II", header[16:24])


@pytest.fixture(scope="module")
def cornell(tmp_path_factory) -> tuple[Path, float]:
    """(a Cornell box this Blender opens, its highest albedo): the shared one (McGuire's), else the
    bundled one built here (Blender 4.2 cannot read files saved by 5.0; the shared ones may be absent)."""
    if CORNELL.exists() and blender_compat.opens_here(CORNELL):
        return CORNELL, 0.725
    out = tmp_path_factory.mktemp("scenes")
    env = {k: v for k, v in os.environ.items() if k != "BLENDER_USER_RESOURCES"}
    subprocess.run([sys.executable, str(REPO / "blend_scenes" / "build.py"), "--only", "cornell", "--out", str(out)],
                   check=True, capture_output=True, timeout=120, env=env, cwd=REPO)
    return out / "cornell.blend", 0.8


VOLUME_SCENE = """
import sys, bpy
bpy.ops.wm.read_factory_settings(use_empty=True)
scene = bpy.context.scene
bpy.ops.object.camera_add(location=(0, -6, 1), rotation=(1.45, 0, 0))
scene.camera = bpy.context.object
bpy.ops.object.light_add(type="SUN", location=(0, 0, 5))
bpy.ops.mesh.primitive_plane_add(size=20)
bpy.ops.mesh.primitive_cube_add(size=2, location=(0, 0, 1))
material = bpy.data.materials.new("fog")
material.use_nodes = True
tree = material.node_tree
tree.nodes.remove(tree.nodes["Principled BSDF"])
volume = tree.nodes.new("ShaderNodeVolumePrincipled")
tree.links.new(volume.outputs[0], tree.nodes["Material Output"].inputs["Volume"])
bpy.context.object.data.materials.append(material)
scene.world = bpy.data.worlds.new("haze")
scene.world.use_nodes = True
tree = scene.world.node_tree
haze = tree.nodes.new("ShaderNodeVolumePrincipled")
haze.inputs["Density"].default_value = 0.02
tree.links.new(haze.outputs[0], tree.nodes["World Output"].inputs["Volume"])
bpy.ops.wm.save_as_mainfile(filepath=sys.argv[-1])
"""


def test_cycles_volume_scene_writes_with_a_warning(tmp_path):
    """Cycles leaves NaN in its own Diffuse Color where a volume fills a pixel: the peer render is
    written (Combined is finite) and the channels named in a warning, not refused."""
    blend = tmp_path / "volume.blend"
    env = {k: v for k, v in os.environ.items() if k != "BLENDER_USER_RESOURCES"}
    subprocess.run([sys.executable, "-c", VOLUME_SCENE, str(blend)], check=True, capture_output=True, timeout=120,
                   env=env)
    run = hybridgi("render", str(blend), "--out", str(tmp_path / "v"), "--engine", "CYCLES", "--samples", "2",
                   "--res", "64x36")
    assert run.returncode == 0, run.stderr[-2000:]
    channels = exr.read_channels(tmp_path / "v_0001.exr")
    assert np.isfinite(channels["ViewLayer.Combined.R"]).all()
    # Blender 5.0's Cycles leaves the NaN (4.2, 4.5 and 5.3 do not): named, not refused.
    if not np.isfinite(channels["ViewLayer.Diffuse Color.R"]).all():
        assert "warning: frame 1: CYCLES left non-finite pixels in ViewLayer.Diffuse Color" in run.stderr


def test_cycles_render_writes_png_exr_and_json(tmp_path, cornell):
    blend, albedo = cornell
    run = hybridgi(
        "render", str(blend), "--out", str(tmp_path / "cb"),
        "--engine", "CYCLES", "--samples", "4", "--res", "64x48", "--frames", "1",
    )
    assert run.returncode == 0, run.stderr[-2000:]

    lines = run.stdout.splitlines()
    assert len(lines) == 1  # Blender's own output went to stderr
    record = json.loads(lines[0])
    assert record["frame"] == 1 and record["engine"] == "CYCLES"
    assert (record["width"], record["height"]) == (64, 48)
    assert record["steps_ms"] == {} and record["seconds"] > 0
    assert png_size(Path(record["png"])) == (64, 48)

    channels = exr.read_channels(record["exr"])
    for name, chans in PASSES.items():
        for c in chans:
            key = f"ViewLayer.{name}.{c}"
            assert key in channels, f"{key} missing from {sorted(channels)}"
            assert channels[key].shape == (48, 64)
    # The values are the passes', not placeholders: an opaque render lit by the ceiling, the box's
    # albedos in Diffuse Color, unit normals, positive depth.
    assert np.all(channels["ViewLayer.Combined.A"] == 1.0)
    assert channels["ViewLayer.Diffuse Direct.R"].mean() > 0.1
    assert channels["ViewLayer.Diffuse Indirect.G"].mean() > 0.01
    assert 0.0 <= channels["ViewLayer.Diffuse Color.R"].min() and channels["ViewLayer.Diffuse Color.R"].max() <= albedo + 0.005
    normal = np.stack([channels[f"ViewLayer.Normal.{c}"] for c in "XYZ"], axis=-1)
    # Unit length on geometry except where pixel filtering averages normals across an edge (or
    # with the background: the bundled box is open towards the camera).
    geometry = channels["ViewLayer.Depth.Z"] < 1e9
    assert geometry.mean() > 0.3
    assert np.mean(np.abs(np.linalg.norm(normal[geometry], axis=-1) - 1.0) < 1e-3) > 0.7
    assert channels["ViewLayer.Depth.Z"].min() > 0.0


@pytest.mark.smoke
def test_check_registers_the_engine_from_this_checkout():
    run = hybridgi("check")
    assert run.returncode == 0, run.stderr[-2000:]
    record = json.loads(run.stdout)
    assert record["engine_registered"] is True
    assert record["addon"] == "bl_ext.hybridgi_dev.hybridgi"
    assert Path(record["path"]) == REPO / "addon"


REGISTERED_MODULES = """
import json, sys
sys.path.insert(0, sys.argv[1])
import bpy
from hybridgi_cli import dev_install
addon = dev_install.enable()
print(json.dumps({name: f"{addon.__name__}.{name}" in sys.modules for name in ("pipeline", "viewport")}))
"""


def test_registering_imports_the_pipeline_and_viewport_before_the_first_render():
    # A module first imported by a render is imported (and compiled, without cached bytecode) in its seconds.
    env = dict(os.environ)
    env.pop("BLENDER_USER_RESOURCES", None)
    run = subprocess.run([sys.executable, "-c", REGISTERED_MODULES, str(REPO)], capture_output=True, text=True,
                         timeout=120, env=env, cwd=REPO)
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads(run.stdout.strip().splitlines()[-1]) == {"pipeline": True, "viewport": True}


def test_a_pipeline_that_fails_to_import_at_registration_is_logged_not_raised(addon, monkeypatch, caplog):
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")

    def broken():
        raise ImportError("no module named embreex")

    monkeypatch.setattr(engine_mod, "_pipeline", broken)
    with caplog.at_level(logging.WARNING, logger=engine_mod.log.name):
        engine_mod._preload()
    assert "pipeline module did not import at registration: no module named embreex" in caplog.text


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["render", "missing.blend", "--out", "x"], "scene not found"),
        (["render", str(CORNELL), "--out", "x", "--res", "64by48"], "resolution must be WxH"),
        (["render", str(CORNELL), "--out", "x", "--frames", "5-2"], "ends before it starts"),
        (["render", str(CORNELL), "--out", "x", "--set", "resolution"], "needs NAME=VALUE"),
        (["render", str(CORNELL)], "--out"),
    ],
)
def test_bad_arguments_exit_2_with_a_message(args, message):
    run = hybridgi(*args)
    assert run.returncode == 2
    assert message in run.stderr
    assert run.stdout == ""


def test_unknown_setting_exits_1(tmp_path, cornell):
    run = hybridgi("render", str(cornell[0]), "--out", str(tmp_path / "x"), "--engine", "CYCLES", "--set", "bogus=1")
    assert run.returncode == 1
    assert "cycles has no writable setting 'bogus'" in run.stderr
    assert not list(tmp_path.iterdir())


# --- in-process: the add-on's engine and the CLI's settings parser ----------------------------


@pytest.fixture(scope="module")
def addon(bpy_module):
    from hybridgi_cli import dev_install

    package = dev_install.enable()
    assert dev_install.enable() is package  # idempotent
    assert dev_install.engine_registered()
    return package


class FakeEngine:
    """Records what the engine reports; stands in for a RenderEngine outside a render job."""

    def __init__(self):
        self.errors = []
        self.reports = []
        self.passes = []

    def error_set(self, message):
        self.errors.append(message)

    def report(self, kind, message):
        self.reports.append((set(kind), message))

    def register_pass(self, scene, layer, name, channels, chan_ids, kind):
        self.passes.append((name, channels, chan_ids, kind))


@pytest.fixture
def fake_pipeline(addon, monkeypatch):
    pipeline = types.ModuleType(f"{addon.__name__}.pipeline")
    monkeypatch.setitem(sys.modules, pipeline.__name__, pipeline)
    monkeypatch.setattr(addon, "pipeline", pipeline, raising=False)  # `from . import pipeline` reads it
    return pipeline


def test_engine_records_pipeline_errors(addon, fake_pipeline):
    from hybridgi_cli import main as cli
    from hybridgi_core.errors import EmptySceneError

    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    assert engine_mod.errors.EmptySceneError is EmptySceneError  # the add-on imports the core by its name

    def empty(engine, depsgraph):
        raise EmptySceneError("the scene has no triangles")

    fake_pipeline.render_frame = empty
    engine = FakeEngine()
    engine_mod.render_frame(engine, depsgraph=None)
    assert engine_mod.LAST_ERROR == "the scene has no triangles"
    assert engine.errors == ["the scene has no triangles"]
    assert engine.reports == [({"ERROR"}, "the scene has no triangles")]
    assert cli.frame_error(addon) == "the scene has no triangles"

    def broken(engine, depsgraph):
        raise ZeroDivisionError("bug")

    fake_pipeline.render_frame = broken
    with pytest.raises(ZeroDivisionError):  # re-raised so Blender prints the traceback
        engine_mod.render_frame(FakeEngine(), depsgraph=None)
    assert engine_mod.LAST_ERROR == "internal error: ZeroDivisionError: bug"

    def works(engine, depsgraph):
        fake_pipeline.LAST_STATS = {"steps_ms": {"gbuffer": 1.5, "update": 12}, "rays": 5}

    fake_pipeline.render_frame = works
    engine_mod.render_frame(FakeEngine(), depsgraph=None)
    assert engine_mod.LAST_ERROR is None
    assert cli.pipeline_stats(addon)["steps_ms"] == {"gbuffer": 1.5, "update": 12.0}


def test_engine_registers_only_enabled_passes(addon, empty_scene):
    engine_mod = importlib.import_module(f"{addon.__name__}.engine")
    layer = empty_scene.view_layers[0]
    for flag in ("use_pass_z", "use_pass_normal", "use_pass_diffuse_direct", "use_pass_diffuse_indirect",
                 "use_pass_diffuse_color", "use_pass_ambient_occlusion"):
        setattr(layer, flag, False)
    layer.use_pass_diffuse_indirect = True
    layer.use_pass_ambient_occlusion = True
    fake = FakeEngine()
    engine_mod.HybridGIRenderEngine.update_render_passes(fake, empty_scene, layer)
    name = blender_compat.cycles_pass_name  # DiffInd, AO ... before Blender 5.0
    assert [p[0] for p in fake.passes] == ["Combined", name("Diffuse Indirect"), name("Ambient Occlusion")]
    assert fake.passes[2] == (name("Ambient Occlusion"), 3, "RGB", "COLOR")

    for flag in ("use_pass_z", "use_pass_normal", "use_pass_diffuse_direct", "use_pass_diffuse_color"):
        setattr(layer, flag, True)
    fake = FakeEngine()
    engine_mod.HybridGIRenderEngine.update_render_passes(fake, empty_scene, layer)
    assert {p[0]: (p[1], p[2]) for p in fake.passes} == {name(n): (len(ch), ch) for n, ch in PASSES.items()}


def test_set_assigns_typed_values(addon, empty_scene):
    from hybridgi_cli import main as cli

    scene = empty_scene
    cli.assign(scene, "resolution", "16", "HYBRIDGI")
    cli.assign(scene, "sh_order", "L1", "HYBRIDGI")
    cli.assign(scene, "hybridgi.hysteresis", "0.5", "CYCLES")
    cli.assign(scene, "cycles.samples", "7", "HYBRIDGI")
    cli.assign(scene, "render.film_transparent", "true", "CYCLES")
    assert (scene.hybridgi.resolution, scene.hybridgi.sh_order) == (16, "L1")
    assert scene.hybridgi.hysteresis == pytest.approx(0.5)
    assert scene.cycles.samples == 7 and scene.render.film_transparent is True
    with pytest.raises(cli.CliError, match="expected true or false"):
        cli.assign(scene, "render.film_transparent", "maybe", "CYCLES")
    with pytest.raises(cli.CliError, match="sh_order"):
        cli.assign(scene, "sh_order", "L7", "HYBRIDGI")
    with pytest.raises(cli.CliError, match="no writable setting"):
        cli.assign(scene, "nonsense", "1", "HYBRIDGI")


class FakeLayout:
    """Checks every property a panel draws exists on the data it names."""

    def __init__(self):
        self.drawn = []
        self.use_property_split = False
        self.use_property_decorate = True

    def column(self, **_kwargs):
        return self

    row = column

    def prop(self, data, name, **_kwargs):
        assert name in data.bl_rna.properties, f"{type(data).__name__} has no property {name!r}"
        self.drawn.append(name)

    def label(self, **_kwargs):
        pass


def test_panels_draw_every_setting(addon, empty_scene):
    ui = importlib.import_module(f"{addon.__name__}.ui")
    properties = importlib.import_module(f"{addon.__name__}.properties")
    scene = empty_scene
    scene.world = scene.world or importlib.import_module("bpy").data.worlds.new("w")
    context = types.SimpleNamespace(scene=scene, view_layer=scene.view_layers[0], engine="HYBRIDGI")
    drawn = set()
    for panel in ui.classes:
        assert panel.poll(context)
        assert not panel.poll(types.SimpleNamespace(engine="CYCLES"))
        layout = FakeLayout()
        panel.draw(types.SimpleNamespace(layout=layout), context)
        assert layout.use_property_split
        drawn.update(layout.drawn)
    settings = set(properties.HybridGISettings.__annotations__)
    assert settings <= drawn, f"not in any panel: {settings - drawn}"
    # Built-in panels shared with the engine exist in this Blender and list it while enabled.
    import bpy

    assert all(hasattr(bpy.types, name) for name in ui.EXTRA_PANELS)
    assert all("HYBRIDGI" in panel.COMPAT_ENGINES for panel in ui.builtin_panels())
    assert "HYBRIDGI" in bpy.types.RENDER_PT_color_management.COMPAT_ENGINES
    assert "HYBRIDGI" not in bpy.types.DATA_PT_light.COMPAT_ENGINES


def test_unregister_mirrors_register(addon, empty_scene):
    import bpy

    from hybridgi_cli import dev_install

    try:
        dev_install.disable()
        assert not dev_install.engine_registered()
        assert not hasattr(empty_scene, "hybridgi")
        assert "HYBRIDGI" not in bpy.types.RENDER_PT_color_management.COMPAT_ENGINES
        assert not hasattr(bpy.types, "HYBRIDGI_PT_cache")
    finally:
        dev_install.enable()  # leave it as the module fixture promised
    assert dev_install.engine_registered() and hasattr(empty_scene, "hybridgi")


def test_engine_render_writes_registered_passes_to_exr(addon, fake_pipeline, empty_scene, tmp_path):
    """A real render job through the HYBRIDGI engine with a stand-in pipeline that fills each pass
    with its index, saved by the CLI's writer and read back."""
    import bpy

    from hybridgi_cli import main as cli

    scene = empty_scene
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.render.engine = "HYBRIDGI"
    scene.render.resolution_x, scene.render.resolution_y, scene.render.resolution_percentage = 8, 6, 100
    for flag in cli.PASS_FLAGS:
        setattr(scene.view_layers[0], flag, True)
    filled = []

    def fill(engine, depsgraph):
        result = engine.begin_result(0, 0, 8, 6)
        for i, render_pass in enumerate(result.layers[0].passes):
            render_pass.rect.foreach_set(np.full(8 * 6 * render_pass.channels, i + 1, np.float32))
            filled.append(render_pass.name)
        engine.end_result(result)

    fake_pipeline.render_frame = fill
    bpy.ops.render.render()
    assert importlib.import_module(f"{addon.__name__}.engine").LAST_ERROR is None
    cli.save(bpy, scene, tmp_path / "f.png", tmp_path / "f.exr")

    channels = exr.read_channels(tmp_path / "f.exr")  # by Blender 5.0's pass names
    current = {blender_compat.cycles_pass_name(name): name for name in PASSES}
    assert set(filled) == set(current)
    for i, name in enumerate(filled):
        for c in PASSES[current[name]]:
            assert np.all(channels[f"ViewLayer.{current[name]}.{c}"] == i + 1), name
    assert png_size(tmp_path / "f.png") == (8, 6)
