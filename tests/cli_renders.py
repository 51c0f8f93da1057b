"""Renders through the real `hybridgi render` command, shared by the tests that compare with Cycles
rendered in the same test (one subprocess per render: what a user runs)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from hybridgi_cli import exr

HYBRIDGI = Path(sys.executable).parent / "hybridgi"


def run_render(blend, prefix, res, *extra, env=None) -> subprocess.CompletedProcess:
    """`hybridgi render BLEND --out PREFIX --res RES EXTRA...`, its output captured."""
    return subprocess.run([str(HYBRIDGI), "render", str(blend), "--out", str(prefix), "--res", res, *extra],
                          capture_output=True, text=True, timeout=600, env=env)


def rendered(blend, prefix, res, *extra, env=None) -> dict:
    """The channels of the multilayer EXR of a render that must succeed."""
    run = run_render(blend, prefix, res, *extra, env=env)
    assert run.returncode == 0, run.stderr[-3000:]
    return exr.read_channels(json.loads(run.stdout.strip().splitlines()[-1])["exr"])


def layer(channels, name, components="RGB") -> np.ndarray:
    """(h, w, len(components)) float32 of a pass (rows top-down, as the EXR stores them)."""
    return np.stack([channels[f"ViewLayer.{name}.{c}"] for c in components], axis=-1)
