"""The fetcher: payloads in priority order over a bounded number of requests, verified, retried, cached.

A `Fetcher` runs its own asyncio event loop on a background thread; the render thread talks to it through three
thread-safe calls:

* `manifest()`: the scene's manifest, parsed once, here (blocking; retried; revalidated against the disk cache with
  its ETag; the cached copy when the server cannot be reached: offline mode).
* `want(requests)`: the complete list of payloads the engine wants now, best first, as (priority, key, entry).
  The fetcher starts the first ones (up to `max_in_flight` network requests), keeps the rest queued in that
  order, and cancels in-flight requests whose key is no longer listed. Disk-cache hits are read beside the
  network requests, without a request.
* `done()`: the payloads completed since the last call, as (key, entry, VerifiedPayload). Every one was checked
  against its manifest entry (size and SHA-256) where it entered, here or in the disk cache, and is delivered as
  checked: decoding takes it without hashing it again; nothing unverified is ever delivered.

Failures are retried as long as the key stays wanted, with capped exponential backoff and full jitter: per
payload for its own failures (5xx, 404, checksum mismatch, truncated body, stall), and for all network requests
together when the link fails (connection refused or lost, no answer in time), so a server that goes away is
polled gently and streaming resumes when it returns. A local store's damaged or missing payload is the exception:
reading it again gives the same bytes, so after a second attempt (a re-encode may have replaced the file in
mid-read) it is a permanent failure (`damaged()`), never tried again, and the view stops with its message.
"""
from __future__ import annotations

import asyncio
import concurrent.futures
import concurrent.futures.thread  # registers its exit hook before ours (below), so ours runs first
import logging
import random
import selectors
import threading
import time
import weakref
from collections.abc import Awaitable, Callable, Hashable, Iterable
from dataclasses import dataclass, field

from splatstream.errors import FormatError, UsageError
from splatstream.format.container import VerifiedPayload, sha256_hex, verify_payload
from splatstream.format.manifest import CHECKSUM_KEY, Manifest, PayloadEntry, parse_manifest

from .cache import DiskCache
from .sources import (
    CHECKSUM,
    LINK_KINDS,
    LOCAL_ATTEMPTS,
    LOCAL_PERMANENT_KINDS,
    NOT_A_SCENE,
    NOT_FOUND,
    STALL,
    TIMEOUT,
    FetchError,
    ManifestReply,
    OnBytes,
    SceneSource,
)

log = logging.getLogger("splatstream.stream")

Key = Hashable
Request = tuple[float, Key, PayloadEntry]
Result = tuple[Key, PayloadEntry, VerifiedPayload]

# Where the manifest came from (FetchStats.manifest_source)
MANIFEST_NETWORK = "network"          # downloaded (status 200)
MANIFEST_REVALIDATED = "revalidated"  # the cached copy, confirmed current by a 304
MANIFEST_OFFLINE = "cache-offline"    # the cached copy, unconfirmed: the server could not be reached
MANIFEST_LOCAL = "local"              # read from a local store
# While every network slot is busy, how far down the wanted list a pump looks for disk-cache hits to start.
CACHE_LOOKAHEAD = 256
# After a payload answers 404, the manifest is revalidated at most this often (seconds): a re-encoded scene.
MANIFEST_RECHECK_S = 2.0


@dataclass(frozen=True)
class RetryPolicy:
    """Capped exponential backoff with full jitter: after the n-th consecutive failure wait
    uniform(0, min(cap_s, base_s * 2**(n-1))) seconds."""

    base_s: float = 0.25
    cap_s: float = 10.0

    def delay(self, failures: int, rng: random.Random) -> float:
        # the exponent bounded: 2.0 ** 1024 overflows, and a fetcher retrying a manifest for minutes gets there
        return rng.uniform(0.0, min(self.cap_s, self.base_s * 2.0 ** min(max(failures - 1, 0), 64)))


