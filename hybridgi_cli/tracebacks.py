"""The command's stderr without the tracebacks of exceptions that are reported otherwise.

Blender prints the traceback of an exception raised in a render engine's `render()` and then
carries on; the HYBRIDGI engine records the error, and the CLI reports it in its one
`hybridgi: error:` line, so the traceback would only be noise (and a second error report).
"""

from __future__ import annotations

import sys


class TracebackFilter:
    """sys.stderr of the command: passes text through, but holds back the tracebacks Python and
    Blender print for an exception they then ignore (one in the engine's render(), which the
    engine records and the CLI reports in its one error line; one in a `__del__` at exit).
    (`main` does not install it when HYBRIDGI_DEBUG is set.) Held tracebacks are kept in `held`."""

    def __init__(self, stream) -> None:
        self.stream = stream
        self.in_traceback = False
        self.pending = ""
        self.held: list[str] = []

    def write(self, text: str) -> int:
        self.pending += text
        *lines, self.pending = self.pending.split("\n")
        for line in lines:
            if line.startswith(("Traceback (most recent call last):", "Exception ignored in")):
                self.in_traceback = True
            elif self.in_traceback and line and not line[0].isspace() and not line.startswith("Traceback"):
                self.in_traceback = False  # the exception's own line ends the traceback
                self.held.append(line)
                continue
            if self.in_traceback:
                self.held.append(line)
            else:
                self.stream.write(line + "\n")
        return len(text)

    def flush(self) -> None:
        if self.pending and not self.in_traceback:
            self.stream.write(self.pending)
        self.pending = ""
        self.stream.flush()

    def __getattr__(self, name):
        return getattr(self.stream, name)


def hold() -> None:
    """From here on, tracebacks printed on sys.stderr are held back."""
    if not isinstance(sys.stderr, TracebackFilter):
        sys.stderr = TracebackFilter(sys.stderr)
