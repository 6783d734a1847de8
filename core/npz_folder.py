"""A folder of .npz files with a size limit: what the slave's scene cache (slave/scene_cache.py)
and the master's kd-tree cache (core/scene/tree_files.py) keep on disk.

Files are written with numpy (no pickle: read with allow_pickle=False) under a temporary name
and renamed, so a reader never sees half a file. Reading a file marks it used; the limit drops
the least recently used first. A file that cannot be read is deleted: what it held is built or
sent again, never trusted.
"""
from __future__ import annotations

import logging
import os
import pathlib
import threading

import numpy as np

from .private import private_folder

log = logging.getLogger("kdtrace.disk")


class NpzFolder:
    def __init__(self, folder: str | os.PathLike, limit_bytes: int):
        self.folder = pathlib.Path(folder)
        self.limit_bytes = int(limit_bytes)
        # Scenes and trees are the users' work: this user's alone (0700), never a folder
        # another user owns.
        private_folder(self.folder)

    def path(self, name: str) -> pathlib.Path:
        """The file of `name` (a name the caller has checked: hex digits, no separators)."""
        return self.folder / f"{name}.npz"

    def write(self, name: str, arrays: dict) -> bool:
        """Keep `arrays` as `name`, then trim the folder to its limit (this file stays). False
        when they are bigger than the limit alone (nothing is written). OSError: a full or
        read-only disk, for the caller to report."""
        if sum(a.nbytes for a in arrays.values()) > self.limit_bytes:
            return False
        path = self.path(name)
        if path.exists():
            os.utime(path)
            return True
        temporary = self.temporary(path)
        try:
            with open(temporary, "wb") as handle:
                np.savez(handle, **arrays)
            os.replace(temporary, path)
        finally:
            temporary.unlink(missing_ok=True)
        self.trim(keep=path)
        return True

    def read(self, name: str, check, heartbeat=None) -> object | None:
        """check(arrays) of the file `name`, or None when there is none. When the file cannot
        be read, or `check` finds it wrong (raises ValueError, KeyError, TypeError or
        IndexError: damaged, truncated, not what its name says), it is deleted and None
        returned. Any other exception from `check`, or from heartbeat() (called after each
        array is read), goes up and the file stays: the caller's Esc."""
        path = self.path(name)
        if not path.exists():
            return None
        arrays = {}
        try:
            data = np.load(path, allow_pickle=False)
        except Exception as exc:    # not an .npz numpy can read
            return self._discard(path, exc)
        with data:
            for key in data.files:
                try:
                    arrays[key] = np.ascontiguousarray(data[key])
                except Exception as exc:
                    return self._discard(path, exc)
                if heartbeat is not None:
                    heartbeat()
        try:
            value = check(arrays)
        except (ValueError, KeyError, TypeError, IndexError) as exc:
            return self._discard(path, exc)
        try:
            os.utime(path)          # used now: the limit drops it last
        except OSError:
            pass
        return value

    @staticmethod
    def _discard(path: pathlib.Path, problem: Exception) -> None:
        log.warning("disk cache: discarding %s: %s", path.name, problem)
        try:
            path.unlink(missing_ok=True)
        except OSError:             # a read-only folder: the file stays, and stays unused
            pass
        return None

    def trim(self, keep: pathlib.Path) -> None:
        """Delete the least recently used files until the folder is within its limit."""
        files = []
        for path in self.folder.glob("*.npz"):
            try:
                stat = path.stat()
            except FileNotFoundError:     # deleted meanwhile by another process
                continue
            files.append((stat.st_mtime, stat.st_size, path))
        total = sum(size for _, size, _ in files)
        for _, size, path in sorted(files, key=lambda f: f[0]):
            if total <= self.limit_bytes:
                break
            if path != keep:
                total -= size
                path.unlink(missing_ok=True)

    def usage(self) -> tuple[int, int]:
        """(files, bytes) in the folder."""
        files = total = 0
        for path in self.folder.glob("*.npz"):
            try:
                total += path.stat().st_size
                files += 1
            except FileNotFoundError:     # deleted meanwhile by another process
                pass
        return files, total

    def clear(self) -> tuple[int, int]:
        """Delete every file of the folder; (files, bytes) deleted."""
        deleted = self.usage()
        for path in self.folder.glob("*.npz"):
            path.unlink(missing_ok=True)
        return deleted

    @staticmethod
    def temporary(path: pathlib.Path) -> pathlib.Path:
        """A name beside `path` no other writer uses (process and thread in it)."""
        return path.with_suffix(f".{os.getpid()}.{threading.get_ident()}.tmp")

