"""A room lit by many small point lamps, HybridGI against Cycles: how the time scales with lamps.

    python bench/many_lamps.py [--lamps 2,12,50] [--res 640x360] [--ref-spp 512] [--out out/many_lamps]

Per lamp count: a closed room (floor, three walls, a ceiling, 12 coloured boxes) lit by N point
lamps of radius 0.1 m under the ceiling (3 kW in all), built in a child process; a Cycles
reference (--ref-spp, cached beside the .blend), Cycles 16 spp + OpenImageDenoise and HybridGI at
its default settings through the `hybridgi` CLI; relative L1 of Combined over geometry pixels
and FLIP against the reference. Why: rooms of many lamps (ceiling spots, string lights) are
common in artists' scenes, and every lamp-related estimator of HybridGI once cost in proportion to
the lamps (50 lamps: 45.6 s where Cycles + OIDN, whose light tree picks a lamp a sample, took 14.8 s).
Prints a table and one JSON line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import compare_cycles  # noqa: E402
import time_to_quality as ttq  # noqa: E402

BUILD = r"""
import bpy, sys, math, random
n, out, w, h = int(sys.argv[-4]), sys.argv[-3], int(sys.argv[-2]), int(sys.argv[-1])
bpy.ops.wm.read_homefile(use_empty=True)
s = bpy.context.scene
s.render.resolution_x, s.render.resolution_y = w, h
def mat(name, col, rough=0.5):
    m = bpy.data.materials.new(name); m.use_nodes = True
    b = m.node_tree.nodes["Principled BSDF"]
    b.inputs["Base Color"].default_value = (*col, 1); b.inputs["Roughness"].default_value = rough
    return m
bpy.ops.mesh.primitive_plane_add(size=20); bpy.context.object.data.materials.append(mat("floor", (0.7, 0.7, 0.7)))
for i, (loc, rot) in enumerate([((0, 6, 3), (math.pi / 2, 0, 0)), ((-8, 0, 3), (0, math.pi / 2, 0)),
                                ((8, 0, 3), (0, math.pi / 2, 0))]):
    bpy.ops.mesh.primitive_plane_add(size=12, location=loc, rotation=rot)
    bpy.context.object.data.materials.append(mat(f"wall{i}", (0.8, 0.75, 0.7)))
bpy.ops.mesh.primitive_plane_add(size=20, location=(0, 0, 6)); bpy.context.object.data.materials.append(mat("ceil", (0.8, 0.8, 0.8)))
random.seed(3)
for i in range(12):
    bpy.ops.mesh.primitive_cube_add(size=random.uniform(0.5, 1.5), location=(random.uniform(-6, 6), random.uniform(-3, 5), 0.6))
    bpy.context.object.data.materials.append(mat(f"c{i}", (random.random(), random.random(), random.random())))
for i in range(n):
    lamp = bpy.data.lights.new(f"L{i}", "POINT"); lamp.energy = 3000.0 / n; lamp.shadow_soft_size = 0.1
    lamp.color = (1.0, 0.85 + 0.15 * random.random(), 0.7 + 0.3 * random.random())
    o = bpy.data.objects.new(f"L{i}", lamp)
    o.location = (-7 + 14 * (i % 10) / 9, -4 + 9 * (i // 10) / max(1, (n - 1) // 10), 5.5)
    s.collection.objects.link(o)
cam = bpy.data.objects.new("cam", bpy.data.cameras.new("cam"))
cam.location = (0, -12, 3.5); cam.rotation_euler = (math.radians(80), 0, 0)
s.collection.objects.link(cam); s.camera = cam
world = bpy.data.worlds.new("w"); world.use_nodes = True
world.node_tree.nodes["Background"].inputs[0].default_value = (0.02, 0.02, 0.03, 1); s.world = world
bpy.ops.wm.save_as_mainfile(filepath=out)
"""


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--lamps", default="2,12,50", help="comma-separated lamp counts")
    parser.add_argument("--res", default="640x360")
    parser.add_argument("--ref-spp", type=int, default=512)
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "many_lamps")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.res.split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for n in (int(v) for v in args.lamps.split(",")):
        blend = args.out / f"lamps{n}_{w}x{h}.blend"
        if not blend.exists():
            subprocess.run([sys.executable, "-c", BUILD, str(n), str(blend), str(w), str(h)], check=True,
                           capture_output=True)
        ref_exr = args.out / f"lamps{n}_{w}x{h}_ref{args.ref_spp}_0001.exr"
        if not ref_exr.exists():
            compare_cycles.render(blend, args.out / f"lamps{n}_{w}x{h}_ref{args.ref_spp}", "CYCLES", (w, h),
                                  samples=args.ref_spp, nice=0)
        ref = ttq.Reference(ref_exr)
        row = {"lamps": n}
        for name, engine, extra in (("cycles_oidn_16spp", "CYCLES", {"samples": 16, "settings": ttq.OIDN_SETTINGS}),
                                    ("hybridgi", "HYBRIDGI", {})):
            r = compare_cycles.render(blend, args.out / f"lamps{n}_{name}", engine, (w, h), nice=0, **extra)
            s = ttq.score_exr(ref, r["exr"])
            row[name] = {"seconds": round(r["seconds"], 2), "combined": round(s["combined"], 4),
                         "flip": round(s["flip"], 4)}
        rows.append(row)
        print(f"{n:3d} lamps: HybridGI {row['hybridgi']['seconds']:6.2f} s Combined {row['hybridgi']['combined']:.4f} | "
              f"Cycles 16 spp + OIDN {row['cycles_oidn_16spp']['seconds']:6.2f} s "
              f"Combined {row['cycles_oidn_16spp']['combined']:.4f}", flush=True)
    print(json.dumps({"res": args.res, "ref_spp": args.ref_spp, "rows": rows}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
