"""The one place the add-on finds `hybridgi_core`.

A packaged extension carries a vendored copy inside this package; a development checkout uses the
copy installed in the Python environment. Both are imported under their own names, so every module
of the add-on imports the core from here and never by an absolute name.
"""

from __future__ import annotations

import importlib
import importlib.util

# find_spec instead of try/except ImportError: a vendored copy that fails to import (a missing
# wheel, a syntax error) must raise, not silently fall back to a different installed version.
if importlib.util.find_spec(f"{__package__}.hybridgi_core") is not None:
    core = importlib.import_module(f"{__package__}.hybridgi_core")
else:
    core = importlib.import_module("hybridgi_core")

errors = importlib.import_module(f"{core.__name__}.errors")
settings = importlib.import_module(f"{core.__name__}.settings")
snapshot = importlib.import_module(f"{core.__name__}.snapshot")


def submodule(name: str):
    """`hybridgi_core.<name>` from whichever copy is in use (e.g. `submodule("raster.gbuffer")`)."""
    return importlib.import_module(f"{core.__name__}.{name}")
