"""Errors of the glossy shader-node scenes (tests/glossy_node_scenes.py) against Cycles: relative
L1 over geometry pixels of Combined, Diffuse Color and the Glossy passes (`error_breakdown`), one
JSON line per scene. Cycles references are rendered once into OUT and reused.

    python bench/glossy_nodes.py [--out out/glossy_nodes] [--res 128x96] [--samples 512] [KIND ...]

Development tool: to measure another checkout's engine, run it with that checkout first on
PYTHONPATH (the references stay the same).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(1, str(Path(__file__).resolve().parent))

import error_breakdown  # noqa: E402

from tests import glossy_node_scenes  # noqa: E402

HYBRIDGI = Path(sys.executable).parent / "hybridgi"
SHOWN = ("Combined", "Diffuse Color", "Glossy Color", "Glossy Direct", "Glossy Indirect")


def _render(blend: Path, prefix: Path, res: str, *extra) -> Path:
    run = subprocess.run([str(HYBRIDGI), "render", str(blend), "--out", str(prefix), "--res", res, *extra],
                         capture_output=True, text=True, check=True)
    return Path(json.loads(run.stdout.strip().splitlines()[-1])["exr"])


def measure(kind: str, out: Path, res: str, samples: int, tag: str) -> dict:
    blend = out / f"{kind}.blend"
    if not blend.exists():
        glossy_node_scenes.build(kind, blend)
    ref = out / f"{kind}_cycles_{res}_{samples}.exr"
    if not ref.exists():
        _render(blend, out / f"{kind}_cycles_tmp", res, "--engine", "CYCLES", "--samples", str(samples)).rename(ref)
    ours = _render(blend, out / f"{kind}_{tag}", res)
    full = error_breakdown.breakdown(ours, ref)
    return {"scene": kind, "tag": tag, **{name: full[name]["rel_l1"] for name in SHOWN if name in full}}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("kinds", nargs="*", default=list(glossy_node_scenes.KINDS))
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "glossy_nodes")
    ap.add_argument("--res", default="128x96")
    ap.add_argument("--samples", type=int, default=512)
    ap.add_argument("--tag", default="hybridgi", help="name of this engine's renders")
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for kind in args.kinds:
        print(json.dumps(measure(kind, args.out, args.res, args.samples, args.tag)), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
