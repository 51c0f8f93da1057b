"""The process settings HybridGI renders under, as one scope for its three owners: the engine's
`render` of a frame, the CLI's HybridGI frames (held across them) and the viewport worker's life.

Inside: freed arrays keep their pages for the next ones (`heap.held`) and the frame's threads
hand the GIL to each other sooner (`gil.quick_handoff`); both counted across owners and threads.
"""

from __future__ import annotations

import contextlib

from . import gil, heap


@contextlib.contextmanager
def rendering():
    """Run the block under HybridGI's render settings (see the module docstring); nestable."""
    with heap.held(), gil.quick_handoff():
        yield
