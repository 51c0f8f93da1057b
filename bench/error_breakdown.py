"""Where a HybridGI render's Combined error comes from, against a Cycles reference.

Combined = Diffuse Color x (Diffuse Direct + Diffuse Indirect) + emission (+ glossy, which
HybridGI does not render). Swapping one of our passes into the reference's composition tells how
much Combined error that pass alone costs; the edge split tells how much sits on pixels next to a
depth or normal discontinuity (pixel anti-aliasing, G-buffer coverage) rather than in smooth
regions (shading). Development tool: prints one JSON line.

    python bench/error_breakdown.py TEST.exr REFERENCE.exr [--heat PREFIX]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import compare_cycles  # noqa: E402
import imagediff  # noqa: E402

PASSES = ("Combined", "Diffuse Direct", "Diffuse Indirect", "Diffuse Color", "Ambient Occlusion", "Glossy Direct",
          "Glossy Indirect", "Glossy Color")


def edge_pixels(passes: dict[str, np.ndarray], mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: geometry pixels within one pixel of a silhouette or a crease (the reference's
    depth jumps by > 2% or its normal turns by > 25 degrees), where a one-sample-per-pixel raster
    and Cycles' filtered pixels differ most."""
    depth = passes["Depth"][..., 0].astype(np.float64)
    depth = np.where(mask, depth, np.nanmax(np.where(mask, depth, 0.0)) * 10.0 + 1.0)
    edge = np.zeros(mask.shape, bool)
    normal = passes.get("Normal")
    for axis in (0, 1):
        d = np.abs(np.diff(depth, axis=axis)) > 0.02 * np.minimum(
            np.delete(depth, -1, axis=axis), np.delete(depth, 0, axis=axis))
        m = np.diff(mask.astype(np.int8), axis=axis) != 0
        jump = d | m
        if normal is not None:
            n = normal[..., :3].astype(np.float64)
            dot = (np.delete(n, -1, axis=axis) * np.delete(n, 0, axis=axis)).sum(-1)
            jump |= dot < np.cos(np.radians(25.0))
        pad_lo = [(0, 0), (0, 0)]
        pad_hi = [(0, 0), (0, 0)]
        pad_lo[axis] = (1, 0)
        pad_hi[axis] = (0, 1)
        edge |= np.pad(jump, pad_lo) | np.pad(jump, pad_hi)
    return edge & mask


def boundary_pixels(passes: dict[str, np.ndarray], mask: np.ndarray) -> np.ndarray:
    """(h, w) bool: geometry pixels whose Diffuse Color differs (> 0.01) from a 4-neighbour's or
    that touch the background: pixels a thin object or a material boundary shares, where the
    film's Diffuse Indirect (sum of colour x light over the summed colour) depends on how much of
    each side the pixel's samples saw. Unlike `edge_pixels` it ignores depth jumps along a
    grazing floor, which are not boundaries."""
    col = passes["Diffuse Color"][..., :3]
    pure = mask.copy()
    for axis in (0, 1):
        for shift in (1, -1):
            pure &= (np.abs(np.roll(col, shift, axis) - col).max(-1) < 0.01) & np.roll(mask, shift, axis)
    return mask & ~pure


def breakdown(test_exr, ref_exr, heat: Path | None = None) -> dict:
    test, ref = compare_cycles.read_passes(test_exr), compare_cycles.read_passes(ref_exr)
    mask = compare_cycles.geometry_mask(ref)
    out: dict = {"geometry_pixels": int(mask.sum())}
    rgb = compare_cycles.rgb
    for name in PASSES:
        if name in test and name in ref:
            t, r = rgb(test[name]), rgb(ref[name])
            out[name] = {"rel_l1": round(imagediff.relative_l1(t, r, mask), 5),
                         "bias": round(imagediff.relative_bias(t, r, mask), 5)}
            if heat is not None:
                strip = imagediff.comparison_strip(t, r, mask, vmax=0.5)
                imagediff.write_png(heat.with_name(f"{heat.name}_{name.replace(' ', '_').lower()}.png"), strip)
    r_comb = rgb(ref["Combined"]).astype(np.float64)
    parts = {k: rgb(ref[k]).astype(np.float64) for k in ("Diffuse Direct", "Diffuse Indirect", "Diffuse Color")}
    ours = {k: rgb(test[k]).astype(np.float64) for k in parts if k in test}
    rest = r_comb - parts["Diffuse Color"] * (parts["Diffuse Direct"] + parts["Diffuse Indirect"])
    swaps = {}
    for k in ours:
        mixed = dict(parts)
        mixed[k] = ours[k]
        comb = mixed["Diffuse Color"] * (mixed["Diffuse Direct"] + mixed["Diffuse Indirect"]) + rest
        swaps[k] = round(imagediff.relative_l1(comb, r_comb, mask), 5)
    out["combined_if_only"] = swaps
    out["reference_rest_share"] = round(float(np.abs(rest[mask]).sum() / max(np.abs(r_comb[mask]).sum(), 1e-30)), 5)
    edges = edge_pixels(ref, mask)
    t_comb = rgb(test["Combined"]).astype(np.float64)
    err = np.abs(t_comb - r_comb).sum(-1)
    total = float(err[mask].sum())
    out["edge_pixels"] = int(edges.sum())
    out["edge_error_share"] = round(float(err[edges].sum()) / total, 4) if total else 0.0
    den = float(np.abs(r_comb[mask]).sum())
    boundary = boundary_pixels(ref, mask)
    out["boundary_pixels"] = int(boundary.sum())
    if "Diffuse Indirect" in test:
        t_di, r_di = rgb(test["Diffuse Indirect"]).astype(np.float64), rgb(ref["Diffuse Indirect"]).astype(np.float64)
        di_err = np.abs(t_di - r_di).sum(-1)
        di_den = max(float(np.abs(r_di[mask]).sum()), 1e-30)
        # Diffuse Indirect's relative L1 split into its boundary and interior parts (they sum to it).
        out["di_boundary_l1"] = round(float(di_err[boundary].sum()) / di_den, 5)
        out["di_interior_l1"] = round(float(di_err[mask & ~boundary].sum()) / di_den, 5)
    out["combined_without_edges"] = round(float(err[mask & ~edges].sum()) / den, 5) if den else 0.0
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("test")
    ap.add_argument("reference")
    ap.add_argument("--heat", type=Path, help="write heatmap strips PREFIX_<pass>.png")
    args = ap.parse_args(argv)
    print(json.dumps(breakdown(args.test, args.reference, args.heat)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
