"""`make demo`: a headless HybridGI render of the bundled atrium, with per-step timings.

Builds blend_scenes/atrium.blend when it is missing (from blend_scenes/build.py), renders it through
the `hybridgi` command with the HYBRIDGI engine, and prints where the PNG / multilayer EXR went and
what each step of the pipeline cost.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
sys.path.insert(0, str(ROOT))

from hybridgi_cli import blender_compat  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", default="atrium", help="bundled scene: atrium, cornell, spheres, car, animated")
    ap.add_argument("--out", default=str(ROOT / "out" / "demo"))
    ap.add_argument("--res", default="640x360")
    ap.add_argument("--frames", default="1")
    args = ap.parse_args()

    blend = blender_compat.scenes_dir() / f"{args.scene}.blend"
    if not blend.exists():
        print(f"demo: building {blend.name}", file=sys.stderr)
        subprocess.run([sys.executable, str(ROOT / "blend_scenes" / "build.py"), "--only", args.scene,
                        "--out", str(blend.parent)], check=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    prefix = out / args.scene
    cmd = [
        str(BIN / "hybridgi"),
        "render",
        str(blend),
        "--out",
        str(prefix),
        "--res",
        args.res,
        "--frames",
        args.frames,
        "--engine",
        "HYBRIDGI",
    ]
    print("demo: " + " ".join(cmd), file=sys.stderr)
    run = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)
    if run.returncode != 0:
        print(f"demo: render failed (exit {run.returncode})", file=sys.stderr)
        return run.returncode
    for line in run.stdout.splitlines():
        record = json.loads(line)
        steps = record.get("steps_ms", {})
        print(
            f"frame {record['frame']}: {record['seconds']:.2f} s  {record['width']}x{record['height']}  "
            f"{record.get('triangles', 0):,} triangles, grid {record.get('grid')}, "
            f"{record.get('rays', 0):,} probe rays"
        )
        print(f"  image: {record['png']}\n  passes: {record['exr']}")
        main_steps = {k: v for k, v in steps.items() if "_" not in k or k == "direct_low"}
        print("  ms per step: " + ", ".join(f"{k} {v:.0f}" for k, v in main_steps.items()))
        print(line)
    return 0


if __name__ == "__main__":
    sys.exit(main())
