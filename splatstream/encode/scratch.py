"""Scratch space of a partitioned encode: the input's centres, the splats routed to each partition, the
partitions' originals for the tiles above them. A local directory or an fsspec URL every worker can reach; every
object is written whole under its final name (a local file through a temporary name), so a task that is run
again after its worker died simply writes it again."""
from __future__ import annotations

import contextlib
import fcntl
import io
import os
import shutil
import tempfile
import uuid

import numpy as np

from ..store import fsspec_filesystem, is_url, local_path

SCRATCH_PREFIX = ".splatstream-scratch-"
# Inside a local scratch directory: a file its creating process holds an exclusive flock on for as long as it
# lives. The kernel drops the lock when the process dies, even by SIGKILL, so a directory whose lock can be taken
# belongs to nobody any more, and the next encode beside it removes it (remove_stale).
OWNER_LOCK = "owner.lock"


class Scratch:
    def __init__(self, location: str):
        self.location = location.rstrip("/")
        self._fs = None
        self._owner_fd: int | None = None

    @staticmethod
    def create(base: str) -> Scratch:
        """A new, empty scratch directory under `base` (a local directory or an fsspec URL). Local: scratch
        directories beside it that a killed encode left are removed first (remove_stale), and the new one is
        locked by this process."""
        name = f"{SCRATCH_PREFIX}{uuid.uuid4().hex[:12]}"
        if is_url(base):
            return Scratch(f"{base.rstrip('/')}/{name}")
        base = local_path(base)
        os.makedirs(base, exist_ok=True)
        remove_stale(base)
        scratch = Scratch(tempfile.mkdtemp(prefix=name + "-", dir=base))
        # Locked under a temporary name, then renamed: a sweeper never sees an owner.lock that nobody holds yet.
        fd, tmp = tempfile.mkstemp(prefix=".owner.", dir=scratch.location)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            os.write(fd, f"{os.getpid()}\n".encode())
            os.rename(tmp, os.path.join(scratch.location, OWNER_LOCK))
        except BaseException:
            os.close(fd)
            shutil.rmtree(scratch.location, ignore_errors=True)
            raise
        scratch._owner_fd = fd
        return scratch

    def __getstate__(self) -> dict:
        return {"location": self.location}

    def __setstate__(self, state: dict) -> None:
        self.__init__(state["location"])

    @property
    def remote(self) -> bool:
        return is_url(self.location)

    def _path(self, name: str) -> str:
        if self.remote:
            if self._fs is None:
                self._fs, self._root = fsspec_filesystem(self.location)
            return f"{self._root}/{name}"
        return os.path.join(self.location, name)

    def write(self, name: str, data: bytes | memoryview | list) -> None:
        """Write an object whole (`data` may be a list of byte strings, written one after the other)."""
        parts = data if isinstance(data, list) else [data]
        path = self._path(name)
        if self.remote:
            self._fs.pipe_file(path, b"".join(bytes(p) for p in parts))
            return
        os.makedirs(os.path.dirname(path), exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=".part.", dir=os.path.dirname(path))
        try:
            with os.fdopen(fd, "wb") as f:
                for p in parts:
                    f.write(p)
            os.replace(tmp, path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise

    def read(self, name: str, start: int | None = None, end: int | None = None) -> bytes:
        path = self._path(name)
        if self.remote:
            return self._fs.cat_file(path, start=start, end=end)
        with open(path, "rb") as f:
            if start:
                f.seek(start)
            return f.read() if end is None else f.read(end - (start or 0))

    def save(self, name: str, **arrays: np.ndarray) -> None:
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        self.write(name, buf.getbuffer())

    def load(self, name: str) -> dict[str, np.ndarray]:
        with np.load(io.BytesIO(self.read(name))) as z:
            return {k: z[k] for k in z.files}

    def delete(self, names: list[str]) -> None:
        """Delete objects (those already gone are skipped: a task run again after its worker died)."""
        for name in names:
            path = self._path(name)
            with contextlib.suppress(FileNotFoundError):
                if self.remote:
                    self._fs.rm_file(path)
                else:
                    os.unlink(path)

    def remove(self) -> None:
        if self.remote:
            with contextlib.suppress(FileNotFoundError):
                self._path("x")
                self._fs.rm(self._root, recursive=True)
        else:
            shutil.rmtree(self.location, ignore_errors=True)
            if self._owner_fd is not None:
                os.close(self._owner_fd)
                self._owner_fd = None


def remove_stale(base: str) -> list[str]:
    """Remove the scratch directories in local directory `base` whose owner process is dead (its OWNER_LOCK can
    be locked); those of running encodes, and directories without the lock file, are left alone. The paths
    removed."""
    removed = []
    try:
        names = [n for n in os.listdir(base) if n.startswith(SCRATCH_PREFIX)]
    except OSError:
        return removed
    for name in names:
        path = os.path.join(base, name)
        try:
            fd = os.open(os.path.join(path, OWNER_LOCK), os.O_RDONLY | os.O_NOFOLLOW)
        except OSError:
            continue  # not ours, or not locked yet (an encode from before owner locks)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            continue  # its encode is running
        finally:
            os.close(fd)
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path, ignore_errors=True)
            removed.append(path)
    return removed
