"""The installable extension zips of `make extension` (scripts/build_extension.py).

Builds (or reuses) one zip per platform, checks each with Blender's validator and holds exactly its
platform's wheels plus the core's, then installs the linux-x64 zip into the bpy module in a fresh
process, with a throw-away Blender user folder and the checkout's `hybridgi_core` hidden, so what
registers and renders is the core wheel the zip brings, and renders one small frame with HYBRIDGI.
"""

from __future__ import annotations

import importlib.util
import io
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

pytestmark = [pytest.mark.slow, pytest.mark.blender]

REPO = Path(__file__).resolve().parents[1]
PLATFORMS = ("linux-x64", "windows-x64", "macos-arm64", "macos-x64")
#: Distinctive parts of the wheel platform tags each Blender platform may hold.
WHEEL_TAGS = {
    "linux-x64": ("manylinux", "_x86_64"),
    "windows-x64": ("win_amd64", "win_amd64"),
    "macos-arm64": ("macosx_", "_arm64"),
    "macos-x64": ("macosx_", "_x86_64"),
}
BUNDLED = {"embreex": "4.4.0.post1", "fast_simplification": "0.2.0"}
PYTHON_TAGS = {"cp311", "cp313"}
RESOLUTION = (64, 48)
CORE_VERSION = "0.1.0"  # hybridgi_core.__version__


