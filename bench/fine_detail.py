"""Issue #12's measurement: HybridGI against Cycles on fine detail (thin geometry, contacts, a large
outdoor yard) and on the bundled car and atrium, pass by pass.

    python bench/fine_detail.py [--scenes yard,contact,trusses,car,atrium] [--res 320x240]
                                [--set key=value ...] [--tag NAME] [--heat]

Builds bench/fine_detail_scenes.py's scenes, renders a Cycles reference per scene (1024 spp,
cached under out/fine_refs by a key of the scene's source, the Blender version, the resolution and
the reference settings), renders HybridGI with the given settings and prints, per scene, the
relative L1 of Diffuse Direct, Diffuse Indirect, AO and Combined (issue #12's targets: DI <= 0.08,
AO <= 0.05, DD <= 0.05), the render's seconds, and a last line of JSON.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import compare_cycles  # noqa: E402
import error_breakdown  # noqa: E402
import quality_ladder as ql  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from hybridgi_core.cycles_reference import CYCLES_REFERENCE  # noqa: E402

BUILT = ("yard", "contact", "trusses")
WORLDS = ("hdri_yard", "sky_yard", "hdri_room")
CLUTTER = ("scatter",)
BUNDLED = ("car", "atrium")
SOURCE = Path(__file__).with_name("fine_detail_scenes.py")
PROCEDURAL = (ROOT / "blend_scenes" / "procedural.py", ROOT / "blend_scenes" / "build.py")
TARGETS = {"Diffuse Indirect": 0.08, "Ambient Occlusion": 0.05, "Diffuse Direct": 0.05}


def scene_path(name: str, out: Path) -> tuple[Path, str]:
    """(blend, content digest) of one scene, building the fine-detail ones when missing."""
    if name in BUNDLED:
        blend = ROOT / "blend_scenes" / f"{name}.blend"
        if not blend.is_file():
            subprocess.run(["make", "scenes"], cwd=ROOT, check=True)
        return blend, ql.scene_digest(blend, PROCEDURAL)
    blend = out / f"{name}.blend"
    if not blend.is_file():
        subprocess.run([sys.executable, str(SOURCE), str(out), name], check=True, stdout=subprocess.DEVNULL)
    return blend, ql.scene_digest(Path(name), (SOURCE,))


def reference(name: str, blend: Path, digest: str, res, spp: int, cache: Path) -> Path:
    import importlib.metadata  # noqa: PLC0415

    key = ql.reference_key(digest, importlib.metadata.version("bpy"), res, spp, CYCLES_REFERENCE)
    prefix = cache / f"{name}_{res[0]}x{res[1]}_{spp}spp_{key}"
    exr = prefix.with_name(prefix.name + "_0001.exr")
    if not exr.is_file():
        print(f"fine_detail: {name}: Cycles reference {spp} spp (key {key}): rendering", file=sys.stderr)
        compare_cycles.render(blend, prefix, "CYCLES", res, samples=spp, nice=5)
    return exr


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(BUILT + BUNDLED), help=f"also: {','.join(WORLDS)} (issue #11's worlds), "
                    f"{','.join(CLUTTER)} (issue #12's dense clutter)")
    ap.add_argument("--res", default="320x240")
    ap.add_argument("--spp", type=int, default=1024)
    ap.add_argument("--set", dest="settings", action="append", default=[])
    ap.add_argument("--tag", default="default")
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "fine_detail")
    ap.add_argument("--ref-cache", type=Path, default=ROOT / "out" / "fine_refs")
    ap.add_argument("--heat", action="store_true", help="write heatmap strips next to each render")
    args = ap.parse_args(argv)
    res = tuple(int(x) for x in args.res.lower().split("x"))
    args.out.mkdir(parents=True, exist_ok=True)
    args.ref_cache.mkdir(parents=True, exist_ok=True)
    results = {}
    for name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        blend, digest = scene_path(name, args.out)
        ref = reference(name, blend, digest, res, args.spp, args.ref_cache)
        prefix = args.out / f"{name}_{args.tag}"
        record = compare_cycles.render(blend, prefix, "HYBRIDGI", res, settings=args.settings, nice=0)
        heat = prefix if args.heat else None
        b = error_breakdown.breakdown(record["exr"], ref, heat)
        row = {p: b.get(p, {}).get("rel_l1") for p in ("Combined", "Diffuse Direct", "Diffuse Indirect",
                                                          "Ambient Occlusion", "Diffuse Color")}
        row["seconds"] = record["seconds"]
        row["edge_error_share"] = b["edge_error_share"]
        row["meets"] = all(row[p] is not None and row[p] <= t for p, t in TARGETS.items())
        results[name] = row
        print(f"{name:8s} " + "  ".join(f"{k[:18]}={v}" for k, v in row.items()), flush=True)
    print(json.dumps({"tag": args.tag, "settings": args.settings, "res": list(res), "scenes": results}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
