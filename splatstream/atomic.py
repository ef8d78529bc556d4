"""Atomic outputs: a failed or interrupted write never leaves a partial file or scene behind.

Files are written under a hidden temporary name in the target's directory and renamed at the end.
Scene directories are built under a hidden temporary name and then swapped into place with
renameat2(RENAME_EXCHANGE) where the kernel has it, so a server reading the old scene sees either
the old or the new one, never a mix. Hidden names (leading '.') are never served.

An exception, Ctrl-C or SIGTERM (the CLI raises it like Ctrl-C) removes the temporary. SIGKILL or a power cut
cannot be caught, so temporaries are named `.<target>.<pid>.<random>.tmp` and locked (flock) by their writer
while it lives: the next write to the same target removes those whose writer is gone (no lock held, and no
process with that pid).
"""
from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import fcntl
import os
import re
import shutil
import stat
import tempfile
from collections.abc import Iterator
from typing import BinaryIO

from .errors import UsageError

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


def _temp_prefix(path: str) -> str:
    return f".{os.path.basename(path)}.{os.getpid()}."


def _temp_pattern(path: str) -> re.Pattern:
    """Names of temporaries (and the .old of a non-atomic swap) a writer of `path` makes, with its pid."""
    return re.compile(re.escape(f".{os.path.basename(path)}.") + r"(\d+)\.[A-Za-z0-9_]+\.tmp(?:\.old)?")


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def _lock(fd: int) -> bool:
    """Take the writer's lock on an open temporary; False if another process holds it."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return False
    except OSError:  # a file system without flock: the pid check alone decides
        return True
    return True


def remove_stale_temporaries(path: str | os.PathLike) -> list[str]:
    """Remove the temporaries of earlier writes to `path` whose writer died without cleaning up (SIGKILL, a
    crash, a power cut): a temporary is stale when no process holds its lock and none has its pid. Returns the
    names removed."""
    path = os.path.abspath(os.fspath(path))
    parent = os.path.dirname(path)
    pattern = _temp_pattern(path)
    removed = []
    try:
        names = os.listdir(parent)
    except OSError:
        return removed
    for name in names:
        match = pattern.fullmatch(name)
        if match is None or int(match.group(1)) == os.getpid() or _process_alive(int(match.group(1))):
            continue
        full = os.path.join(parent, name)
        try:
            st = os.lstat(full)
            if not (stat.S_ISDIR(st.st_mode) or stat.S_ISREG(st.st_mode)):
                continue
            fd = os.open(full, os.O_RDONLY | os.O_NONBLOCK)
        except OSError:
            continue
        try:
            if not _lock(fd):
                continue  # a writer on another host (same pid number, shared file system) still holds it
            if stat.S_ISDIR(st.st_mode):
                shutil.rmtree(full, ignore_errors=True)
            else:
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(full)
            removed.append(name)
        finally:
            os.close(fd)
    return removed


MOUNTINFO = "/proc/self/mountinfo"


def mountinfo_points(text: str) -> set[str]:
    """The mount points a /proc/PID/mountinfo text lists (its fifth field, with the kernel's octal escapes of space,
    tab, newline and backslash undone)."""
    points = set()
    for line in text.splitlines():
        fields = line.split(" ")
        if len(fields) > 4:
            points.add(re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), fields[4]))
    return points


def is_mount_point(path: str, mountinfo: str | None = None) -> bool:
    """os.path.ismount, and the mount points the kernel lists: ismount compares a directory's device with its
    parent's, so a bind mount within one file system (`mount --bind`, a container volume from the host's disk) was
    not seen (newuser64: the encode ran to its end and failed with 'Device or resource busy')."""
    if os.path.ismount(path):
        return True
    try:
        with open(mountinfo or MOUNTINFO, encoding="utf-8", errors="surrogateescape") as f:
            text = f.read()
    except OSError:  # not Linux, or no /proc
        return False
    return os.path.realpath(path) in mountinfo_points(text)


# The index file of each of our directory outputs and what it makes of its directory (format/names.py's
# MANIFEST_NAME, TILESET_NAME and LOD_META_NAME: this module sits below format/, test_atomic checks they agree).
DIRECTORY_OUTPUT_INDEXES = {"manifest.msgpack": "an encoded scene", "tileset.json": "a 3D Tiles tileset",
                            "lod-meta.json": "a streamed SOG"}


def check_replaceable(given: str, path: str, holds: str | None) -> None:
    """An existing directory that a directory output would replace must be empty or hold `holds` (the file every
    output of that kind has: manifest.msgpack, tileset.json, ...), so that a mistyped output path never deletes a
    directory of the user's own files (`encode scene.ply ~/Documents`). Nor may it be a mount point (a container's
    volume, `docker run -v $PWD/out:/out ... encode scene.ply /out`): the finished output takes its place by a
    rename, which cannot move a mount point, so the whole encode ran and then failed with 'Device or resource
    busy'. Nor may it hold another output's index beside `holds` (a scene directory with a tileset.json copied
    in: export-3dtiles replaced it, deleting the scene; encode, the tileset)."""
    if not os.path.isdir(path) or os.path.islink(path):
        return
    if is_mount_point(path):
        raise UsageError(f"{given}: is a mount point, which the finished output cannot replace (it is renamed into "
                         f"place); give a directory inside it, e.g. {os.path.join(given, 'scene')}")
    if holds is None:
        return
    entries = sorted(os.listdir(path))
    if holds in entries:
        other = next((name for name in DIRECTORY_OUTPUT_INDEXES if name != holds and name in entries), None)
        if other is not None:
            kind = DIRECTORY_OUTPUT_INDEXES[other]
            raise UsageError(f"{given}: holds {kind} ({other}) beside {holds}: replacing it would delete that "
                             f"{kind[kind.index(' ') + 1:]}; give a new or empty directory, or move one of them out")
        return
    if not entries:
        return
    shown = ", ".join(entries[:3]) + (", ..." if len(entries) > 3 else "")
    raise UsageError(f"{given}: exists and holds other files ({shown}) but no {holds}: not replaced; give a new "
                     "or empty directory, or remove this one first")


# Where a directory output (a scene, a 3D Tiles tileset, a streamed SOG) would replace a file: it said "a scene is
# written as a directory" for export-sog-lod and export-3dtiles too.
NOT_A_DIRECTORY = "exists and is not a directory (the output is a directory: a scene, a 3D Tiles tileset or a " \
    "streamed SOG)"


def check_output(path: str | os.PathLike, directory: bool = False, holds: str | None = None) -> None:
    """Fail now, before a long computation, if `path` cannot be written the way atomic_file / atomic_directory will
    write it (a missing or unwritable parent, a file where a scene directory goes, or the reverse; a directory of
    other files where a directory output holding `holds` goes: check_replaceable)."""
    given = os.fspath(path)
    path = os.path.abspath(given)
    parent = os.path.dirname(path)
    if directory and os.path.lexists(path) and not os.path.isdir(path):
        raise UsageError(f"{given}: {NOT_A_DIRECTORY}")
    if directory:
        check_replaceable(given, path, holds)
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
        raise UsageError(f"{path}: the output directory {directory} does not exist")
    if os.path.isdir(path):
        raise UsageError(f"{path}: is a directory, expected a file name")
    remove_stale_temporaries(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path), suffix=".tmp", dir=directory)
    except OSError as exc:
        raise UsageError(f"{path}: cannot write in {directory} ({exc.strerror})") from None
    try:
        _lock(fd)
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
def atomic_directory(path: str | os.PathLike, holds: str | None = None) -> Iterator[str]:
    """Yield a temporary directory next to `path`; on success it replaces `path` in one step (an existing `path`
    only where it is empty or holds `holds`: check_replaceable)."""
    given = os.fspath(path)
    path = os.path.abspath(given)
    parent = os.path.dirname(path)
    if os.path.lexists(path) and not os.path.isdir(path):
        raise UsageError(f"{given}: {NOT_A_DIRECTORY}")
    check_replaceable(given, path, holds)
    try:
        os.makedirs(parent, exist_ok=True)
        remove_stale_temporaries(path)
        tmp = tempfile.mkdtemp(prefix=_temp_prefix(path), suffix=".tmp", dir=parent)
        try:
            lock = os.open(tmp, os.O_RDONLY)
        except OSError:
            os.rmdir(tmp)
            raise
    except OSError as exc:
        raise UsageError(f"{given}: cannot write a directory here ({exc.strerror})") from None
    try:
        _lock(lock)  # held while this process lives: the lock travels with the directory through the renames
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
                raise UsageError(f"{given}: {NOT_A_DIRECTORY}")
            os.rename(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        os.close(lock)