@dataclass(frozen=True)
class FetchStats:
    """A snapshot of the fetcher's counters."""

    bytes_downloaded: int = 0   # bytes received from the source: payload bodies (also of failed requests) and manifests
    bytes_from_cache: int = 0   # payload and manifest bytes read from the disk cache instead
    requests: int = 0           # requests sent to the source (manifest and payloads)
    retries: int = 0            # failed attempts that will be (or were) tried again
    failures: dict[str, int] = field(default_factory=dict)  # failed attempts by kind (sources.KINDS)
    cancelled: int = 0          # in-flight requests cancelled because their key left the wanted list
    delivered: int = 0          # payloads handed to done()
    cache_hits: int = 0         # of which read from the disk cache
    in_flight: int = 0          # requests running now (network and disk cache)
    queued: int = 0             # wanted keys waiting (not in flight, not delivered)
    offline: bool = False       # the last network attempt could not reach the server (or the manifest is unconfirmed)
    manifest_source: str = ""   # MANIFEST_*
    last_error: str = ""        # the last failure's one-line message


_LIVE: weakref.WeakSet[Fetcher] = weakref.WeakSet()


def _close_live_fetchers() -> None:
    """At interpreter exit, before the thread pools stop: close fetchers their owners left open (no tracebacks
    from a loop that loses its executor mid-request)."""
    for fetcher in list(_LIVE):
        fetcher.close(0.5)


# threading's exit hooks run before atexit's and before concurrent.futures stops its pools (last registered,
# first run); a fetcher's loop thread is a daemon, so nothing else would stop it in time.
getattr(threading, "_register_atexit", lambda fn: None)(_close_live_fetchers)


class _Job:
    __slots__ = ("key", "entry", "via_cache", "task")

    def __init__(self, key: Key, entry: PayloadEntry, via_cache: bool):
        self.key, self.entry, self.via_cache = key, entry, via_cache
        self.task: asyncio.Task | None = None


class _GatedSelector(selectors.DefaultSelector):
    """The event loop's selector: after a wait that found I/O, waits for the gate's event (Fetcher.yield_to)."""

    gate: tuple[threading.Event, float] | None = None

    def select(self, timeout=None):
        ready = super().select(timeout)
        gate = self.gate
        if ready and gate is not None:
            gate[0].wait(gate[1])
        return ready


