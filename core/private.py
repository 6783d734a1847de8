"""Folders and files that only this user may read: identities (their private keys), the scene
and kd-tree caches (scenes are the users' work), PoCL's kernel cache (a kernel planted there
would run as this user). On POSIX a folder is made 0700 and must be owned by this user and
not writable by others; elsewhere (Windows) the user's profile folders are private already
and the checks are skipped."""
from __future__ import annotations

import os
import pathlib
import stat
import tempfile

POSIX = os.name == "posix"


class NotPrivate(OSError):
    """A folder that should be this user's alone belongs to another user or is open to others."""


def private_folder(path, parents: bool = True) -> pathlib.Path:
    """`path` made (0700) if missing, else checked: owned by this user; its mode is narrowed
    to 0700 where it was wider. NotPrivate when another user owns it or it is a symbolic
    link (planted in a shared folder such as /tmp)."""
    path = pathlib.Path(path)
    if parents:
        path.parent.mkdir(parents=True, exist_ok=True)
    try:
        path.mkdir(mode=0o700)
    except FileExistsError:
        pass
    if not POSIX:
        return path
    info = os.lstat(path)
    if stat.S_ISLNK(info.st_mode) or not stat.S_ISDIR(info.st_mode):
        raise NotPrivate(f"{path} is not a folder of its own (a link or a file): not used")
    if info.st_uid != os.getuid():
        raise NotPrivate(f"{path} belongs to another user (uid {info.st_uid}): not used")
    if stat.S_IMODE(info.st_mode) & 0o077:
        os.chmod(path, 0o700)
    return path


def is_private(path) -> bool:
    """The folder exists, is this user's and no one else may enter it (always True off POSIX)."""
    if not POSIX:
        return True
    try:
        info = os.lstat(path)
    except OSError:
        return False
    return (stat.S_ISDIR(info.st_mode) and info.st_uid == os.getuid()
            and not stat.S_IMODE(info.st_mode) & 0o077)


def write_private_file(path, data: bytes) -> None:
    """Write `data` to `path` readable by this user only (0600), atomically: a temporary file
    in the same folder, then renamed over `path`."""
    path = pathlib.Path(path)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(handle, "wb") as file:
            file.write(data)
        if POSIX:
            os.chmod(temporary, 0o600)
        os.replace(temporary, path)
    except BaseException:
        pathlib.Path(temporary).unlink(missing_ok=True)
        raise
