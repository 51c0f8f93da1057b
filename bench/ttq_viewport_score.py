"""Score bench/ttq_viewport.py output against a cached Cycles reference (the quick loop of issue
#10's viewport work; bench/time_to_quality.py runs the same scoring inside its full run).

    python bench/ttq_viewport_score.py OUT_DIR/record.json --scene cornell [--ref-cache DIR | --ref-exr EXR]

OUT_DIR/record.json is ttq_viewport.py's stdout JSON line. Prints, per timeline, the Combined
relative L1 at each checkpoint (and the worker step timings of the publication shown there).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import compare_cycles  # noqa: E402
import imagediff  # noqa: E402
import numpy as np  # noqa: E402
import time_to_quality as ttq  # noqa: E402


def find_reference(ref_cache: Path, scene: str, res: str) -> Path:
    metas = sorted(ref_cache.glob(f"{scene}_{res}_*spp_*.json"))
    if not metas:
        raise SystemExit(f"no cached reference for {scene} {res} under {ref_cache}")
    record = json.loads(metas[-1].read_text())
    return ref_cache / record["exr_name"]


def combined_error(ref, img) -> float:
    """Combined relative L1 over the reference's geometry pixels (`time_to_quality.score`'s, without
    FLIP, a bench extra this quick loop does without)."""
    rgb = compare_cycles.rgb(img)
    finite = ref.mask & np.isfinite(rgb).all(axis=-1)
    return float(imagediff.relative_l1(rgb, ref.combined, finite))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("record", type=Path)
    parser.add_argument("--scene", required=True)
    parser.add_argument("--ref-cache", type=Path,
                        default=Path(os.environ.get("HYBRIDGI_REF_CACHE", "/work/main/out/ttq_refs")))
    parser.add_argument("--ref-exr", type=Path,
                        help="score against this EXR instead (a final render or a Cycles render of the same camera)")
    parser.add_argument("--steps", action="store_true", help="also print the worker step timings")
    args = parser.parse_args(argv)
    record = json.loads(args.record.read_text().strip().splitlines()[-1])
    folder = args.record.parent
    ref = ttq.Reference(args.ref_exr or find_reference(args.ref_cache, args.scene, f"{record['width']}x{record['height']}"))
    out = {}
    for name, shots in record["timelines"].items():
        row = []
        for shot in shots:
            img = np.load(folder / shot["file"])[::-1].astype(np.float32)
            err = combined_error(ref, img)
            row.append((shot["checkpoint"], shot["t"], err))
            if args.steps and shot.get("steps_ms"):
                print(f"  {name} @{shot['checkpoint']}: updates {shot.get('updates')} {shot['steps_ms']}")
            if args.steps and "draw_ms" in shot:
                aa = shot.get("aa_draw_ms", [])
                print(f"  {name} @{shot['checkpoint']}: llvmpipe redraw {shot['draw_ms']} ms, {len(aa)} subframes "
                      f"{sum(aa):.0f} ms")
        out[name] = row
        print(f"{name:14s} " + "  ".join(f"{c}:{e:.4f}" if c is not None else f"({t:.1f}s):{e:.4f}" for c, t, e in row))
    print(json.dumps({k: [e for _, _, e in v] for k, v in out.items()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
