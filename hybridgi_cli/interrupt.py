"""Ctrl-C (SIGINT) and SIGTERM stop a render within a second, leaving no file that looks finished.

Python runs signal handlers on the main thread between bytecodes, and a KeyboardInterrupt raised
inside a render engine's `render()` is swallowed by Blender (the frame "finishes" empty). So
the signal is taken off the main thread: Python's C-level handler writes the signal number to a
wakeup pipe at once, even while the main thread sits in a long Cycles render, and a watcher
thread reading that pipe removes the unfinished frame's temporary files, prints one error line
and ends the process (status 128 + signal: 130 for Ctrl-C). A frame being committed finishes
its rename and JSON line first (`output.COMMIT_LOCK`).
"""

from __future__ import annotations

import os
import signal
import threading

from . import output

SIGNALS = (signal.SIGINT, signal.SIGTERM)

_installed = False


def install(cleanups=()) -> None:
    """Start the watcher (main thread only; once per process). `cleanups`: callables run before
    the process ends on a signal (the throw-away Blender user folder, ...)."""
    global _installed
    if _installed or threading.current_thread() is not threading.main_thread():
        return
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)
    for sig in SIGNALS:
        # A Python-level handler must be set for the C handler (and its wakeup write) to run;
        # it does nothing itself: the watcher acts.
        signal.signal(sig, _ignore)
    signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    threading.Thread(target=_watch, args=(read_fd, tuple(cleanups)), name="hybridgi-interrupt", daemon=True).start()
    _installed = True


def _ignore(_signum, _frame) -> None:
    return None


def _watch(read_fd: int, cleanups) -> None:
    while True:
        data = os.read(read_fd, 64)
        signums = [b for b in data if b in {int(s) for s in SIGNALS}]
        if signums:
            _stop(signal.Signals(signums[0]), cleanups)


def _stop(sig: signal.Signals, cleanups) -> None:
    # A frame in the middle of its commit gets to finish it (a rename and one line: milliseconds).
    output.COMMIT_LOCK.acquire(timeout=0.5)
    output.discard_pending()
    for cleanup in cleanups:
        try:
            cleanup()
        except OSError:
            pass
    message = f"hybridgi: error: interrupted by {sig.name}; the unfinished frame was not written\n"
    try:
        os.write(2, message.encode())
    except OSError:
        pass
    os._exit(128 + int(sig))
