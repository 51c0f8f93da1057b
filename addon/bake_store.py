"""Finished Cycles bakes by content key, and the background threads that make them.

World maps (`world_bake`) and material textures (`material_bake`) are both rendered by a Cycles
subprocess, keyed by what they depend on, kept a few in memory and all on disk (so a later
process or session pays nothing), and baked on a thread while the viewport goes on. One store
per kind holds that machinery; the modules keep only what to bake and how.

Any thread may call it: numpy arrays and files only, never bpy.
"""

from __future__ import annotations

import logging
import os
import threading
from collections.abc import Callable
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


#: Bytes a store's folder may hold on disk before its least recently used bakes are deleted.
#: Why: every edit of a procedural material or world is a new key; without a bound the folder
#: only grew (3.8 GiB of material bakes after a day of renders and tests).
DISK_LIMIT = 1 << 30


class BakeStore:
    def __init__(self, folder: str, kept: int, disk_dtype=None, disk_limit: int = DISK_LIMIT):
        """folder : name under ~/.cache/hybridgi (XDG_CACHE_HOME honoured); kept : arrays held in
        memory (the oldest go first); disk_dtype : dtype written to disk (None: the array's);
        disk_limit : bytes the folder keeps (`prune`)."""
        self.folder = folder
        self.kept = kept
        self.disk_dtype = disk_dtype
        self.disk_limit = disk_limit
        self._memory: dict[str, np.ndarray] = {}
        self._jobs: dict[str, threading.Thread] = {}
        self._lock = threading.Lock()
        #: Finished background bakes: the viewport compares it to re-read what they changed.
        self.completed = 0

    def directory(self) -> Path:
        root = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
        return Path(root) / "hybridgi" / self.folder

    def get(self, key: str) -> np.ndarray | None:
        """The float32 array of a finished bake, from memory or disk, or None."""
        with self._lock:
            array = self._memory.get(key)
        if array is not None:
            return array
        disk = self.directory() / f"{key}.npy"
        if not disk.is_file():
            return None
        try:
            array = np.load(disk).astype(np.float32, copy=False)
        except (OSError, ValueError):
            return None
        try:
            os.utime(disk)  # recently used: the last to go when the folder is pruned
        except OSError:
            pass
        self._remember(key, array)
        return array

    def put(self, key: str, array: np.ndarray) -> np.ndarray:
        """Keep a finished bake in memory and on disk (written whole, then renamed: a reader never
        sees half a file); returns it."""
        try:
            disk = self.directory() / f"{key}.npy"
            disk.parent.mkdir(parents=True, exist_ok=True)
            tmp = disk.with_suffix(".tmp.npy")
            np.save(tmp, array if self.disk_dtype is None else array.astype(self.disk_dtype))
            os.replace(tmp, disk)
            self.prune()
        except OSError as err:
            log.debug("%s bake not cached on disk: %s", self.folder, err)
        self._remember(key, array)
        return array

    def load_arrays(self, key: str) -> dict[str, np.ndarray] | None:
        """The named arrays `save_arrays` kept on disk under `key`, or None (disk only: the caller
        keeps what it built from them)."""
        disk = self.directory() / f"{key}.npz"
        if not disk.is_file():
            return None
        try:
            with np.load(disk, allow_pickle=False) as data:
                arrays = {name: data[name] for name in data.files}
        except (OSError, ValueError, KeyError, EOFError) as err:
            log.debug("%s: %s unreadable (%s); made again", self.folder, disk.name, err)
            return None
        try:
            os.utime(disk)
        except OSError:
            pass
        return arrays

    def save_arrays(self, key: str, arrays: dict[str, np.ndarray]) -> None:
        """Keep named arrays on disk under `key` (written whole, then renamed), as `put` does."""
        try:
            disk = self.directory() / f"{key}.npz"
            disk.parent.mkdir(parents=True, exist_ok=True)
            tmp = disk.with_suffix(".tmp.npz")
            with open(tmp, "wb") as handle:
                np.savez(handle, **arrays)
            os.replace(tmp, disk)
            self.prune()
        except OSError as err:
            log.debug("%s not cached on disk: %s", self.folder, err)

    def prune(self) -> int:
        """Delete the least recently used bakes (by modification time: `get` touches what it
        reads) until the folder holds at most `disk_limit` bytes; returns how many went."""
        files = []
        for path in [*self.directory().glob("*.npy"), *self.directory().glob("*.npz")]:
            try:
                stat = path.stat()
            except OSError:
                continue  # another process pruned it meanwhile
            files.append((stat.st_mtime, stat.st_size, path))
        total = sum(size for _t, size, _p in files)
        removed = 0
        for _t, size, path in sorted(files):
            if total <= self.disk_limit:
                break
            try:
                path.unlink()
            except OSError:
                continue
            total -= size
            removed += 1
        if removed:
            log.info("%s bakes: %d least recently used deleted (the folder keeps %d MiB)", self.folder, removed,
                     self.disk_limit >> 20)
        return removed

    def forget_memory(self) -> None:
        """Drop the in-memory copies (the disk keeps them)."""
        with self._lock:
            self._memory.clear()

    def _remember(self, key: str, array: np.ndarray) -> None:
        with self._lock:
            self._memory[key] = array
            while len(self._memory) > self.kept:
                self._memory.pop(next(iter(self._memory)))

    def running(self, name: str) -> bool:
        """Whether a background bake of that name is still running."""
        with self._lock:
            job = self._jobs.get(name)
        return job is not None and job.is_alive()

    def pending(self) -> bool:
        """Whether any background bake is running."""
        with self._lock:
            return any(job.is_alive() for job in self._jobs.values())

    def start(self, name: str, work: Callable[[], None], thread_name: str) -> None:
        """Run `work` on a daemon thread; `completed` counts it when it ends, however it ends."""

        def run():
            try:
                work()
            finally:
                with self._lock:
                    self.completed += 1

        thread = threading.Thread(target=run, name=thread_name, daemon=True)
        with self._lock:
            self._jobs[name] = thread
        thread.start()

    def join(self, name: str, timeout: float | None = None) -> None:
        """Wait for the background bake of that name, if one runs (a final render that started
        it early waits here for it instead of baking the same again)."""
        with self._lock:
            job = self._jobs.get(name)
        if job is not None:
            job.join(timeout)
