"""`make plots`: the README's performance and accuracy figures as plots (matplotlib).

    python bench/plots.py [--scene atrium] [--out out/plots] [--docs docs] [--accuracy out/compare/report.json]

Timings, as in the seed's timing graphs: one HYBRIDGI render of the scene per point through the
`hybridgi` command, its per-step milliseconds (the JSON record's steps_ms) stacked, against rays
per cell, cache resolution (cells along the longest axis) and image resolution, each swept around
the defaults with the others held. The numbers go to OUT/timings.json, the figure to
DOCS/timings.png.

Accuracy: the relative L1 error per pass and scene from `bench/compare_cycles.py`'s report.json
(not re-rendered here: its Cycles references take minutes each), to DOCS/accuracy.png; skipped
with a message when that file is missing.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "bench"))

from compare_cycles import render  # noqa: E402

from hybridgi_cli import blender_compat  # noqa: E402

#: Stacked groups of the pipeline's top-level steps (the JSON record's steps_ms keys), bottom to
#: top. The warm-up's own sub-steps (warmup_trace, warmup_shadow, ...) overlap in time (threads),
#: so the warm-up is one block.
STEP_GROUPS = (
    ("G-buffer + downsample", ("gbuffer", "downsample")),
    ("visible cells", ("select",)),
    ("cache warm-up (probe rays, shading, SH, bounces)", ("warmup", "update")),
    ("gather (+ visibility rays)", ("visibility", "gather")),
    ("direct light", ("direct", "direct_low")),
    ("SSAO", ("ssao",)),
    ("bilateral + deferred", ("bilateral", "deferred")),
    ("sync, ray scene, upload, write", ("sync", "build", "upload", "write")),
)

DEFAULTS = {"rays_per_cell": 64, "resolution": 48, "image": (320, 180)}
SWEEPS = {
    "rays_per_cell": (16, 32, 64, 128),
    "resolution": (16, 32, 48, 64),
    "image": ((160, 90), (320, 180), (640, 360)),
}
LABELS = {"rays_per_cell": "rays per cell", "resolution": "cache resolution (cells)", "image": "image resolution"}


def measure(blend: Path, out: Path, nice: int) -> dict:
    """{sweep: [{"x": value, "steps_ms": {...}, "seconds": s, "rays": n}]} for every point."""
    results = {}
    for name, values in SWEEPS.items():
        points = []
        for value in values:
            setting = dict(DEFAULTS, **{name: value})
            res = setting["image"]
            tag = f"{name}_{value[0]}x{value[1]}" if name == "image" else f"{name}_{value}"
            print(f"plots: {tag}", file=sys.stderr, flush=True)
            record = render(blend, out / "renders" / tag, "HYBRIDGI", res, nice=nice, settings=(
                f"rays_per_cell={setting['rays_per_cell']}", f"resolution={setting['resolution']}"))
            x = f"{res[0]}x{res[1]}" if name == "image" else value
            points.append({"x": x, "steps_ms": record["steps_ms"], "seconds": record["seconds"],
                           "rays": record.get("rays")})
        results[name] = points
    return results


def plot_timings(results: dict, path: Path, scene: str) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    fig, axes = plt.subplots(1, len(results), figsize=(5 * len(results), 4.8), sharey=True)
    colours = plt.get_cmap("tab10").colors
    for ax, (name, points) in zip(axes, results.items(), strict=True):
        xs = [str(p["x"]) for p in points]
        bottom = [0.0] * len(points)
        for (label, keys), colour in zip(STEP_GROUPS, colours, strict=False):
            heights = [sum(p["steps_ms"].get(k, 0.0) for k in keys) / 1000 for p in points]
            ax.bar(xs, heights, bottom=bottom, label=label, color=colour)
            bottom = [b + h for b, h in zip(bottom, heights, strict=True)]
        ax.set_xlabel(LABELS[name])
        ax.grid(axis="y", alpha=0.3)
    axes[0].set_ylabel("seconds per final frame (warm-up included)")
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles[::-1], labels[::-1], fontsize=8, loc="lower center", ncol=4, frameon=False)
    others = ", ".join(f"{LABELS[k]} {v if k != 'image' else f'{v[0]}x{v[1]}'}" for k, v in DEFAULTS.items())
    fig.suptitle(f"HybridGI per-step time, {scene} (defaults: {others})", fontsize=10)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def plot_accuracy(report: dict, path: Path) -> None:
    import matplotlib  # noqa: PLC0415

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    scenes = [r for r in report["scenes"] if r.get("errors")]
    passes = list(scenes[0]["errors"])
    fig, ax = plt.subplots(figsize=(7, 3.8))
    width = 0.8 / len(passes)
    for k, name in enumerate(passes):
        xs = [i + (k - (len(passes) - 1) / 2) * width for i in range(len(scenes))]
        ax.bar(xs, [r["errors"][name]["rel_l1"] for r in scenes], width, label=name)
    ax.set_xticks(range(len(scenes)), [r["scene"] for r in scenes])
    ax.set_ylabel("relative L1 vs Cycles")
    ax.set_title(f"HybridGI against Cycles at {report['samples']} spp, per pass", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", default="atrium")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "plots")
    parser.add_argument("--docs", type=Path, default=ROOT / "docs")
    parser.add_argument("--accuracy", type=Path, default=ROOT / "out" / "compare" / "report.json")
    parser.add_argument("--timings", type=Path, help="plot these timings (a timings.json) instead of rendering")
    parser.add_argument("--nice", type=int, default=10, help="niceness of the render processes (0: none)")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    args.docs.mkdir(parents=True, exist_ok=True)

    if args.timings:
        results = json.loads(args.timings.read_text())
    else:
        blend = blender_compat.scenes_dir() / f"{args.scene}.blend"
        if not blend.is_file():
            parser.error(f"{blend} is missing (make scenes)")
        results = measure(blend, args.out, args.nice)
        (args.out / "timings.json").write_text(json.dumps(results, indent=1) + "\n")
    plot_timings(results, args.docs / "timings.png", args.scene)
    print(f"plots: {args.docs / 'timings.png'}", file=sys.stderr)
    if args.accuracy.is_file():
        plot_accuracy(json.loads(args.accuracy.read_text()), args.docs / "accuracy.png")
        print(f"plots: {args.docs / 'accuracy.png'}", file=sys.stderr)
    else:
        print(f"plots: no {args.accuracy}: run bench/compare_cycles.py for the accuracy plot", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
