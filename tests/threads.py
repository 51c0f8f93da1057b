"""A scope held by another thread, for tests of process-wide settings counted across threads."""

from __future__ import annotations

import contextlib
import threading


@contextlib.contextmanager
def held_on_another_thread(scope):
    """Enter `scope()` on a thread of its own and keep it entered while the block runs; the thread
    leaves it, and ends, when the block does."""
    inside, go = threading.Event(), threading.Event()

    def hold():
        with scope():
            inside.set()
            go.wait(5)

    thread = threading.Thread(target=hold)
    thread.start()
    try:
        assert inside.wait(5), "the other thread never entered the scope"
        yield
    finally:
        go.set()
        thread.join(5)
