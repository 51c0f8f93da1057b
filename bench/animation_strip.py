"""Render the bundled animated scene in INCREMENTAL mode through the CLI and lay out a contact sheet.

    python bench/animation_strip.py [--frames 1-48] [--every 4] [--res 320x180]
                                    [--compare 13,25,37] [--out out/animation] [--set NAME=VALUE ...]

One INCREMENTAL job renders every frame of the range (a job needs successive frames); the sheet
shows every `--every`th. The `--compare` frames are also rendered INDEPENDENT (one CLI run each,
as a render farm would), for the speedup and for the difference between the two modes. Writes into
OUT: incremental_####.png/.exr (the CLI's), independent_####.png/.exr, strip.png (the sheet),
compare.png (per compare frame: incremental | independent | error heatmap of Combined). Prints one
line per frame, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

import imagediff  # noqa: E402
from compare_cycles import cli_command  # noqa: E402
from compare_cycles import render as cli_render  # noqa: E402

from hybridgi_cli import blender_compat, exr  # noqa: E402
from hybridgi_cli.main import frame_range, resolution  # noqa: E402

SCENE = blender_compat.scenes_dir() / "animated.blend"
GAP = 4  # pixels between tiles (white)


def run_range(prefix: Path, first: int, last: int, res, settings) -> list[dict]:
    """One CLI run over frames first-last (one incremental job); its JSON records in frame order."""
    cmd = cli_command() + ["render", str(SCENE), "--out", str(prefix), "--frames", f"{first}-{last}",
                           "--res", f"{res[0]}x{res[1]}"]
    for item in settings:
        cmd += ["--set", item]
    prefix.parent.mkdir(parents=True, exist_ok=True)
    with open(prefix.with_name(prefix.name + ".log"), "w") as log:
        proc = subprocess.run(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=log, text=True)
    if proc.returncode != 0:
        sys.exit(f"incremental render failed (exit {proc.returncode}); see {prefix}.log")
    return [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]


def combined(path) -> np.ndarray:
    """(h, w, 3) linear Combined of a CLI EXR, row 0 at the top."""
    ch = exr.read_channels(path)
    return np.stack([ch[f"ViewLayer.Combined.{c}"] for c in "RGB"], axis=-1)


def sheet(tiles: list[np.ndarray], columns: int) -> np.ndarray:
    """Tile (h, w, 3) uint8 images row by row with GAP white pixels between them."""
    h, w, _ = tiles[0].shape
    rows = -(-len(tiles) // columns)
    out = np.full((rows * h + (rows - 1) * GAP, columns * w + (columns - 1) * GAP, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        r, c = divmod(i, columns)
        out[r * (h + GAP) : r * (h + GAP) + h, c * (w + GAP) : c * (w + GAP) + w] = tile
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=frame_range, default=(1, 48))
    parser.add_argument("--every", type=int, default=4, help="every Nth frame on the contact sheet")
    parser.add_argument("--res", type=resolution, default=(320, 180))
    parser.add_argument("--compare", default="13,25,37", help="frames also rendered INDEPENDENT")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "animation")
    parser.add_argument("--set", action="append", default=[], dest="settings", metavar="NAME=VALUE",
                        help="scene setting for both modes (see `hybridgi render --help`)")
    parser.add_argument("--columns", type=int, default=4)
    args = parser.parse_args(argv)
    first, last = args.frames
    compare = [f for f in (int(x) for x in args.compare.split(",") if x.strip()) if first < f <= last]
    out = args.out.resolve()

    incremental = run_range(out / "incremental", first, last, args.res,
                            [*args.settings, "animation_mode=INCREMENTAL"])
    by_frame = {r["frame"]: r for r in incremental}
    for r in incremental:
        print(f"incremental frame {r['frame']:3d}: {r['seconds']:6.3f} s  rays {r['rays']:>9,}  "
              f"touched {r.get('touched_cells', 0):>5}  {'warm-up' if 'warmup' in r['steps_ms'] else ''}")

    shown = [f for f in range(first, last + 1) if (f - first) % args.every == 0]
    strip = imagediff.write_png(out / "strip.png", sheet(
        [imagediff.to_display(combined(by_frame[f]["exr"]), 1.0) for f in shown], args.columns))

    rows, speed = [], []
    for f in compare:
        ind = cli_render(SCENE, out / "independent", "HYBRIDGI", args.res, frame=f,
                         settings=[*args.settings, "animation_mode=INDEPENDENT"], nice=0)
        inc = by_frame[f]
        a, b = combined(inc["exr"]), combined(ind["exr"])
        diff = imagediff.relative_l1(a, b)
        speed.append({"frame": f, "independent_s": ind["seconds"], "incremental_s": inc["seconds"],
                      "speedup": round(ind["seconds"] / inc["seconds"], 2), "combined_rel_l1": round(diff, 4)})
        print(f"frame {f:3d}: independent {ind['seconds']:6.3f} s, incremental {inc['seconds']:6.3f} s "
              f"-> {speed[-1]['speedup']:.1f}x; Combined rel. L1 between the modes {diff:.3f}")
        rows.append(imagediff.comparison_strip(a, b, vmax=0.5))
    compare_png = imagediff.write_png(out / "compare.png", sheet(rows, 1)) if rows else None

    later = [r["seconds"] for r in incremental[1:]]
    summary = {
        "scene": str(SCENE.relative_to(ROOT)),
        "resolution": list(args.res),
        "frames": [first, last],
        "incremental_first_s": incremental[0]["seconds"],
        "incremental_mean_s": round(float(np.mean(later)), 3) if later else None,
        "incremental_s": {r["frame"]: r["seconds"] for r in incremental},
        "compare": speed,
        "mean_speedup": round(float(np.mean([s["speedup"] for s in speed])), 2) if speed else None,
        "strip": str(strip),
        "compare_png": str(compare_png) if compare_png else None,
    }
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
