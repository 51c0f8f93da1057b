"""In-process A/B of a final render's pixel rays: the render's own GI-pixel rays traced and shaded
again, once per variant in each round, the variants interleaved in one process.

    python bench/pixel_rays_ab.py SCENE.blend [--rounds 6] [--variant 'module:NAME=VALUE,...' ...]
                                  [--res 640x360] [--set NAME=VALUE ...]

The first variant is the code as it is; each --variant patches module constants (values are
Python literals) for its runs and restores them after. --set is the render's own (the ladder's
rungs: resolution=32 rays_per_cell=32 pixel_rays=32 ...). Prints, per variant, the medians and
minima of wall and CPU milliseconds of `begin_pixels` + `finish_pixels` over the render's first
full set of GI pixels (its points, cache, lookup and ScreenLight); the last line is JSON.

Why: this host's speed drifts 10-15% between runs and spikes within one, more than most changes
to the shading move a whole render (stop 45: spheres' r32 rung read 1.48 and 1.59 s in two runs
of the same code). Interleaved over the same inputs in one process, variants a few per cent apart
separate in 6-12 rounds. Not a test; errors against Cycles still need whole renders.
"""

from __future__ import annotations

import argparse
import ast
import importlib
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hybridgi_core import pixel_gather  # noqa: E402

#: GI pixels a `begin_pixels` call must have to be the pass measured (not a subframe's few).
MIN_PIXELS = 10_000


def parse_variant(text: str) -> list[tuple[str, str, object]]:
    """'module:NAME=VALUE,...' -> [(module, NAME, value)]; '' is the code as it is."""
    out = []
    for part in (p for p in text.split(",") if p.strip()):
        target, value = part.split("=", 1)
        module, name = target.strip().split(":", 1)
        out.append((module, name, ast.literal_eval(value.strip())))
    return out


def patched(variant: list[tuple[str, str, object]]) -> list[tuple[object, str, object]]:
    """Set the variant's constants; returns what restores them."""
    old = []
    for module, name, value in variant:
        mod = importlib.import_module(module)
        old.append((mod, name, getattr(mod, name)))
        setattr(mod, name, value)
    return old


def restore(old: list[tuple[object, str, object]]) -> None:
    for mod, name, value in reversed(old):
        setattr(mod, name, value)


class Harness:
    """Wraps `begin_pixels` and `finish_pixels` everywhere they are referenced: the first large
    call's arguments are kept, and once its own shading is done the variants run `rounds` times."""

    def __init__(self, variants: list[str], rounds: int):
        self.variants = {v: parse_variant(v) for v in variants}  # a malformed one fails before the render
        self.rounds = rounds
        self.begun_args = None
        self.results: dict[str, dict[str, list[float]]] = {}
        self._begin, self._finish = pixel_gather.begin_pixels, pixel_gather.finish_pixels

    def install(self) -> None:
        for mod in list(sys.modules.values()):
            for name, new, old in (("begin_pixels", self.begin, self._begin),
                                   ("finish_pixels", self.finish, self._finish)):
                if getattr(mod, name, None) is old:
                    setattr(mod, name, new)

    def begin(self, *args, **kwargs):
        if self.begun_args is None and args[1].shape[0] >= MIN_PIXELS:
            self.begun_args = (args, dict(kwargs, trickle=False))
        return self._begin(*args, **kwargs)

    def finish(self, begun, screen=None):
        result = self._finish(begun, screen)
        if self.begun_args is not None and not self.results:
            self._measure(screen)
        return result

    def _measure(self, screen) -> None:
        args, kwargs = self.begun_args
        self.results = {v: {"wall_ms": [], "cpu_ms": []} for v in self.variants}
        for _ in range(self.rounds):
            for v, variant in self.variants.items():
                old = patched(variant)
                try:
                    wall, cpu = time.perf_counter(), time.process_time()
                    self._finish(self._begin(*args, **kwargs), screen)
                    self.results[v]["wall_ms"].append((time.perf_counter() - wall) * 1e3)
                    self.results[v]["cpu_ms"].append((time.process_time() - cpu) * 1e3)
                finally:
                    restore(old)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("blend")
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--variant", action="append", default=[], help="module:NAME=VALUE,... (Python literals)")
    ap.add_argument("--res", default="640x360")
    ap.add_argument("--set", action="append", default=[], dest="settings", metavar="NAME=VALUE")
    args = ap.parse_args(argv)
    try:
        harness = Harness([""] + args.variant, args.rounds)
    except (ValueError, SyntaxError) as error:
        ap.error(f"--variant: {error} (expected module:NAME=VALUE,... with Python literals)")
    harness.install()
    from hybridgi_cli import main as cli

    with tempfile.TemporaryDirectory() as tmp:
        render = ["render", args.blend, "--out", str(Path(tmp) / "ab"), "--res", args.res]
        for s in args.settings:
            render += ["--set", s]
        code = cli.main(render)
    if not harness.results:
        print(f"pixel_rays_ab: no pass of {MIN_PIXELS} GI pixels or more ran (pixel_rays=0?)", file=sys.stderr)
        return 1
    rows = {}
    for v, r in harness.results.items():
        name = v or "as is"
        rows[name] = {k: {"median": round(statistics.median(x), 1), "min": round(min(x), 1)} for k, x in r.items()}
        w, c = rows[name]["wall_ms"], rows[name]["cpu_ms"]
        print(f"{name:60s} wall {w['median']:7.1f} (min {w['min']:7.1f})  cpu {c['median']:7.1f} "
              f"(min {c['min']:7.1f}) ms", file=sys.stderr)
    print(json.dumps({"blend": args.blend, "rounds": args.rounds, "variants": rows}))
    return code or 0


if __name__ == "__main__":
    sys.exit(main())
