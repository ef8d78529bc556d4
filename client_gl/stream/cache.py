"""The streaming client's disk cache: immutable payloads by SHA-256, and manifests by URL with their ETag.

Payloads are content-addressed, so the same payload from any server or scene is one file
(`payloads/<2 hex>/<sha256>.bin`); a payload is never revalidated. Manifests change when a scene is re-encoded,
so each is kept with its ETag (`manifests/<sha256 of the URL>.msgpack`) and revalidated with If-None-Match
before use (format_spec/http.md section 4); it is used unrevalidated only when the server cannot be reached.

Safe with several processes (and threads) sharing one directory: every file is written under a unique temporary
name and renamed into place, so a reader sees a whole file or none; every read is verified (a payload's size and
SHA-256, a manifest's URL and checksum) and a damaged file is deleted and reported as a miss; a payload is handed
out as a VerifiedPayload, so nothing downstream hashes it again. Payloads are kept under a size cap, least
recently used evicted first; "use" is the file's mtime, bumped on every hit, so processes share one LRU order.
Blocking: the fetcher calls it from worker threads.
"""
from __future__ import annotations

import contextlib
import hashlib
import os
import tempfile
import threading
import time
from dataclasses import dataclass

import msgpack

from splatstream.errors import FormatError, UsageError
from splatstream.format.container import VerifiedPayload, verify_payload
from splatstream.format.manifest import MAX_MANIFEST_BYTES, PayloadEntry
from splatstream.format.names import DIGEST_HEX_RE

CACHE_DIR_ENV = "SPLATSTREAM_CACHE_DIR"
DEFAULT_MAX_BYTES = 2 << 30
PAYLOADS = "payloads"
MANIFESTS = "manifests"
TMP_PREFIX = ".tmp-"
STALE_TMP_SECONDS = 3600.0  # temporary files older than this were left by a crashed process
EVICT_TO = 0.9  # eviction frees down to this fraction of the cap, so not every put evicts


def default_cache_dir() -> str:
    """$SPLATSTREAM_CACHE_DIR, else the user's cache directory for splatstream (platformdirs)."""
    env = os.environ.get(CACHE_DIR_ENV)
    if env:
        return env
    import platformdirs

    return platformdirs.user_cache_dir("splatstream")


@dataclass(frozen=True)
class CachedManifest:
    data: bytes
    etag: str | None


@dataclass
class CacheStats:
    hits: int = 0
    misses: int = 0
    puts: int = 0
    corrupt: int = 0  # damaged files found (and deleted) on read
    evicted: int = 0
    evicted_bytes: int = 0


