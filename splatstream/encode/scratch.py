"""Scratch space of a partitioned encode: the input's centres, the splats routed to each partition, the
partitions' originals for the tiles above them. A local directory or an fsspec URL every worker can reach; every
object is written whole under its final name (a local file through a temporary name), so a task that is run
again after its worker died simply writes it again."""
from __future__ import annotations

import contextlib
import io
import os
import shutil
import tempfile
import uuid

import numpy as np

from ..store import _fsspec, is_url, local_path


class Scratch:
    def __init__(self, location: str):
        self.location = location.rstrip("/")
        self._fs = None

    @staticmethod
    def create(base: str) -> Scratch:
        """A new, empty scratch directory under `base` (a local directory or an fsspec URL)."""
        name = f".splatstream-scratch-{uuid.uuid4().hex[:12]}"
        if is_url(base):
            return Scratch(f"{base.rstrip('/')}/{name}")
        base = local_path(base)
        os.makedirs(base, exist_ok=True)
        return Scratch(tempfile.mkdtemp(prefix=name + "-", dir=base))

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
                self._fs, self._root = _fsspec(self.location)
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
