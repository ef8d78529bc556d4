"""The scene root on disk: opening served files safely, discovering scenes, caching what is cheap to cache.

Nothing is cached that could mix two versions of a scene: files are opened per request (an open file keeps
its bytes even when an encoder swaps the scene directory away), and the caches hold only facts derived from
one manifest file, keyed by its (device, inode, mtime_ns, size) taken from the open file.
"""
from __future__ import annotations

import errno
import hashlib
import logging
import os
import stat
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from splatstream.errors import SplatstreamError
from splatstream.format.manifest import MAX_MANIFEST_BYTES, parse_manifest, scene_summary
from splatstream.format.names import MANIFEST_NAME

from .limits import rate_limited
from .paths import MAX_SCENE_DEPTH, SEGMENT_RE, ScenePath, is_inside

log = logging.getLogger("splatstream.server")

SMALL_FILE_BYTES = 64 << 10  # files up to this size are read into memory; larger ones go out with sendfile
MAX_SCAN_DIRS = 10_000
_CACHE_ENTRIES = 1024
_PROC_FD = "/proc/self/fd"


class NotFound(Exception):
    pass


class Forbidden(Exception):
    """The file exists but this server may not read it (its mode): answered 403, and the operator is told."""


class OutOfResources(Exception):
    """No descriptor or memory left to open a file: answered 503 (try again), never 404."""


