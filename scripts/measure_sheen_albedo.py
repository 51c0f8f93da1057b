"""Measure Cycles' Sheen BSDF directional albedo A(mu, roughness) into hybridgi_core/sheen_albedo.npz.

Why: Cycles counts its Sheen closure (the Sheen BSDF node and the Principled BSDF's sheen layer)
as a diffuse closure whose weight is the sheen lobe's directional albedo at the view cosine mu
(the microfiber LTC model of Zeltner et al. 2022): Diffuse Color = colour x A(mu, r), and the
Principled BSDF's base under it is weighted 1 - max(sheen colour) x A. HybridGI weights the
G-buffer's diffuse colour by the same A, so the table is read from Cycles itself rather than
re-derived: per roughness, a white Sheen BSDF sphere under an orthographic camera; each pixel's
Diffuse Color over its Normal pass's cosine to the camera, averaged per mu bin.

Run with the project's venv (bpy): `.venv/bin/python scripts/measure_sheen_albedo.py`
(~1 minute on two cores). The table's grid: ROUGHNESS_SAMPLES x MU_SAMPLES, both from 0 to 1.
"""

from __future__ import annotations

import logging
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

MU_SAMPLES = 32
ROUGHNESS_SAMPLES = 17
RES = 384
OUT = ROOT / "hybridgi_core" / "sheen_albedo.npz"
log = logging.getLogger("measure_sheen_albedo")


def render_sphere(roughness: float, path: Path) -> dict:
    """Diffuse Color and Normal planes of a white Sheen BSDF sphere seen from +Z (orthographic)."""
    import bpy  # noqa: PLC0415

    from hybridgi_core import exr  # noqa: PLC0415

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 4
    scene.render.resolution_x = scene.render.resolution_y = RES
    bpy.ops.mesh.primitive_uv_sphere_add(segments=256, ring_count=128, radius=1.0)
    sphere = bpy.context.object
    bpy.ops.object.shade_smooth()
    material = bpy.data.materials.new("sheen")
    material.use_nodes = True
    tree = material.node_tree
    for node in list(tree.nodes):
        if node.bl_idname != "ShaderNodeOutputMaterial":
            tree.nodes.remove(node)
    sheen = tree.nodes.new("ShaderNodeBsdfSheen")
    sheen.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    sheen.inputs["Roughness"].default_value = roughness
    tree.links.new(sheen.outputs[0], tree.nodes["Material Output"].inputs["Surface"])
    sphere.data.materials.append(material)
    camera = bpy.data.objects.new("camera", bpy.data.cameras.new("camera"))
    camera.data.type = "ORTHO"
    camera.data.ortho_scale = 2.05
    camera.location = (0.0, 0.0, 5.0)
    scene.collection.objects.link(camera)
    scene.camera = camera
    layer = scene.view_layers[0]
    layer.use_pass_diffuse_color = True
    layer.use_pass_normal = True
    blend = path.with_suffix(".blend")
    bpy.ops.wm.save_as_mainfile(filepath=str(blend))
    from hybridgi_cli.main import main  # noqa: PLC0415

    if main(["render", str(blend), "--out", str(path), "--engine", "CYCLES", "--samples", "4",
             "--res", f"{RES}x{RES}"]) != 0:
        raise SystemExit("the Cycles render failed")
    return exr.read_channels(str(path) + "_0001.exr")


def albedo_row(channels: dict) -> np.ndarray:
    """(MU_SAMPLES,) mean Diffuse Color per cosine bin, the bins' centres at i / (MU_SAMPLES - 1)."""
    def plane(name, axes):
        key = next(k for k in channels if k.endswith(f"{name}.{axes[0]}"))[: -2]
        return np.stack([channels[f"{key}.{a}"] for a in axes], -1)

    colour = plane("Diffuse Color", "RGB").mean(-1)
    normal = plane("Normal", "XYZ")
    length = np.linalg.norm(normal, axis=-1)
    keep = (length > 0.999) & (colour > 0)
    mu = normal[..., 2][keep] / length[keep]
    grid = np.linspace(0.0, 1.0, MU_SAMPLES)
    which = np.clip(np.rint(mu * (MU_SAMPLES - 1)).astype(int), 0, MU_SAMPLES - 1)
    sums = np.bincount(which, colour[keep], MU_SAMPLES)
    counts = np.bincount(which, minlength=MU_SAMPLES)
    row = np.interp(grid, grid[counts > 0], sums[counts > 0] / counts[counts > 0])
    return row.astype(np.float32)


def main() -> None:
    roughness = np.linspace(0.0, 1.0, ROUGHNESS_SAMPLES)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, r in enumerate(roughness):
            rows.append(albedo_row(render_sphere(float(r), Path(tmp) / f"sheen_{i}")))
            log.info("roughness %.3f: A(mu=1) %.4f, A(mu=0.5) %.4f", r, rows[-1][-1], rows[-1][MU_SAMPLES // 2])
    np.savez_compressed(OUT, albedo=np.stack(rows), roughness=roughness.astype(np.float32),
                        mu=np.linspace(0.0, 1.0, MU_SAMPLES).astype(np.float32))
    log.info("wrote %s", OUT)


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    main()