def _load_builder():
    spec = importlib.util.spec_from_file_location("build_extension", REPO / "scripts" / "build_extension.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses looks the module up by name
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def builder():
    if importlib.util.find_spec("bpy") is None:
        pytest.skip("the bpy module (which ships Blender's extension tool) is not installed")
    return _load_builder()


@pytest.fixture(scope="module")
def zips(builder):
    """{platform: PlatformZip}, built into dist/ or reused when dist/ is up to date."""
    try:
        items = builder.build()
    except builder.WheelsUnavailable as err:
        pytest.skip(f"PyPI is unreachable and build/wheels/ holds no cached wheels: {str(err).splitlines()[0]}")
    return {item.platform: item for item in items}


def test_one_valid_zip_per_platform_with_only_its_wheels(builder, zips):
    assert sorted(zips) == sorted(PLATFORMS)  # no linux-arm64: embreex has no wheel for it
    tool = builder.blender_ext_tool()
    for platform, item in zips.items():
        assert item.path.name == f"hybridgi-0.1.0-{platform.replace('-', '_')}.zip"
        output = builder.check_zip(item, tool)  # Blender's `validate`, then contents; raises if wrong
        assert "Success" in output, output
        with zipfile.ZipFile(item.path) as archive:
            names = archive.namelist()
        wheels = [n.removeprefix("wheels/") for n in names if n.endswith(".whl")]
        # Both bundled packages for both Pythons, nothing else (no numpy: Blender ships it).
        core = f"hybridgi_core-{CORE_VERSION}-py3-none-any.whl"
        assert core in wheels, wheels  # the core, pure Python, in every zip
        wheels.remove(core)
        found = {(w.split("-")[0], w.split("-")[1], w.split("-")[-3]) for w in wheels}
        assert found == {(n, v, py) for n, v in BUNDLED.items() for py in PYTHON_TAGS}, wheels
        assert len(wheels) == len(found)
        head, tail = WHEEL_TAGS[platform]
        for wheel in wheels:
            tag = wheel.removesuffix(".whl").split("-")[-1]
            assert tag.startswith(head) and tag.endswith(tail), f"{wheel} in the {platform} zip"
        # The add-on at the zip's root; the core only as its wheel, with its shaders inside.
        assert "__init__.py" in names and not any(n.startswith("hybridgi_core/") for n in names)
        with zipfile.ZipFile(item.path) as archive, zipfile.ZipFile(io.BytesIO(archive.read(f"wheels/{core}"))) as wheel:
            inside = wheel.namelist()
        assert "hybridgi_core/__init__.py" in inside and "hybridgi_core/session.py" in inside
        assert any(n.startswith("hybridgi_core/raster/") and n.endswith(".glsl") for n in inside)
        assert "hybridgi_core/specular_tables.npz" in inside  # else every render computes them (~0.6 s)
        assert not any("__pycache__" in n or n.startswith("tests/") for n in names + inside)


def test_core_wheel_is_reproducible(builder, tmp_path):
    """Equal sources give byte-equal wheels (the zips' digests stay stable across machines)."""
    first = builder.core_wheel(tmp_path / "a").read_bytes()
    second = builder.core_wheel(tmp_path / "b").read_bytes()
    assert first == second
    with zipfile.ZipFile(io.BytesIO(first)) as wheel:
        record = wheel.read(f"hybridgi_core-{CORE_VERSION}.dist-info/RECORD").decode()
        assert wheel.testzip() is None
    assert "hybridgi_core/changes.py,sha256=" in record


#: Runs in a fresh Python: argv = zip, output folder. Writes result.json there.
INSTALL_AND_RENDER = r'''
import importlib.abc
import importlib.machinery
import json
import os
import sys
from pathlib import Path

#: Where Blender unpacks extension wheels for this Python.
WHEEL_SITE = (
    Path(os.environ["BLENDER_USER_RESOURCES"]) / "extensions" / ".local" / "lib"
    / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
)
WHEEL_MODULES = {"embreex", "fast_simplification", "hybridgi_core"}


class ExtensionOnly(importlib.abc.MetaPathFinder):
    """The venv holds the checkout's hybridgi_core (editable install), embreex and
    fast_simplification: take all three from the wheels Blender unpacked, so what runs is what
    the zip brings, as in a Blender that has none of them."""

    def find_spec(self, name, path=None, target=None):
        if name in WHEEL_MODULES:
            spec = importlib.machinery.PathFinder.find_spec(name, [str(WHEEL_SITE)])
            if spec is None:
                raise ModuleNotFoundError(f"{name} is not among the extension's wheels", name=name)
            return spec
        return None


sys.meta_path.insert(0, ExtensionOnly())
zip_path, out = Path(sys.argv[1]), Path(sys.argv[2])
result = {}


def save():
    (out / "result.json").write_text(json.dumps(result, indent=1))


import bpy  # first: it puts Blender's script folders (addon_utils) on sys.path
import addon_utils
import numpy as np

from hybridgi_cli import blender_compat  # the version differences of code outside the add-on

bpy.ops.wm.read_homefile(use_empty=True)
bpy.ops.extensions.package_install_files(filepath=str(zip_path), repo="user_default", enable_on_install=True)
module_name = "bl_ext.user_default.hybridgi"
repo_dir = Path(bpy.utils.user_resource("EXTENSIONS", path="user_default"))
ext_dir = repo_dir / "hybridgi"
site = Path(bpy.utils.user_resource("EXTENSIONS")) / ".local" / "lib"
site = site / f"python{sys.version_info[0]}.{sys.version_info[1]}" / "site-packages"
assert site == WHEEL_SITE, (site, WHEEL_SITE)
result["ext_dir"] = str(ext_dir)
result["wheel_site"] = str(site)
result["enabled"] = addon_utils.check(module_name)[1]
result["engine_registered"] = any(
    getattr(cls, "bl_idname", None) == "HYBRIDGI" and cls.is_registered
    for cls in bpy.types.RenderEngine.__subclasses__()
)
result["core_file"] = getattr(sys.modules.get("hybridgi_core"), "__file__", None)
result["wheels_installed"] = sorted(p.name for p in site.glob("*") if not p.name.endswith(".dist-info")) if site.is_dir() else []
result["has_pipeline"] = (ext_dir / "pipeline.py").is_file()
save()

if result["engine_registered"] and result["has_pipeline"]:
    from mathutils import Vector

    scene = bpy.context.scene
    bpy.ops.mesh.primitive_plane_add(size=8.0)
    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.5))
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (0.6, 0.3, 0.0)
    scene.collection.objects.link(sun)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.location = (4.0, -4.0, 3.0)
    camera.rotation_euler = (Vector((0.0, 0.0, 0.3)) - camera.location).to_track_quat("-Z", "Y").to_euler()
    scene.collection.objects.link(camera)
    scene.camera = camera
    scene.world = bpy.data.worlds.new("world")
    scene.world.color = (0.05, 0.05, 0.05)
    scene.render.engine = "HYBRIDGI"
    scene.render.resolution_x, scene.render.resolution_y = RESOLUTION
    scene.render.resolution_percentage = 100
    bpy.ops.render.render()
    result["last_error"] = sys.modules[f"{module_name}.engine"].LAST_ERROR
    result["pipeline_file"] = sys.modules[f"{module_name}.pipeline"].__file__
    result["wheel_modules"] = {n: getattr(sys.modules.get(n), "__file__", None) for n in sorted(WHEEL_MODULES)}
    settings = scene.render.image_settings
    blender_compat.set_file_format(bpy, settings, "OPEN_EXR")
    settings.color_depth = "32"
    exr = out / "frame.exr"
    bpy.data.images["Render Result"].save_render(str(exr), scene=scene)
    image = bpy.data.images.load(str(exr))
    pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    rgb = pixels.reshape(image.size[1], image.size[0], image.channels)[..., :3]
    result["size"] = list(image.size)
    result["finite"] = bool(np.isfinite(rgb).all())
    result["mean"] = float(np.nanmean(rgb))
    result["max"] = float(np.nanmax(rgb))
    result["lit_fraction"] = float(np.mean(rgb.max(axis=-1) > 1e-3))
    save()
blender_compat.exit_now(0)  # without bpy's teardown (Blender 4.2 segfaults in it)
'''


@pytest.fixture(scope="module")
def installed(zips, tmp_path_factory):
    """What the fresh process saw after installing the linux-x64 zip (and rendering a frame)."""
    work = tmp_path_factory.mktemp("extension_install")
    user = work / "blender_user"
    user.mkdir()
    script = work / "install_and_render.py"
    script.write_text(f"RESOLUTION = {RESOLUTION!r}\n" + INSTALL_AND_RENDER)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONSTARTUP")}
    env["BLENDER_USER_RESOURCES"] = str(user)
    run = subprocess.run(
        [sys.executable, str(script), str(zips["linux-x64"].path), str(work)],
        capture_output=True, text=True, timeout=600, env=env, cwd=work,
    )
    result_file = work / "result.json"
    assert result_file.is_file(), f"the install process died ({run.returncode}):\n{run.stderr[-4000:]}"
    result = json.loads(result_file.read_text())
    result["returncode"], result["stderr"] = run.returncode, run.stderr[-4000:]
    return result


@pytest.mark.smoke
def test_installed_zip_registers_engine_with_the_core_wheel(installed):
    assert installed["enabled"], installed["stderr"]
    assert installed["engine_registered"], installed["stderr"]
    # The add-on imported `hybridgi_core` by its plain name, from the wheel Blender unpacked.
    core_file = Path(installed["core_file"])
    assert core_file == Path(installed["wheel_site"]) / "hybridgi_core" / "__init__.py", core_file
    # Blender unpacked this platform's wheels for its Python into the extensions' site-packages.
    assert {"embreex", "fast_simplification", "hybridgi_core"} <= set(installed["wheels_installed"])


@pytest.mark.smoke
def test_installed_zip_renders_a_frame(installed):
    if not installed["has_pipeline"]:
        pytest.skip("addon/pipeline.py is not written yet: the render assertion is pending")
    assert installed["returncode"] == 0, installed["stderr"]
    assert installed["last_error"] is None, installed["last_error"]
    assert Path(installed["pipeline_file"]).is_relative_to(installed["ext_dir"])
    # The frame traced with the embreex the zip brought (the venv's copy is hidden).
    embreex = installed["wheel_modules"]["embreex"]
    assert embreex and Path(embreex).is_relative_to(installed["wheel_site"]), installed["wheel_modules"]
    assert installed["size"] == list(RESOLUTION)
    assert installed["finite"]
    # Every pixel non-black (the world is 0.05 grey), and the sunlit plane far brighter than that.
    assert installed["lit_fraction"] == 1.0 and installed["max"] > 0.2, installed