@dataclass
class OpenedFile:
    fd: int
    size: int
    etag_token: str  # the SHA-256 hex of the bytes
    data: bytes | None  # the whole file when it is small (or was read to hash it)

    def close(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


class _LRU(OrderedDict):
    def get_fresh(self, key):
        value = self.get(key)
        if value is not None:
            self.move_to_end(key)
        return value

    def put(self, key, value) -> None:
        self[key] = value
        self.move_to_end(key)
        while len(self) > _CACHE_ENTRIES:
            self.popitem(last=False)


def real_path_of_fd(fd: int, fallback: str) -> str:
    """The real path of the file opened as `fd` (/proc/self/fd's link), else `fallback`'s real path."""
    try:
        path = os.readlink(f"{_PROC_FD}/{fd}")
    except OSError:
        return os.path.realpath(fallback)
    return path.removesuffix(" (deleted)")


class SceneRoot:
    def __init__(self, root: str | os.PathLike):
        # Kept as given (made absolute), resolved per request: a root that is a symbolic link switched to a new
        # release directory ("current" -> "release-42") is followed at the next request.
        self.root = os.path.abspath(os.fspath(root)).rstrip("/") or "/"
        self._real_root = os.path.realpath(self.root)  # re-resolved whenever a containment check fails
        self._manifest_hashes: _LRU = _LRU()  # (dev, ino, mtime_ns, size) -> sha256 hex
        self._summaries: _LRU = _LRU()  # (path, dev, ino, mtime_ns, size) -> summary dict or None
        self._have_proc_fd = os.path.isdir(_PROC_FD)

    def _resolve_root(self) -> str:
        """The root's real path now. A file opened through a root link that was switched since the last
        resolution lies outside the cached real root: the check then resolves again before refusing."""
        self._real_root = os.path.realpath(self.root)
        return self._real_root

    def contains_real_path(self, real: str) -> bool:
        """Whether the real path `real` (of an opened file) lies inside the root: the cached real root first, then
        the root resolved again (a root link switched since) before refusing."""
        return is_inside(real, self._real_root) or is_inside(real, self._resolve_root())

    def _open_inside(self, path: str, missing: str, what: str) -> tuple[int, os.stat_result]:
        """Open the regular file `path` for reading if its real path lies inside the root: (fd, stat).

        NotFound(missing) when it does not exist, is not a regular file or leads out of the root (the same rule
        for serving and for the scene list); Forbidden when its permissions keep this server from reading it
        (`what` names it in that message).
        """
        try:
            # O_NONBLOCK: opening a FIFO planted in the tree must not hang the server.
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC | os.O_NONBLOCK)
        except PermissionError:
            _report_unreadable(path)
            raise Forbidden(f"the server may not read {what} (file permissions)") from None
        except OSError as exc:
            if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOMEM):
                rate_limited("open", logging.WARNING, "cannot open %s: %s; answered 503", path, exc.strerror)
                raise OutOfResources(f"server busy: cannot open {what} now; retry later") from None
            raise NotFound(missing) from None
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise NotFound(missing)
            real = real_path_of_fd(fd, path) if self._have_proc_fd else os.path.realpath(path)
            if not self.contains_real_path(real):
                # A client can ask again and again: INFO (not shown by default), once per interval.
                rate_limited("outside", logging.INFO, "refused %s: resolves outside the root (%s)", path, real)
                raise NotFound(missing)
            return fd, st
        except BaseException:
            os.close(fd)
            raise

    # -- serving files -----------------------------------------------------------------------------------------
    def open(self, sp: ScenePath) -> OpenedFile:
        """Open a validated scene file; NotFound unless it is a regular file of a scene, inside the root."""
        scene_dir = f"{self.root}/{sp.scene_id}"  # ids and rel use "/" (POSIX only, like the rest of serve)
        if sp.kind == "payload":
            try:
                if not stat.S_ISREG(os.stat(f"{scene_dir}/{MANIFEST_NAME}").st_mode):
                    raise NotFound(f"no scene {sp.scene_id!r}")
            except OSError:
                raise NotFound(f"no scene {sp.scene_id!r}") from None
        missing = f"no scene {sp.scene_id!r}" if sp.kind == "manifest" else \
            f"no file {sp.rel!r} in scene {sp.scene_id!r}"
        fd, st = self._open_inside(f"{scene_dir}/{sp.rel}", missing, f"{sp.rel} of scene {sp.scene_id!r}")
        try:
            size = st.st_size
            data = None
            if sp.kind == "payload":
                token = sp.sha256
                if size <= SMALL_FILE_BYTES:
                    data = read_first_bytes(fd, size)
                    size = len(data)
            else:
                if size > MAX_MANIFEST_BYTES:
                    raise NotFound(f"manifest of scene {sp.scene_id!r} is larger than {MAX_MANIFEST_BYTES} bytes")
                key = (st.st_dev, st.st_ino, st.st_mtime_ns, size)
                token = self._manifest_hashes.get_fresh(key)
                if token is None or size <= SMALL_FILE_BYTES:
                    data = read_first_bytes(fd, size)
                    size = len(data)
                    if token is None:
                        token = hashlib.sha256(data).hexdigest()
                        self._manifest_hashes.put(key, token)
            assert token is not None
            return OpenedFile(fd, size, token, data)
        except BaseException:
            os.close(fd)
            raise

    # -- discovering scenes ------------------------------------------------------------------------------------
    def scan(self) -> list[tuple[str, str]]:
        """(scene id, directory) of every scene under the root, sorted by id.

        Walks non-hidden directories with safe names, at most MAX_SCENE_DEPTH deep, following symbolic links
        only where they stay inside the root, and does not look inside a scene (a scene's data/ is no scene).
        """
        found: list[tuple[str, str]] = []
        real_root = self._resolve_root()
        stack: list[tuple[str, tuple[str, ...]]] = [(self.root, ())]
        visited = 0
        while stack:
            directory, segs = stack.pop()
            visited += 1
            if visited > MAX_SCAN_DIRS:
                log.warning("scene scan stopped after %d directories", MAX_SCAN_DIRS)
                break
            try:
                entries = list(os.scandir(directory))
            except OSError as exc:
                if exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOMEM):
                    raise OutOfResources("server busy: cannot list the scenes now; retry later") from None
                continue
            for e in entries:
                if not SEGMENT_RE.match(e.name) or len(segs) >= MAX_SCENE_DEPTH:
                    continue
                try:
                    if not e.is_dir():
                        continue
                    if e.is_symlink() and not is_inside(os.path.realpath(e.path), real_root):
                        continue
                except OSError:
                    continue
                child = (*segs, e.name)
                if os.path.isfile(os.path.join(e.path, MANIFEST_NAME)):
                    found.append(("/".join(child), e.path))
                else:
                    stack.append((e.path, child))
        found.sort()
        return found

    def summary(self, scene_id: str, directory: str) -> dict | None:
        """The /api/scenes entry of one scene, or None when its manifest is unreadable or invalid."""
        path = os.path.join(directory, MANIFEST_NAME)
        try:
            # The rule of serving: a manifest leading out of the root is no scene here (it would leak its facts).
            fd, st = self._open_inside(path, f"no scene {scene_id!r}", f"the manifest of scene {scene_id!r}")
        except (NotFound, Forbidden):
            return None  # (OutOfResources goes up: a list missing scenes must not look complete)
        try:
            if st.st_size > MAX_MANIFEST_BYTES:
                return None
            key = (path, st.st_dev, st.st_ino, st.st_mtime_ns, st.st_size)
            cached = self._summaries.get_fresh(key)
            if cached is not None:
                return cached or None
            raw = read_first_bytes(fd, st.st_size)
        finally:
            os.close(fd)
        try:
            m = parse_manifest(raw, f"{scene_id}/{MANIFEST_NAME}")
            s = scene_summary(m)
            size = m.bytes_on_disk
            entry = {
                "id": scene_id,
                "name": s["name"],
                "splats": s["splats"],
                "sh_degree": s["sh_degree"],
                "preset": s["preset"],
                "bounds": s["bounds"],
                "bytes": size,
                "manifest": f"/scenes/{scene_id}/{MANIFEST_NAME}",
            }
        except SplatstreamError as exc:
            # 'skipped' read as not served, where its files still are (http.md 6; newuser64)
            log.warning("scene %s: left out of /api/scenes (its files are still served), its manifest is not valid: "
                        "%s", scene_id, exc)
            entry = {}
        self._summaries.put(key, entry)
        return entry or None

    def list_scenes(self) -> list[dict]:
        return [s for sid, d in self.scan() if (s := self.summary(sid, d)) is not None]


