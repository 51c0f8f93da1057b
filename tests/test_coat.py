"""A Principled BSDF's Coat (car paint, varnish) is a glossy lobe of its own over the layers under
it (`specular.SpecularLayer.coat`): Cycles' coat closure (GGX, the dielectric Fresnel of the Coat
IOR) whose albedo weighs the diffuse base and the lobes beneath at the view angle, which its tint
colours. Before, only the tint was applied (a note said its reflection and layering were not
rendered): three coated spheres (red paint, brown paint, blue 70% metal) against Cycles 64 spp,
320x180: Combined 0.102 / 0.102 / 0.067 -> 0.035 / 0.039 / 0.041, Diffuse Color 0.04-0.07 ->
0.002."""

from __future__ import annotations

import pytest

from tests.cli_renders import CYCLES, QUICK, layer, pass_error, principled_sphere_scene, rendered, run_bpy

RES = "240x135"

SCENE = principled_sphere_scene("coat", {"Base Color": (0.6, 0.05, 0.05, 1), "Roughness": 0.5, "Coat Weight": 1.0,
                                         "Coat Roughness": 0.2})


@pytest.mark.blender
@pytest.mark.slow
@pytest.mark.smoke
def test_a_coated_sphere_matches_cycles(tmp_path):
    """Combined and Diffuse Color over the sphere against Cycles' (64 spp + OIDN): the coat's
    sharp reflection and its darkening of the paint beneath at grazing views are there."""
    run_bpy(SCENE, OUT=str(tmp_path))
    ours = rendered(tmp_path / "coat.blend", tmp_path / "h", RES, *QUICK)
    cycles = rendered(tmp_path / "coat.blend", tmp_path / "c", RES, *CYCLES)
    sphere = layer(cycles, "Depth", "Z")[..., 0] < 4.5
    sphere &= layer(cycles, "Diffuse Color")[..., 1] < 0.1  # the red paint, not the grey floor
    assert sphere.sum() > 2000
    errors = {name: pass_error(ours, cycles, name, sphere) for name in ("Combined", "Diffuse Color")}
    # Measured (before: only the tint) Combined 0.021 (0.284), Diffuse Color 0.002 (0.090).
    assert errors["Combined"] < 0.06 and errors["Diffuse Color"] < 0.02, errors
