"""The multilayer EXRs the CLI writes, read without bpy (`hybridgi_core.exr`), with every pass
under its Blender 5.0 name: Cycles and HybridGI before 5.0 write DiffDir, DiffInd, DiffCol, AO,
GlossDir, GlossInd and GlossCol, so files from every version compare by name. `channel_names`
gives the names in the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hybridgi_core import exr as _file
from hybridgi_core.exr import MAGIC, ExrError, channel_names

from .blender_compat import LEGACY_PASS_NAMES

__all__ = ["MAGIC", "ExrError", "channel_names", "read_channels"]


def read_channels(path: str | Path) -> dict[str, np.ndarray]:
    """Every channel as an (h, w) float32 array, row 0 at the top of the image, by its name with
    Blender 5.0's pass names."""
    return {_current_name(name): plane for name, plane in _file.read_channels(path).items()}


def _current_name(channel: str) -> str:
    """`<ViewLayer>.DiffDir.R` -> `<ViewLayer>.Diffuse Direct.R`; other names unchanged."""
    parts = channel.split(".")
    if len(parts) >= 3 and parts[-2] in LEGACY_PASS_NAMES:
        parts[-2] = LEGACY_PASS_NAMES[parts[-2]]
    return ".".join(parts)
