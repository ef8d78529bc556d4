"""Atomic outputs: a failed or interrupted write never leaves a partial file or scene behind.

Files are written under a hidden temporary name in the target's directory and renamed at the end.
Scene directories are built under a hidden temporary name and then swapped into place with
renameat2(RENAME_EXCHANGE) where the kernel has it, so a server reading the old scene sees either
the old or the new one, never a mix. Hidden names (leading '.') are never served.
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import os
import shutil
import tempfile
from collections.abc import Iterator
from typing import BinaryIO

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def check_output(path: str | os.PathLike, directory: bool = False) -> None:
    """Fail now, before a long computation, if `path` cannot be written the way atomic_file / atomic_directory will
    write it (a missing or unwritable parent, a file where a scene directory goes, or the reverse)."""
    from .errors import UsageError

    given = os.fspath(path)
    path = os.path.abspath(given)
    parent = os.path.dirname(path)
    if directory and os.path.lexists(path) and not os.path.isdir(path):
        raise UsageError(f"{given}: exists and is not a directory (a scene is written as a directory)")
    if not directory and os.path.isdir(path):
        raise UsageError(f"{given}: is a directory, expected a file name")
    if not directory and not os.path.isdir(parent):
        raise UsageError(f"{given}: the output directory {parent} does not exist")
    probe = parent
    while not os.path.isdir(probe):  # a scene's missing parents are created: check the nearest existing one
        probe = os.path.dirname(probe)
    try:
        os.rmdir(tempfile.mkdtemp(prefix=".check.", dir=probe))
    except OSError as exc:
        raise UsageError(f"{given}: cannot write in {probe} ({exc.strerror})") from None


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[BinaryIO]:
    path = os.fspath(path)
    directory = os.path.dirname(os.path.abspath(path))
    if not os.path.isdir(directory):
        from .errors import UsageError

        raise UsageError(f"{path}: the output directory {directory} does not exist")
    if os.path.isdir(path):
        from .errors import UsageError

        raise UsageError(f"{path}: is a directory, expected a file name")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=directory)
    except OSError as exc:
        from .errors import UsageError

        raise UsageError(f"{path}: cannot write in {directory} ({exc.strerror})") from None
    try:
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _exchange(a: str, b: str) -> bool:
    """Atomically swap two paths (Linux renameat2). False where the call is not available."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    rc = fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    return rc == 0


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike) -> Iterator[str]:
    """Yield a temporary directory next to `path`; on success it replaces `path` in one step."""
    from .errors import UsageError

    given = os.fspath(path)
    path = os.path.abspath(given)
    parent = os.path.dirname(path)
    if os.path.lexists(path) and not os.path.isdir(path):
        raise UsageError(f"{given}: exists and is not a directory (a scene is written as a directory)")
    try:
        os.makedirs(parent, exist_ok=True)
        tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=parent)
    except OSError as exc:
        raise UsageError(f"{given}: cannot write a scene directory here ({exc.strerror})") from None
    try:
        yield tmp
        os.chmod(tmp, 0o755)
        if os.path.isdir(path) and not os.path.islink(path):
            if _exchange(tmp, path):
                shutil.rmtree(tmp, ignore_errors=True)  # tmp now holds the old scene
                return
            old = tmp + ".old"
            os.rename(path, old)
            os.rename(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            if os.path.lexists(path):
                raise UsageError(f"{given}: exists and is not a directory (a scene is written as a directory)")
            os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
