"""Where a render's files go, and writing them so that only a finished frame looks finished.

- `resolve_prefix`: `--out` as a Blender user means it: `//` is the .blend file's folder, a
  trailing slash or an existing folder means "inside it", named after the .blend file.
- `prepare_folder`: the output folder is created and proven writable before anything renders.
- `FrameFiles`: a frame's PNG and EXR are written under hidden temporary names in the target
  folder and renamed over the final names only when both are complete; anything else (an error,
  an interrupt) removes the temporary files, so no half-written file carries a frame's name.
"""

from __future__ import annotations

import os
import re
import tempfile
import threading
from pathlib import Path

import numpy as np

#: Held while a frame's files are renamed and its JSON line is written: an interrupt waits for it,
#: so a frame is either complete and reported, or absent.
COMMIT_LOCK = threading.RLock()

#: Temporary files of frames being written; an interrupt removes them (`discard_pending`).
_PENDING: set[Path] = set()
_PENDING_LOCK = threading.Lock()


class OutputError(Exception):
    """The output cannot be written where asked; the message says where and why."""


def resolve_prefix(out: str, blend: Path) -> Path:
    """The absolute file prefix of `--out`.

    `//x` is relative to the folder of the .blend file (Blender's `//`), `~` is the home folder,
    other relative paths are relative to the working directory. A value ending in a slash, or
    naming an existing folder, is a folder: frames go inside it as `<blend name>_####`.
    """
    text = os.path.expanduser(out)
    if text.startswith("//"):
        text = os.path.join(str(Path(blend).resolve().parent), text[2:])
    is_folder = text == "" or text.endswith(("/", os.sep)) or Path(text).is_dir()
    path = Path(os.path.abspath(text or "."))
    return path / Path(blend).stem if is_folder else path


def frame_paths(prefix: Path, frame: int) -> tuple[Path, Path]:
    """(png, exr) of `frame`: `PREFIX_0001.*`, or Blender's convention when the name holds `#`s
    (the last run of `#` becomes the zero-padded frame number: `shot_##` -> `shot_07`)."""
    name = prefix.name
    runs = list(re.finditer(r"#+", name))
    if runs:
        run = runs[-1]
        stem = f"{name[:run.start()]}{frame:0{len(run.group())}d}{name[run.end():]}"
    else:
        stem = f"{name}_{frame:04d}"
    return prefix.with_name(f"{stem}.png"), prefix.with_name(f"{stem}.exr")


def prepare_folder(prefix: Path) -> None:
    """Create the folder of `prefix` and prove it writable, or raise OutputError saying why."""
    folder = prefix.parent
    if prefix.is_dir():
        raise OutputError(f"--out {prefix} is a folder; end it with a slash to write inside it")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise OutputError(f"cannot create output folder {folder}: a file of that name exists") from None
    except OSError as err:
        raise OutputError(f"cannot create output folder {folder}: {err.strerror or err}") from None
    if not folder.is_dir():
        raise OutputError(f"cannot create output folder {folder}: a file of that name exists")
    try:
        handle, probe = tempfile.mkstemp(prefix=".hybridgi-probe-", dir=folder)
    except OSError as err:
        raise OutputError(f"output folder {folder} is not writable: {err.strerror or err}") from None
    os.close(handle)
    os.unlink(probe)


class FrameFiles:
    """The PNG and EXR of one frame, written atomically.

    Inside the `with` block, write to `self.temp[path]` for each final path; `commit()` checks
    that every temporary file is non-empty and renames it over its final name (EXR first, the
    PNG last). Leaving the block without a commit removes the temporary files.
    """

    def __init__(self, *paths: Path) -> None:
        self.paths = tuple(Path(p) for p in paths)
        self.temp = {p: p.with_name(f".{p.stem}.part-{os.getpid()}{p.suffix}") for p in self.paths}
        self.committed = False

    def __enter__(self) -> FrameFiles:
        with _PENDING_LOCK:
            _PENDING.update(self.temp.values())
        return self

    def __exit__(self, *exc) -> None:
        with _PENDING_LOCK:
            _PENDING.difference_update(self.temp.values())
        if not self.committed:
            for temp in self.temp.values():
                _remove(temp)

    def commit(self) -> None:
        for final, temp in self.temp.items():
            if not temp.is_file() or temp.stat().st_size == 0:
                raise OutputError(f"Blender did not write {final}")
        try:
            for final in sorted(self.paths, key=lambda p: p.suffix == ".png"):
                os.replace(self.temp[final], final)
        except OSError as err:
            raise OutputError(f"cannot write {final}: {err.strerror or err}") from None
        self.committed = True


def non_finite_channels(exr_path: Path) -> list[str]:
    """Channels of an EXR that hold NaN or infinite pixels, as "name (count)" (a render that
    produced them is a failed render, whatever the engine says)."""
    from . import exr  # noqa: PLC0415

    bad = []
    for name, values in exr.read_channels(exr_path).items():
        count = int(values.size - np.count_nonzero(np.isfinite(values)))
        if count:
            bad.append(f"{name} ({count})")
    return bad


def fatal_non_finite(bad: list[str], engine: str) -> list[str]:
    """Which of `non_finite_channels`' channels fail the frame: all of them for HybridGI's own
    render; for a peer engine (Cycles, EEVEE) only Combined's (a single-layer file's R, G, B, A
    are Combined). Why: Cycles itself leaves NaN in its Diffuse Color pass where a volume fills a
    pixel with no surface (0 / 0), and Blender saves that pass as it is; refusing the frame made
    `--engine CYCLES` unusable on any scene with a volume. The other channels are written as the
    engine made them and named in a warning."""
    if engine == "HYBRIDGI":
        return list(bad)
    return [b for b in bad if _pass_of(b) in ("Combined", "")]


def _pass_of(channel: str) -> str:
    """The pass of a `non_finite_channels` label ("ViewLayer.Diffuse Color.R (12)" -> "Diffuse
    Color"; "R (1)", a single-layer channel -> "")."""
    parts = channel.rsplit(" (", 1)[0].split(".")
    return parts[-2] if len(parts) >= 2 else ""


def discard_pending() -> None:
    """Remove the temporary files of every frame being written (interrupt path)."""
    with _PENDING_LOCK:
        pending = list(_PENDING)
        _PENDING.clear()
    for temp in pending:
        _remove(temp)


def _remove(path: Path) -> None:
    try:
        path.unlink()
    except FileNotFoundError:
        pass