class Fetcher:
    """Fetches a scene's manifest and payloads from `source` on a background event loop (see the module doc).

    `request_timeout_s`: longest wait for a response's headers (connect included). `stall_timeout_s`: longest
    gap without body bytes once the headers came. `request_deadline_s`: longest time one request may take in all.
    `manifest_timeout_s`: how long `manifest()` may take in all, retries included.
    `cache_readers`: disk-cache reads running beside the network requests. `seed`: the jitter's random seed."""

    def __init__(self, source: SceneSource, *, cache: DiskCache | None = None, max_in_flight: int = 6,
                 request_timeout_s: float = 15.0, stall_timeout_s: float = 10.0, retry: RetryPolicy | None = None,
                 manifest_timeout_s: float = 30.0, cache_readers: int = 2, seed: int | None = None,
                 request_deadline_s: float = 60.0):
        if max_in_flight < 1 or cache_readers < 1:
            raise UsageError(f"max_in_flight {max_in_flight}, cache_readers {cache_readers}: expected at least 1")
        if request_timeout_s <= 0 or stall_timeout_s <= 0 or manifest_timeout_s < 0 or request_deadline_s <= 0:
            raise UsageError("request, stall, deadline and manifest timeouts must be positive")
        self.request_deadline_s = request_deadline_s
        self.source = source
        # Local stores are not worth a disk cache: their bytes are on this machine already.
        self.cache = cache if getattr(source, "cache_key", None) else None
        self.max_in_flight = max_in_flight
        self.cache_readers = cache_readers
        self.request_timeout_s = request_timeout_s
        self.stall_timeout_s = stall_timeout_s
        self.manifest_timeout_s = manifest_timeout_s
        self.retry = retry or RetryPolicy()
        self._rng = random.Random(seed)

        self._lock = threading.Lock()
        self._wanted: dict[Key, tuple[float, PayloadEntry]] = {}  # insertion order = service order
        self._jobs: dict[Key, _Job] = {}        # in flight
        self._ready: list[Result] = []          # delivered, not yet drained by done()
        self._undrained: set[Key] = set()
        self._retry_at: dict[Key, float] = {}   # per-key backoff (loop time)
        self._key_failures: dict[Key, int] = {}
        self._link_failures = 0
        self._link_until = 0.0                  # no network request before this loop time
        self._counts = {"bytes_downloaded": 0, "bytes_from_cache": 0, "requests": 0, "retries": 0, "cancelled": 0,
                        "delivered": 0, "cache_hits": 0}
        self._failures: dict[str, int] = {}
        self._offline = False
        self._manifest_source = ""
        self._manifest_bytes: bytes | None = None  # what manifest() returned, as bytes
        self._last_error = ""
        self._key_errors: dict[Key, tuple[str, int]] = {}  # wanted keys failing now: (last message, attempts)
        self._rejected: set[str] = set()  # SHA-256 of payloads that verified but do not decode (reject())
        # A local store's payloads that failed LOCAL_ATTEMPTS times (damaged or missing): SHA-256 -> the failure,
        # in the order found. Never requested again: the same bytes would be read.
        self._damaged: dict[str, FetchError] = {}
        self._local = bool(getattr(source, "local", False))
        self._manifest_etag: str | None = None
        self._manifest_data: bytes | None = None
        self._recheck: asyncio.Task | None = None
        self._recheck_at = -float("inf")
        self._new_manifest: tuple[bytes, Manifest] | None = None

        self._selector = _GatedSelector()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._closed = False
        self._pump_pending = False
        self._timer: asyncio.TimerHandle | None = None
        self._timer_at = float("inf")

    # -- life cycle -----------------------------------------------------------------------------------------------
    def start(self) -> Fetcher:
        if self._thread is not None:
            return self
        if self._closed:
            raise UsageError("this fetcher was closed; make a new one")
        self._loop = asyncio.SelectorEventLoop(self._selector)
        self._loop.set_exception_handler(_log_loop_exception)
        started = threading.Event()

        def main() -> None:
            asyncio.set_event_loop(self._loop)
            self._loop.call_soon(started.set)
            try:
                self._loop.run_forever()
            finally:
                try:
                    self._loop.run_until_complete(self._loop.shutdown_asyncgens())
                    self._loop.run_until_complete(self._loop.shutdown_default_executor())
                finally:
                    self._loop.close()

        self._thread = threading.Thread(target=main, name="splatstream-fetch", daemon=True)
        self._thread.start()
        started.wait()
        _LIVE.add(self)
        if self.cache is not None:  # read the cache's index now, not in the first pump
            self._loop.call_soon_threadsafe(lambda: self._loop.run_in_executor(None, self.cache.contains, ""))
        return self

    def yield_to(self, idle: threading.Event | None, timeout_s: float = 0.05) -> None:
        """When I/O is ready, handle it only while `idle` is set (at most timeout_s later): a frame loop clears it
        during its CPU work. The loop's Python (responses, callbacks) then runs while the frame loop waits for the
        GPU, instead of taking the interpreter lock from it at each of its numpy calls. None: no waiting."""
        self._selector.gate = None if idle is None else (idle, float(timeout_s))

    def close(self, timeout_s: float = 1.0) -> None:
        """Cancel everything, close the source's connections and stop the loop thread (within about timeout_s)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        if self._loop is None or self._thread is None:
            return
        deadline = time.monotonic() + timeout_s
        try:
            asyncio.run_coroutine_threadsafe(self._shutdown(timeout_s * 0.5), self._loop).result(timeout_s)
        except (concurrent.futures.TimeoutError, concurrent.futures.CancelledError, RuntimeError):
            pass
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(max(0.0, deadline - time.monotonic()) + 0.5)

    async def _shutdown(self, timeout_s: float) -> None:
        if self._timer is not None:
            self._timer.cancel()
        current = asyncio.current_task()
        tasks = [t for t in asyncio.all_tasks() if t is not current]
        for t in tasks:
            t.cancel()
        if tasks:
            await asyncio.wait(tasks, timeout=timeout_s)
        try:
            async with asyncio.timeout(timeout_s):
                await self.source.aclose()
        except (TimeoutError, Exception):  # closing is best effort: never a traceback at exit
            log.debug("closing %s failed", self.source.location, exc_info=True)

    def __enter__(self) -> Fetcher:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()

    def _require_running(self) -> asyncio.AbstractEventLoop:
        if self._loop is None:
            raise UsageError("the fetcher is not started (call start() or use it as a context manager)")
        if self._closed:
            raise UsageError("the fetcher is closed")
        return self._loop

    # -- the render thread's API ----------------------------------------------------------------------------------
    def manifest(self, timeout_s: float | None = None) -> Manifest:
        """The scene's manifest, fetched (retried on transient failures for up to `timeout_s`, default
        manifest_timeout_s) and parsed here, once (payload entries checked when first read): the session, its
        engine and whoever else needs it share this Manifest. Its bytes: `manifest_bytes`. Raises FetchError: at
        once when the scene does not exist or is not a scene, at the deadline when the server stays unreachable
        and nothing is cached."""
        loop = self._require_running()
        limit = self.manifest_timeout_s if timeout_s is None else timeout_s
        fut = asyncio.run_coroutine_threadsafe(self._get_manifest(limit), loop)
        try:
            return fut.result()
        except concurrent.futures.CancelledError:
            raise FetchError(self.source.location, "closed", "the fetcher was closed", transient=False) from None

    @property
    def manifest_bytes(self) -> bytes | None:
        """The bytes of the manifest the last manifest() call returned (None before one did)."""
        return self._manifest_bytes

    def want(self, requests: Iterable[Request]) -> None:
        """Replace the wanted list: (priority, key, entry), best first (the list's order is the service order;
        `priority` is informative). List only what you do not hold yet; keys whose bytes wait in done() are
        ignored, and a key leaves the list when it is delivered. Keys in flight that are no longer listed
        (or now name another payload) are cancelled: no result for them is delivered after this call returns."""
        loop = self._require_running()
        wanted: dict[Key, tuple[float, PayloadEntry]] = {}
        for priority, key, entry in requests:
            if key not in wanted:
                wanted[key] = (priority, entry)
        cancelled = []
        with self._lock:
            for key in self._undrained:  # delivered already: its bytes wait in done()
                wanted.pop(key, None)
            for key, job in list(self._jobs.items()):
                w = wanted.get(key)
                if w is None or w[1].sha256 != job.entry.sha256:
                    del self._jobs[key]
                    cancelled.append(job)
            for key in [k for k in self._retry_at if k not in wanted]:
                del self._retry_at[key]
                self._key_failures.pop(key, None)
            for key in [k for k in self._key_errors if k not in wanted]:
                del self._key_errors[key]
            self._counts["cancelled"] += len(cancelled)
            self._wanted = wanted
            self._schedule_pump()
        for job in cancelled:
            if job.task is not None:
                loop.call_soon_threadsafe(job.task.cancel)

    def done(self) -> list[Result]:
        """Verified payloads completed since the last call: (key, entry, VerifiedPayload), in completion order."""
        with self._lock:
            out, self._ready = self._ready, []
            for key, _, _ in out:
                self._undrained.discard(key)
        return out

    def stats(self) -> FetchStats:
        with self._lock:
            # the wanted keys not in flight, counted over those in flight (a few) rather than over the wanted
            # (hundreds: the stats are asked for every frame, on the frame thread)
            wanted = self._wanted
            queued = len(wanted) - sum(1 for k in self._jobs if k in wanted)
            return FetchStats(failures=dict(self._failures), in_flight=len(self._jobs), queued=queued,
                              offline=self._offline, manifest_source=self._manifest_source,
                              last_error=self._last_error, **self._counts)

    def where(self, entry: PayloadEntry) -> str:
        """The payload's URL (or path), as messages name it."""
        url = getattr(self.source, "payload_url", None)
        return url(entry) if url else f"{self.source.location}/{entry.file}"

    def failing(self) -> list[tuple[Key, str, int]]:
        """Wanted payloads whose last attempt failed: (key, the failure's one-line message naming the URL, failed
        attempts in a row), most attempts first."""
        with self._lock:
            return sorted(((k, m, n) for k, (m, n) in self._key_errors.items()), key=lambda t: -t[2])

    def damaged(self) -> list[FetchError]:
        """A local store's payloads that failed permanently (size or SHA-256 against the manifest, or missing:
        LOCAL_PERMANENT_KINDS, LOCAL_ATTEMPTS times), in the order found; each message names the file. Empty for
        HTTP sources: their failures are retried while wanted."""
        with self._lock:
            return list(self._damaged.values())

    def reject(self, entry: PayloadEntry) -> None:
        """A delivered payload matched its checksum but does not decode (the scene is broken): drop it from the
        disk cache, and never cache it again in this fetcher."""
        with self._lock:
            self._rejected.add(entry.sha256)
        if self.cache is not None:
            self.cache.discard(entry.sha256)

    def take_new_manifest(self) -> tuple[bytes, Manifest] | None:
        """A newer manifest of the scene, found after payloads of the one held answered 404 (the scene was
        re-encoded, http.md 10), once: (bytes, parsed). The caller continues with it (StreamingSession)."""
        with self._lock:
            out, self._new_manifest = self._new_manifest, None
        return out

    @property
    def idle(self) -> bool:
        """Nothing wanted is waiting or in flight (everything listed was delivered)."""
        with self._lock:
            return not self._jobs and not self._wanted

    # -- the loop thread ------------------------------------------------------------------------------------------
    def _schedule_pump(self) -> None:
        """(lock held) Run _pump soon on the loop, once however many changes come before it runs."""
        if not self._pump_pending and not self._closed:
            self._pump_pending = True
            self._loop.call_soon_threadsafe(self._pump)

    def _pump(self) -> None:
        """Start the best wanted keys that can start: network requests up to max_in_flight (unless the link is
        backing off), disk-cache reads up to cache_readers."""
        loop = self._loop
        with self._lock:
            self._pump_pending = False
            if self._closed:
                return
            now = loop.time()
            net = sum(1 for j in self._jobs.values() if not j.via_cache)
            disk = len(self._jobs) - net
            link_open = now >= self._link_until
            busy_shas = {j.entry.sha256 for j in self._jobs.values()}
            wake = float("inf") if link_open else self._link_until
            lookahead = CACHE_LOOKAHEAD
            for key, (_, entry) in self._wanted.items():
                net_full = net >= self.max_in_flight or not link_open
                if net_full:
                    # Only disk-cache hits can start now; look for them near the front of the list only, so a
                    # long list costs little per completion.
                    lookahead -= 1
                    if self.cache is None or disk >= self.cache_readers or lookahead < 0:
                        break
                if key in self._jobs or entry.sha256 in self._damaged:
                    continue
                at = self._retry_at.get(key)
                if at is not None and at > now:
                    wake = min(wake, at)
                    continue
                if entry.sha256 in busy_shas:  # the same bytes are on their way for another key
                    continue
                via_cache = self.cache is not None and self.cache.contains(entry.sha256)
                if via_cache:
                    if disk >= self.cache_readers:
                        continue
                    disk += 1
                else:
                    if net_full:
                        continue
                    net += 1
                    self._counts["requests"] += 1
                busy_shas.add(entry.sha256)
                job = _Job(key, entry, via_cache)
                self._jobs[key] = job
                job.task = loop.create_task(self._run(job))
            if wake < self._timer_at:
                if self._timer is not None:
                    self._timer.cancel()
                self._timer_at = wake
                self._timer = loop.call_at(wake, self._on_timer)

    def _on_timer(self) -> None:
        with self._lock:
            self._timer, self._timer_at = None, float("inf")
        self._pump()

    async def _run(self, job: _Job) -> None:
        loop = asyncio.get_running_loop()
        entry = job.entry
        try:
            if job.via_cache:
                data = await loop.run_in_executor(None, self.cache.get, entry)
                self._complete(job, data, from_cache=True)  # None (damaged or evicted meanwhile): to the network
                return
            where = self.where(entry)
            data = await self._timed(lambda on_bytes: self.source.fetch_payload(entry, on_bytes), where)
            try:
                payload = await loop.run_in_executor(None, verify_payload, data, entry, where)
            except FormatError as exc:
                if not self._local:
                    raise FetchError(where, CHECKSUM, exc.problem) from None
                # A local file: name the field and both values (this message may be the one the view stops on).
                problem = exc.problem
                if exc.field == "sha256":
                    problem = (f"SHA-256 {sha256_hex(data)}, the manifest says {entry.sha256} (the file is damaged "
                               "or was replaced)")
                raise FetchError(where, CHECKSUM, problem, field=exc.field) from None
            if self._complete(job, payload, from_cache=False) and self.cache is not None:
                loop.run_in_executor(None, self._cache_put, entry, payload.data)  # never raises; awaited at shutdown
        except asyncio.CancelledError:
            raise
        except FetchError as exc:
            self._failed(job, exc)
        except Exception as exc:  # a bug must not kill the loop or leave the key stuck: log, count, retry
            if self._closed:
                return
            log.exception("fetching %s failed unexpectedly", entry.file)
            self._failed(job, FetchError(self.source.location, "internal", f"{type(exc).__name__}: {exc}"))

    async def _timed(self, request: Callable[[OnBytes], Awaitable], where: str, until: float | None = None):
        """Run one request: TIMEOUT when its headers take longer than request_timeout_s, STALL when its body
        pauses for stall_timeout_s or the whole request takes longer than request_deadline_s (a server that drips
        a byte at a time resets no timer for ever); every byte received is counted. `until`: a loop time by which
        the request must be complete, whatever the timers say (FetchError TIMEOUT, not transient)."""
        loop = asyncio.get_running_loop()
        started = loop.time()
        hard = started + self.request_deadline_s
        if until is not None:
            hard = min(hard, until)
        headers = False
        received = 0
        cm = asyncio.timeout(min(started + self.request_timeout_s, hard) - started)

        def on_bytes(n: int) -> None:
            nonlocal headers, received
            if not headers:
                headers = True
                self._link_up()
            if n:
                received += n
                with self._lock:
                    self._counts["bytes_downloaded"] += n
            cm.reschedule(min(loop.time() + self.stall_timeout_s, hard))

        try:
            async with cm:
                return await request(on_bytes)
        except TimeoutError:
            if not cm.expired():
                raise
            now = loop.time()
            got = "no answer" if not headers else f"{received} bytes received"
            if until is not None and now >= until - 1e-3:
                raise FetchError(where, TIMEOUT, f"not complete in time ({got} in the last attempt's "
                                 f"{until - started:.3g} s)", transient=False) from None
            if now >= hard - 1e-3:
                raise FetchError(where, STALL, f"not complete within {self.request_deadline_s:g} s ({got}: too "
                                 "slow)") from None
            if headers:
                raise FetchError(where, STALL, f"no data for {self.stall_timeout_s:g} s (stalled)") from None
            raise FetchError(where, TIMEOUT, f"no answer within {self.request_timeout_s:g} s") from None

    def _cache_put(self, entry: PayloadEntry, data: bytes) -> None:
        """Store verified bytes, unless the payload was rejected as undecodable (also meanwhile: removed again)."""
        if entry.sha256 in self._rejected:
            return
        self.cache.put(entry, data)
        if entry.sha256 in self._rejected:
            self.cache.discard(entry.sha256)

    def _link_up(self) -> None:
        with self._lock:
            self._link_failures = 0
            self._link_until = 0.0
            self._offline = False

    def _complete(self, job: _Job, data: VerifiedPayload | None, from_cache: bool) -> bool:
        """Deliver verified bytes to the job's key and every other waiting key of the same payload; False when the
        job was cancelled meanwhile (nothing delivered)."""
        with self._lock:
            if self._jobs.get(job.key) is not job:
                return False
            del self._jobs[job.key]
            if data is not None:
                sha = job.entry.sha256
                keys = [job.key] + [k for k, (_, e) in self._wanted.items()
                                    if e.sha256 == sha and k != job.key and k not in self._jobs]
                for key in keys:
                    self._ready.append((key, self._wanted.pop(key, (0.0, job.entry))[1], data))
                    self._undrained.add(key)
                    self._retry_at.pop(key, None)
                    self._key_failures.pop(key, None)
                    self._key_errors.pop(key, None)
                self._counts["delivered"] += len(keys)
                if from_cache:
                    self._counts["cache_hits"] += 1
                    self._counts["bytes_from_cache"] += len(data)
            self._schedule_pump()
            return data is not None

    def _failed(self, job: _Job, exc: FetchError) -> None:
        with self._lock:
            self._failures[exc.kind] = self._failures.get(exc.kind, 0) + 1
            self._last_error = str(exc)
            if self._jobs.get(job.key) is not job:
                return  # cancelled meanwhile
            del self._jobs[job.key]
            now = self._loop.time()
            previous = self._key_errors.get(job.key)
            self._key_errors[job.key] = (str(exc), (previous[1] if previous else 0) + 1)
            if self._local and exc.kind in LOCAL_PERMANENT_KINDS and \
                    self._key_errors[job.key][1] >= LOCAL_ATTEMPTS:
                # Reading the same file a third time gives the same bytes: permanent (damaged()).
                self._damaged.setdefault(job.entry.sha256, exc)
                self._retry_at.pop(job.key, None)
                self._schedule_pump()
                log.debug("giving up: %s", exc)
                return
            if exc.kind == NOT_FOUND:
                self._recheck_manifest_soon(now)
            if exc.kind in LINK_KINDS:
                self._link_failures += 1
                self._link_until = now + self.retry.delay(self._link_failures, self._rng)
                self._offline = True
            else:
                n = self._key_failures[job.key] = self._key_failures.get(job.key, 0) + 1
                self._retry_at[job.key] = now + self.retry.delay(n, self._rng)
            self._counts["retries"] += 1
            self._schedule_pump()
        log.debug("retrying: %s", exc)

    # -- the manifest ---------------------------------------------------------------------------------------------
    def _recheck_manifest_soon(self, now: float) -> None:
        """(lock held) A payload answered 404: revalidate the manifest (If-None-Match), at most every
        MANIFEST_RECHECK_S; a new version is offered through take_new_manifest (http.md 10)."""
        revalidate = getattr(self.source, "revalidate_manifest", None)
        if revalidate is None or self._manifest_data is None or now < self._recheck_at + MANIFEST_RECHECK_S or \
                (self._recheck is not None and not self._recheck.done()):
            return
        self._recheck_at = now
        self._recheck = self._loop.create_task(self._recheck_manifest(revalidate))

    async def _recheck_manifest(self, revalidate) -> None:
        try:
            reply = await self._timed(lambda on_bytes: revalidate(self._manifest_etag, on_bytes),
                                      self.source.location)
            if reply.data is None or reply.data == self._manifest_data:
                return  # the same version: the 404s are the server's problem (retried, and named at a timeout)
            loop = asyncio.get_running_loop()
            parsed = await loop.run_in_executor(None, lambda: parse_manifest(reply.data, self.source.location,
                                                                             lazy_payloads=True))
        except (FetchError, FormatError) as exc:
            log.debug("manifest recheck failed: %s", exc)
            return
        key = getattr(self.source, "cache_key", None)
        if self.cache is not None and key:
            await asyncio.get_running_loop().run_in_executor(None, self.cache.put_manifest, key, reply.data,
                                                             reply.etag)
        with self._lock:
            self._manifest_data, self._manifest_etag = reply.data, reply.etag
            self._new_manifest = (reply.data, parsed)
            self._counts["requests"] += 1
        log.info("%s: the scene was re-encoded; continuing with its new manifest", self.source.location)

    async def _get_manifest(self, limit_s: float) -> Manifest:
        loop = asyncio.get_running_loop()
        key = getattr(self.source, "cache_key", None)
        cached = None
        if self.cache is not None and key:
            cached = await loop.run_in_executor(None, self.cache.get_manifest, key)
        revalidate = getattr(self.source, "revalidate_manifest", None)
        deadline = loop.time() + limit_s
        until = deadline if limit_s > 0 else None  # 0: one attempt, as long as the request's own timers allow
        attempt = 0
        while True:
            with self._lock:
                self._counts["requests"] += 1
            try:
                if revalidate is not None:
                    etag = cached.etag if cached is not None else None
                    reply = await self._timed(lambda on_bytes, etag=etag: revalidate(etag, on_bytes),
                                              self.source.location, until)
                else:
                    reply = ManifestReply(await self._timed(self.source.fetch_manifest, self.source.location,
                                                            until), None)
                if reply.data is None:
                    if cached is None:
                        raise FetchError(self.source.location, NOT_A_SCENE, "304 Not Modified for a manifest "
                                         "that was not asked for conditionally", transient=False)
                    self._manifest_data, self._manifest_etag = cached.data, reply.etag or cached.etag
                    return self._manifest_done(cached.data, MANIFEST_REVALIDATED, from_cache=True)
                try:
                    parsed = parse_manifest(reply.data, self.source.location, lazy_payloads=True)
                except FormatError as exc:
                    where = getattr(self.source, "manifest_location", self.source.location)
                    detail = f"{exc.field + ': ' if exc.field else ''}{exc.problem}"
                    # a manifest whose checksum does not match is a corrupt one, not another kind of file: said as
                    # info and decode say it ('not a splatstream manifest (checksum: ...)' before, newuser64)
                    raise FetchError(where, NOT_A_SCENE, detail if exc.field == CHECKSUM_KEY else
                                     f"not a splatstream manifest ({detail})", transient=False) from None
                if self.cache is not None and key:
                    await loop.run_in_executor(None, self.cache.put_manifest, key, reply.data, reply.etag)
                self._manifest_data, self._manifest_etag = reply.data, reply.etag
                return self._manifest_done(reply.data, MANIFEST_LOCAL if key is None else MANIFEST_NETWORK,
                                           parsed=parsed)
            except FetchError as exc:
                with self._lock:
                    self._failures[exc.kind] = self._failures.get(exc.kind, 0) + 1
                    self._last_error = str(exc)
                    if exc.kind in LINK_KINDS:
                        self._offline = True
                if not exc.transient:
                    if exc.kind == TIMEOUT and until is not None:
                        if cached is not None:
                            return self._manifest_done(cached.data, MANIFEST_OFFLINE, from_cache=True)
                        raise FetchError(self.source.location, TIMEOUT, f"no complete manifest within {limit_s:g} s:"
                                         f" {exc.problem}", transient=False) from None
                    raise
                if exc.unreachable and cached is None and attempt == 0:
                    # Nothing cached and the server was never reached (refused, unknown host): say so at once
                    # rather than polling a server that is probably not there (a user runs the command again).
                    raise
                if cached is not None and exc.kind in LINK_KINDS:
                    return self._manifest_done(cached.data, MANIFEST_OFFLINE, from_cache=True)
                attempt += 1
                delay = self.retry.delay(attempt, self._rng)
                if loop.time() + delay > deadline:
                    if cached is not None:
                        return self._manifest_done(cached.data, MANIFEST_OFFLINE, from_cache=True)
                    raise
                with self._lock:
                    self._counts["retries"] += 1
                await asyncio.sleep(delay)

    def _manifest_done(self, data: bytes, source: str, from_cache: bool = False,
                       parsed: Manifest | None = None) -> Manifest:
        """The manifest parsed (a cached copy is parsed here: it was valid when stored, and is checked again by
        this reader), its bytes and origin kept."""
        if parsed is None:
            parsed = parse_manifest(data, self.source.location, lazy_payloads=True)
        with self._lock:
            self._manifest_source = source
            self._manifest_bytes = data
            if source == MANIFEST_OFFLINE:
                self._offline = True
            if from_cache:
                self._counts["bytes_from_cache"] += len(data)
        return parsed


def _log_loop_exception(loop: asyncio.AbstractEventLoop, context: dict) -> None:
    """Nothing on the fetcher's loop may print a traceback: unexpected exceptions go to the debug log."""
    log.debug("fetch loop: %s", context.get("message"), exc_info=context.get("exception"))


__all__ = ["Fetcher", "FetchStats", "RetryPolicy", "FetchError", "TIMEOUT", "STALL"]
