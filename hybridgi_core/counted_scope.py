"""A process-wide setting held while at least one owner, on any thread, is inside its scope.

Why: the settings HybridGI renders under (`heap.held`, `gil.quick_handoff`) belong to the process,
and a final render, the CLI's frames and a viewport worker may overlap: the first owner in
applies a setting, the last one out restores it, and nobody in between changes it.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable


class CountedScope:
    """`with scope():` runs `apply()` when the first holder enters and `restore()` when the last
    leaves (also when its block raises); nestable and thread-safe."""

    def __init__(self, apply: Callable[[], None], restore: Callable[[], None]):
        self._apply, self._restore = apply, restore
        self._lock = threading.Lock()
        self.holders = 0

    @contextlib.contextmanager
    def __call__(self):
        with self._lock:
            self.holders += 1
            if self.holders == 1:
                self._apply()
        try:
            yield
        finally:
            with self._lock:
                self.holders -= 1
                if self.holders == 0:
                    self._restore()
