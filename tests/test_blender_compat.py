"""hybridgi_cli/blender_compat.py's bpy-free half: versions, scene folders, pass names."""

from __future__ import annotations

import re

import pytest

from hybridgi_cli import blender_compat, exr


def test_version_of_the_installed_bpy_without_importing_it():
    major, minor = blender_compat.blender_version()
    assert (major, minor) >= (4, 2)


def test_scenes_of_the_default_blender_in_blend_scenes_others_beside_them():
    root = blender_compat.ROOT / "blend_scenes"
    assert blender_compat.scenes_dir(blender_compat.DEFAULT_BLENDER) == root
    assert blender_compat.scenes_dir((4, 2)) == root / "blender-4.2"
    assert blender_compat.scenes_dir((5, 3)) == root / "blender-5.3"


@pytest.mark.parametrize(("version", "expected"), [((4, 2), "DiffInd"), ((4, 5), "DiffInd"), ((5, 0), "Diffuse Indirect"),
                                                   ((5, 3), "Diffuse Indirect")])
def test_cycles_pass_names_per_version(version, expected):
    assert blender_compat.cycles_pass_name("Diffuse Indirect", version) == expected
    assert blender_compat.cycles_pass_name("Normal", version) == "Normal"
    assert blender_compat.cycles_pass_name("Ambient Occlusion", version) == ("AO" if version < (5, 0) else "Ambient Occlusion")


def test_exr_reader_gives_legacy_passes_their_current_names():
    assert exr._current_name("ViewLayer.DiffDir.R") == "ViewLayer.Diffuse Direct.R"
    assert exr._current_name("ViewLayer.AO.G") == "ViewLayer.Ambient Occlusion.G"
    # The glossy passes too (Blender 4.x's GlossDir, GlossInd, GlossCol: the full suite on 4.5
    # failed five glossy tests on a missing 'Glossy Color').
    assert exr._current_name("ViewLayer.GlossCol.R") == "ViewLayer.Glossy Color.R"
    assert exr._current_name("ViewLayer.GlossInd.B") == "ViewLayer.Glossy Indirect.B"
    assert blender_compat.cycles_pass_name("Glossy Direct", (4, 5)) == "GlossDir"
    assert exr._current_name("ViewLayer.Diffuse Color.B") == "ViewLayer.Diffuse Color.B"
    assert exr._current_name("ViewLayer.Depth.Z") == "ViewLayer.Depth.Z"


def test_setup_makefile_and_compat_agree_on_the_versions():
    """scripts/setup.sh's table, the Makefile's default and DEFAULT_BLENDER name the same versions."""
    setup = (blender_compat.ROOT / "scripts" / "setup.sh").read_text()
    makefile = (blender_compat.ROOT / "Makefile").read_text()
    versions = set(re.findall(r"^\s+(\d\.\d)\) BPY=", setup, re.M))
    assert versions == {"4.2", "4.5", "5.0", "5.3"}
    default = ".".join(map(str, blender_compat.DEFAULT_BLENDER))
    assert f"DEFAULT_BLENDER := {default}" in makefile and f'BLENDER="${{BLENDER:-{default}}}"' in setup
