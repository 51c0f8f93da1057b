"""Shared fixtures. bpy is imported once per process, lazily, only by tests that ask for it."""

from __future__ import annotations

import importlib
import os
import tempfile

import pytest

_BPY = None


def _import_bpy():
    global _BPY
    if _BPY is None:
        # Must be set before the first `import bpy`: keeps the user's Blender config untouched.
        os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="hybridgi_bl_"))
        try:
            import bpy  # noqa: PLC0415
        except ImportError:
            pytest.skip("the bpy module is not installed")
        _BPY = bpy
    return _BPY


@pytest.fixture(scope="session")
def bpy_module():
    """The bpy module (skips the test where it is not installed)."""
    return _import_bpy()


@pytest.fixture(scope="session")
def gpu_context(bpy_module):
    """Makes Blender create its GPU context in background mode (a tiny Workbench render)."""
    bpy = bpy_module
    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.render.resolution_x = 8
    scene.render.resolution_y = 8
    scene.render.resolution_percentage = 100
    cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    bpy.ops.render.render()
    import gpu  # noqa: PLC0415

    return gpu


@pytest.fixture(scope="module")
def addon(bpy_module):
    """The add-on package, enabled from this checkout (imports it the way Blender does); a test
    module may define its own (with handlers registered, say)."""
    from hybridgi_cli import dev_install  # noqa: PLC0415

    return dev_install.enable()


@pytest.fixture(scope="module")
def sync(addon):
    """The add-on's `sync` module: the one reader of Blender data."""
    return importlib.import_module(f"{addon.__name__}.sync")


@pytest.fixture
def empty_scene(bpy_module):
    """A fresh empty file; returns its scene."""
    bpy_module.ops.wm.read_homefile(use_empty=True)
    return bpy_module.context.scene


def pytest_sessionfinish(session, exitstatus):
    session.config._hybridgi_exitstatus = int(exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    """Leave without finalizing Python once bpy was imported.

    The bpy module tears its GPU context down before Python frees the `gpu` objects that modules
    still cache (shaders, batches): finalizing after that segfaults (exit 139) although every
    test passed and was reported. This runs after the summary line and every other plugin.
    """
    import sys  # noqa: PLC0415

    if "bpy" in sys.modules:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(getattr(config, "_hybridgi_exitstatus", 0))