def walk_root(root: str, visit: Callable[[os.DirEntry, tuple[str, ...]], bool], max_dirs: int) -> None:
    """Depth first under `root` for `serve`'s start-up checks (SceneRoot.scan keeps its own walk: it runs per request,
    and turns a lack of file descriptors into OutOfResources): hidden entries (a leading '.', as build
    temporaries are) and anything deeper than a scene id can be are skipped, at most `max_dirs` directories read.
    `visit(entry, its path's segments)` says whether to descend into it; an entry that cannot be read is passed by."""
    stack: list[tuple[str, tuple[str, ...]]] = [(root, ())]
    visited = 0
    while stack and visited < max_dirs:
        directory, segs = stack.pop()
        visited += 1
        try:
            entries = sorted(os.scandir(directory), key=lambda e: e.name)
        except OSError:
            continue
        for e in entries:
            if e.name.startswith(".") or len(segs) >= MAX_SCENE_DEPTH:
                continue
            child = (*segs, e.name)
            try:
                if visit(e, child):
                    stack.append((e.path, child))
            except OSError:
                continue


def _report_unreadable(path: str) -> None:
    """Tell the operator why a file answers 403 (files written 0600 by another user's encoder, for instance)."""
    try:
        st = os.stat(path)
        why = f"mode {stat.S_IMODE(st.st_mode):04o}, owner uid {st.st_uid}"
    except OSError as exc:
        why = exc.strerror or str(exc)
    rate_limited("unreadable", logging.WARNING, "cannot read %s: permission denied (%s; this server runs as uid %d); "
                 "answered 403", path, why, os.geteuid())


def read_first_bytes(fd: int, size: int) -> bytes:
    """The first `size` bytes (fewer if the file is shorter)."""
    data = os.pread(fd, size, 0)
    if len(data) == size or not data:
        return data
    chunks = [data]
    offset = len(data)
    while offset < size and (chunk := os.pread(fd, size - offset, offset)):
        chunks.append(chunk)
        offset += len(chunk)
    return b"".join(chunks)