class DiskCache:
    """Payloads (capped at `max_bytes`, LRU) and manifests under `directory` (default: `default_cache_dir()`)."""

    def __init__(self, directory: str | os.PathLike | None = None, max_bytes: int = DEFAULT_MAX_BYTES):
        if max_bytes < 0:
            raise UsageError(f"cache size {max_bytes}: expected 0 or more bytes")
        self.directory = os.path.abspath(os.fspath(directory) if directory is not None else default_cache_dir())
        self.max_bytes = max_bytes
        self.stats = CacheStats()
        self._lock = threading.Lock()
        self._index: dict[str, tuple[int, float]] | None = None  # sha -> (size, last use), this process's view
        self._total = 0
        try:
            os.makedirs(os.path.join(self.directory, PAYLOADS), exist_ok=True)
            os.makedirs(os.path.join(self.directory, MANIFESTS), exist_ok=True)
        except OSError as exc:
            raise UsageError(f"{self.directory}: cannot create the cache directory ({exc.strerror}); set "
                             f"{CACHE_DIR_ENV} to a writable directory") from None

    # -- payloads -------------------------------------------------------------------------------------------------
    def payload_path(self, sha256: str) -> str:
        return os.path.join(self.directory, PAYLOADS, sha256[:2], sha256 + ".bin")

    def _scan(self) -> None:
        """Rebuild the index from the directory (other processes add and evict files); lock held."""
        index: dict[str, tuple[int, float]] = {}
        now = time.time()
        base = os.path.join(self.directory, PAYLOADS)
        with contextlib.suppress(FileNotFoundError):
            for sub in os.scandir(base):
                if not sub.is_dir(follow_symlinks=False):
                    continue
                with contextlib.suppress(FileNotFoundError):
                    for e in os.scandir(sub.path):
                        try:
                            st = e.stat(follow_symlinks=False)
                        except FileNotFoundError:
                            continue
                        if e.name.startswith(TMP_PREFIX):
                            if now - st.st_mtime > STALE_TMP_SECONDS:
                                with contextlib.suppress(FileNotFoundError):
                                    os.unlink(e.path)
                            continue
                        sha = e.name.removesuffix(".bin")
                        if e.name.endswith(".bin") and DIGEST_HEX_RE.match(sha):
                            index[sha] = (st.st_size, st.st_mtime)
        self._index = index
        self._total = sum(size for size, _ in index.values())

    def _ensure_index(self) -> dict[str, tuple[int, float]]:
        if self._index is None:
            self._scan()
        return self._index

    def contains(self, sha256: str) -> bool:
        """Whether this process believes the payload is cached (a cheap index lookup; `get` is the truth)."""
        with self._lock:
            return sha256 in self._ensure_index()

    def get(self, entry: PayloadEntry) -> VerifiedPayload | None:
        """The payload's bytes, verified against the entry (size and SHA-256: decoding does not hash them again);
        None when absent or damaged (a damaged file is deleted)."""
        path = self.payload_path(entry.sha256)
        try:
            with open(path, "rb") as f:
                data = f.read(entry.bytes + 1)
        except OSError:  # absent (evicted by another process), or unreadable: a miss either way
            with self._lock:
                self._forget(entry.sha256)
                self.stats.misses += 1
            return None
        try:
            payload = verify_payload(data, entry, path)
        except FormatError:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            with self._lock:
                self._forget(entry.sha256)
                self.stats.corrupt += 1
                self.stats.misses += 1
            return None
        now = time.time()
        with contextlib.suppress(OSError):  # the LRU order other processes see (atime is not reliable)
            os.utime(path, (now, now))
        with self._lock:
            self._ensure_index()[entry.sha256] = (len(data), now)
            self.stats.hits += 1
        return payload

    def discard(self, sha256: str) -> None:
        """Remove a payload (it verified but does not decode: nothing bad stays in the cache)."""
        with contextlib.suppress(OSError):
            os.unlink(self.payload_path(sha256))
        with self._lock:
            self._forget(sha256)

    def _forget(self, sha256: str) -> None:
        index = self._ensure_index()
        old = index.pop(sha256, None)
        if old is not None:
            self._total -= old[0]

    def put(self, entry: PayloadEntry, data: bytes) -> bool:
        """Store verified payload bytes (the caller has checked them against `entry`); False when it does not fit
        the cap or the directory cannot be written (the cache is an optimisation: writing never raises)."""
        if len(data) > self.max_bytes * EVICT_TO:
            return False
        path = self.payload_path(entry.sha256)
        if not _write_atomic(path, data):
            return False
        now = time.time()
        with self._lock:
            self._forget(entry.sha256)
            self._ensure_index()[entry.sha256] = (len(data), now)
            self._total += len(data)
            self.stats.puts += 1
            if self._total > self.max_bytes:
                self._evict()
        return True

    def _evict(self) -> None:
        """Delete least recently used payloads down to EVICT_TO of the cap; lock held. Rescans first: the files
        of other processes count, and their last uses are their mtimes."""
        self._scan()
        if self._total <= self.max_bytes:
            return
        target = int(self.max_bytes * EVICT_TO)
        for sha, (size, _) in sorted(self._index.items(), key=lambda kv: kv[1][1]):
            if self._total <= target:
                break
            with contextlib.suppress(FileNotFoundError):  # another process may have evicted it already
                os.unlink(self.payload_path(sha))
            del self._index[sha]
            self._total -= size
            self.stats.evicted += 1
            self.stats.evicted_bytes += size

    def size_bytes(self) -> int:
        """Bytes of payloads this process knows of (rescanned: includes other processes' files)."""
        with self._lock:
            self._scan()
            return self._total

    def clear(self) -> None:
        with self._lock:
            self._scan()
            for sha in list(self._index):
                with contextlib.suppress(FileNotFoundError):
                    os.unlink(self.payload_path(sha))
            self._index, self._total = {}, 0

    # -- manifests ------------------------------------------------------------------------------------------------
    def manifest_path(self, url: str) -> str:
        return os.path.join(self.directory, MANIFESTS, hashlib.sha256(url.encode()).hexdigest() + ".msgpack")

    def get_manifest(self, url: str) -> CachedManifest | None:
        """The cached manifest of `url` with its ETag; None when absent or damaged (then deleted)."""
        path = self.manifest_path(url)
        try:
            with open(path, "rb") as f:
                raw = f.read(MAX_MANIFEST_BYTES + 4096)
        except OSError:
            return None
        try:
            rec = msgpack.unpackb(raw, raw=False)
            data, etag = rec["data"], rec["etag"]
            ok = (rec["url"] == url and isinstance(data, bytes) and (etag is None or isinstance(etag, str))
                  and hashlib.sha256(data).hexdigest() == rec["sha256"])
        except (ValueError, TypeError, KeyError, msgpack.UnpackException):
            ok = False
        if not ok:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(path)
            with self._lock:
                self.stats.corrupt += 1
            return None
        return CachedManifest(data, etag)

    def put_manifest(self, url: str, data: bytes, etag: str | None) -> bool:
        rec = {"url": url, "etag": etag, "sha256": hashlib.sha256(data).hexdigest(), "data": data}
        return _write_atomic(self.manifest_path(url), msgpack.packb(rec, use_bin_type=True))


def _write_atomic(path: str, data: bytes) -> bool:
    """Write under a unique temporary name in the same directory, then rename: readers (in any process) see the
    whole file or none."""
    directory = os.path.dirname(path)
    try:
        os.makedirs(directory, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=TMP_PREFIX, dir=directory)
    except OSError:
        return False
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
        return True
    except OSError:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        return False
