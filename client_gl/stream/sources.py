"""Where a streamed scene's bytes come from: an HTTP server, a scene directory, or a splat file encoded in memory.

A `SceneSource` gives the manifest's bytes and a payload's bytes, asynchronously (the fetcher runs it on its own
event loop). Sources do not verify, cache or retry: the fetcher does (client_gl/stream/fetch.py). They report
failures as `FetchError`, whose `kind` says what went wrong (the fetcher retries by kind) and whose message is one
line naming the URL or path and what was expected.

`open_source(spec)` turns what a user typed into a source: `http(s)://HOST/scenes/ID` (or the manifest URL), a
scene directory (or its manifest file), or any splat file splatstream.io reads (encoded in memory, LOD on).
"""
from __future__ import annotations

import asyncio
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Protocol, runtime_checkable

import aiohttp  # imported with the module, not at the first request: the first frame should not wait for it
import yarl

from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.errors import InputError, UsageError
from splatstream.format.manifest import MAX_MANIFEST_BYTES, PayloadEntry
from splatstream.format.names import MANIFEST_NAME, TILESET_NAME, manifest_url, payload_url
from splatstream.io import declared_up, read_gaussians
from splatstream.rad_import import encode_rad
from splatstream.readers.rad import is_rad
from splatstream.readers.sog import SOG_META_NAME
from splatstream.sog_import import encode_streamed_sog
from splatstream.store import DirectoryStore, FsspecStore, MemoryStore, SceneStore

# on_bytes(n): called with 0 when a response's headers arrive, then with the size of each body chunk received.
OnBytes = Callable[[int], None]
# progress(stage, fraction in [0, 1]) while a splat file is read and encoded
Progress = Callable[[str, float], None]

# FetchError kinds. Transient ones are retried by the fetcher; permanent ones end a manifest request at once.
CONNECTION = "connection"  # refused, reset, DNS, server disconnected: the link or the server is gone
TIMEOUT = "timeout"        # no response headers within the request timeout
STALL = "stall"            # headers came, then no body bytes for the stall timeout
TRUNCATED = "truncated"    # the body ended before its Content-Length, or was longer than expected
CHECKSUM = "checksum"      # size or SHA-256 differs from the manifest
HTTP_5XX = "http_5xx"
NOT_FOUND = "not_found"    # 404 (a payload: the scene was re-encoded; a manifest: no such scene)
HTTP_4XX = "http_4xx"      # any other 4xx
MISSING = "missing"        # a local store lacks a file the manifest names, or cannot read it
NOT_A_SCENE = "not_a_scene"  # a 200 answer that is not a manifest
KINDS = (CONNECTION, TIMEOUT, STALL, TRUNCATED, CHECKSUM, HTTP_5XX, NOT_FOUND, HTTP_4XX, MISSING, NOT_A_SCENE)
# Errors of the link rather than of one file: the fetcher backs off all network requests together on these.
LINK_KINDS = frozenset({CONNECTION, TIMEOUT})
# Failures of a local store's file that reading it again will not heal (the same bytes come back): the fetcher
# makes them permanent after LOCAL_ATTEMPTS attempts (the second read guards against a re-encode renaming the file
# in mid-read). Over HTTP the same kinds stay transient: a cache or a server may heal.
LOCAL_PERMANENT_KINDS = frozenset({CHECKSUM, MISSING, TRUNCATED})
LOCAL_ATTEMPTS = 2


class FetchError(InputError):
    """A request failed. `kind` is one of KINDS; `transient` says whether trying again may help; `unreachable`:
    the server was never reached (connection refused, unknown host), so a first request need not wait for it."""

    def __init__(self, where: str, kind: str, problem: str, transient: bool = True, unreachable: bool = False,
                 field: str | None = None):
        super().__init__(where, field, problem)
        self.kind = kind
        self.transient = transient
        self.unreachable = unreachable


@runtime_checkable
class SceneSource(Protocol):
    """One scene's bytes. `location` names it in messages; `cache_key` is the manifest's URL for sources worth a
    disk cache (None: local bytes, not cached). `local`: reading again gives the same bytes (a store on this
    machine), so a damaged or missing payload is permanent (LOCAL_PERMANENT_KINDS); absent means False."""

    location: str
    cache_key: str | None

    async def fetch_manifest(self, on_bytes: OnBytes | None = None) -> bytes: ...

    async def fetch_payload(self, entry: PayloadEntry, on_bytes: OnBytes | None = None) -> bytes: ...

    async def aclose(self) -> None: ...


@dataclass(frozen=True)
class ManifestReply:
    """An answer to a conditional manifest request: `data` None means 304 (the cached copy is current)."""

    data: bytes | None
    etag: str | None


# --------------------------------------------------------------------------------------------------------------
# HTTP


class HttpSource:
    """A scene served over HTTP (format_spec/http.md): `http(s)://HOST/scenes/ID`, with or without a trailing
    slash, or the manifest's URL. Payload URLs are resolved against the manifest URL (http.md section 2).

    Uses one aiohttp ClientSession (keep-alive connections, at most `connections` at a time), created on first
    use in the running event loop; `aclose()` closes it."""

    def __init__(self, url: str, *, connections: int = 8):
        try:
            parsed = yarl.URL(url)
        except (ValueError, TypeError) as exc:
            raise UsageError(f"{url}: not a valid URL ({exc})") from None
        if parsed.scheme not in ("http", "https") or not parsed.host:
            raise UsageError(f"{url}: expected an http:// or https:// URL of a scene (http://HOST/scenes/ID)")
        if parsed.path in ("", "/"):
            raise UsageError(f"{url}: expected the URL of a scene (http://HOST/scenes/ID), not of the server; "
                             f"the server lists its scenes at {parsed.with_path('/api/scenes')}")
        self.manifest_url = manifest_url(url)
        self.location = self.manifest_url
        self.cache_key: str | None = self.manifest_url
        self.connections = connections
        self._session = None
        self._session_loop: asyncio.AbstractEventLoop | None = None

    def payload_url(self, entry: PayloadEntry) -> str:
        return payload_url(self.manifest_url, entry.file)

    def _get_session(self) -> aiohttp.ClientSession:
        loop = asyncio.get_running_loop()
        if self._session is None or self._session_loop is not loop or self._session.closed:
            connector = aiohttp.TCPConnector(limit=self.connections, enable_cleanup_closed=True)
            # No aiohttp timeout: the fetcher times requests itself (time to headers, then stalls of the body).
            # Accept-Encoding identity: payloads and manifests are never compressed again (http.md 7); a CDN that
            # gzips them anyway is decoded (aiohttp's auto_decompress) and the decoded bytes are what is checked.
            self._session = aiohttp.ClientSession(
                connector=connector, timeout=aiohttp.ClientTimeout(total=None),
                headers={"User-Agent": "splatstream-client", "Accept-Encoding": "identity"})
            self._session_loop = loop
        return self._session

    async def aclose(self) -> None:
        if self._session is not None and not self._session.closed:
            await self._session.close()
        self._session = None

    async def _get(self, url: str, limit: int, what: str, on_bytes: OnBytes | None,
                   headers: dict[str, str] | None = None) -> tuple[int, bytes, str | None]:
        """(status, body, ETag) of a GET; the body is refused beyond `limit` bytes; errors as FetchError."""
        try:
            async with self._get_session().get(url, headers=headers, allow_redirects=True) as resp:
                if on_bytes:
                    on_bytes(0)
                etag = resp.headers.get("ETag")
                if resp.status == 304:
                    return 304, b"", etag
                if resp.status != 200:
                    raise _status_error(url, resp.status, what)
                encoded = resp.headers.get("Content-Encoding", "identity").strip().lower() not in ("", "identity")
                if not encoded and resp.content_length is not None and resp.content_length > limit:
                    raise FetchError(url, TRUNCATED, f"the server sends {resp.content_length} bytes, expected at "
                                     f"most {limit} for {what}")
                body = bytearray()
                async for chunk in resp.content.iter_any():
                    body += chunk
                    if on_bytes:
                        on_bytes(len(chunk))
                    if len(body) > limit:
                        raise FetchError(url, TRUNCATED, f"more than the {limit} bytes expected for {what}")
                return 200, bytes(body), etag
        except FetchError:
            raise
        except aiohttp.ClientPayloadError as exc:
            raise FetchError(url, TRUNCATED, f"{what}: the body was cut short ({_payload_reason(exc)})") from None
        except aiohttp.ClientConnectorDNSError as exc:
            raise FetchError(url, CONNECTION, f"unknown host {exc.host!r} (the name does not resolve: "
                             f"{_dns_reason(exc)})", unreachable=True) from None
        except aiohttp.ClientConnectorError as exc:
            refused = isinstance(exc.os_error, ConnectionRefusedError)
            raise FetchError(url, CONNECTION, f"cannot connect to {exc.host}:{exc.port} ({_reason(exc)}); is the "
                             f"server running?", unreachable=refused) from None
        except aiohttp.TooManyRedirects as exc:
            hops = len(exc.history)
            raise FetchError(url, HTTP_4XX, f"too many redirects ({hops} followed, last to "
                             f"{exc.request_info.real_url}): a redirect loop?", transient=False) from None
        except (aiohttp.ClientConnectionError, ConnectionError) as exc:  # disconnected, reset
            raise FetchError(url, CONNECTION, f"connection lost ({_reason(exc)})") from None
        except aiohttp.ClientError as exc:  # too many redirects, invalid answer
            raise FetchError(url, HTTP_4XX, f"request failed ({_reason(exc)})") from None

    async def fetch_manifest(self, on_bytes: OnBytes | None = None) -> bytes:
        return (await self.revalidate_manifest(None, on_bytes)).data or b""

    async def revalidate_manifest(self, etag: str | None, on_bytes: OnBytes | None = None) -> ManifestReply:
        """GET the manifest, with If-None-Match when `etag` is given: a 304 gives data None."""
        headers = {"If-None-Match": etag} if etag else None
        status, body, new_etag = await self._get(self.manifest_url, MAX_MANIFEST_BYTES, "a manifest", on_bytes,
                                                 headers)
        if status == 304:
            return ManifestReply(None, new_etag or etag)
        return ManifestReply(body, new_etag)

    async def fetch_payload(self, entry: PayloadEntry, on_bytes: OnBytes | None = None) -> bytes:
        return (await self._get(self.payload_url(entry), entry.bytes, f"a {entry.bytes}-byte payload", on_bytes))[1]


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
    os_error = getattr(exc, "os_error", exc)
    if isinstance(os_error, OSError) and os_error.errno:  # asyncio's strerror is "Connect call failed (...)"
        text = os.strerror(os_error.errno).lower()
    return text or type(exc).__name__


def _payload_reason(exc: BaseException) -> str:
    """aiohttp's payload errors nest reprs ("Response payload is not completed: <ContentLengthError: 400, ...>"):
    the byte counts when it gives them, else its first line."""
    import re

    m = re.search(r"received (\d+) of (\d+) bytes", str(exc))
    if m:
        return f"{m.group(1)} of {m.group(2)} bytes received, then the connection closed"
    return _reason(exc)


def _dns_reason(exc: BaseException) -> str:
    os_error = getattr(exc, "os_error", None)
    text = getattr(os_error, "strerror", None) or (os_error.args[1] if os_error is not None and len(
        getattr(os_error, "args", ())) > 1 else "")
    return str(text).lower() if text else "name or service not known"


def _status_error(url: str, status: int, what: str) -> FetchError:
    is_manifest = url.endswith("/" + MANIFEST_NAME)
    if status == 404:
        if is_manifest:
            return FetchError(url, NOT_FOUND, "no such scene (the server answered 404; a scene's URL is "
                              "http://HOST/scenes/ID)", transient=False)
        return FetchError(url, NOT_FOUND, "payload named in the manifest is not on the server (404; the scene "
                          "was re-encoded?)")
    if status >= 500:
        return FetchError(url, HTTP_5XX, f"server error {status} for {what}")
    # 408 and 429 say "try again later"; other 4xx will not change by themselves.
    return FetchError(url, HTTP_4XX, f"the server refused the request ({status}) for {what}",
                      transient=status in (408, 429))


# --------------------------------------------------------------------------------------------------------------
# Local stores


class StoreSource:
    """A scene in a SceneStore: a directory on disk (reads run in a worker thread) or memory."""

    def __init__(self, store: SceneStore):
        self.store = store
        self.location = store.location
        # Where a manifest that does not parse is named: the file (a directory store's manifest_path), as `info` and
        # `decode` name it; `view DIR` named the directory.
        self.manifest_location = getattr(store, "manifest_path", store.location)
        self.cache_key: str | None = None
        self.local = True  # a damaged payload reads the same again: the fetcher gives up after LOCAL_ATTEMPTS

    async def _read(self, fn, *args) -> bytes:
        if isinstance(self.store, MemoryStore):
            return fn(*args)
        return await asyncio.to_thread(fn, *args)

    async def fetch_manifest(self, on_bytes: OnBytes | None = None) -> bytes:
        try:
            data = await self._read(self.store.read_manifest)
        except InputError as exc:
            raise FetchError(exc.path or self.location, NOT_A_SCENE, exc.problem, transient=False) from None
        if on_bytes:
            on_bytes(len(data))
        return data

    async def fetch_payload(self, entry: PayloadEntry, on_bytes: OnBytes | None = None) -> bytes:
        try:
            data = await self._read(self.store.read_payload, entry)
        except InputError as exc:
            kind = TRUNCATED if "bytes expected" in exc.problem else MISSING
            raise FetchError(exc.path or self.store.payload_source(entry), kind, exc.problem,
                             field="bytes" if kind == TRUNCATED else exc.field) from None
        if on_bytes:
            on_bytes(len(data))
        return data

    async def aclose(self) -> None:
        return None


# --------------------------------------------------------------------------------------------------------------
# What the user typed


OBJECT_STORE_SCHEMES = ("s3", "gs", "gcs", "az", "abfs", "memory")


def open_source(spec: str | os.PathLike, *, encode_options=None, progress: Progress | None = None,
                connections: int = 8, drop_invalid: bool = False) -> SceneSource:
    """A source for an `http(s)://` scene URL, a scene directory (or its manifest.msgpack), a PlayCanvas streamed
    SOG (lod-meta.json or its directory: its own LOD tree, encoded in memory), a Spark .rad (its own LoD tree,
    encoded in memory), or a splat file
    (3DGS PLY, compressed PLY, SPZ, .splat, SOG: a .sog, a meta.json or its directory: read and encoded in memory
    with LOD on; `progress(stage, fraction)`
    follows the read and the encode; `encode_options` an EncodeOptions; `drop_invalid`: a splat file's invalid
    splats dropped, not refused, and refused for an encoded scene). Raises UsageError or InputError with one line
    naming `spec` and what was expected."""
    text = os.fspath(spec)
    if text.startswith("file://"):
        text = text[len("file://"):]
    if "://" in text:
        scheme = text.split("://", 1)[0].lower()
        _no_splats_to_drop(drop_invalid, text)
        if scheme in OBJECT_STORE_SCHEMES:
            # An object store (through fsspec): the scene layout read object by object.
            return StoreSource(FsspecStore(text))
        if scheme not in ("http", "https"):
            raise UsageError(f"{text}: unsupported URL scheme {scheme!r} (expected http:// or https://, an object "
                             f"store URL ({', '.join(s + '://' for s in OBJECT_STORE_SCHEMES)}), a scene directory "
                             f"or a splat file)")
        return HttpSource(text, connections=connections)
    if not os.path.exists(text):
        raise InputError(text, None, "no such file or directory (expected an http(s):// scene URL, a scene "
                         "directory or a splat file)")
    if _is_streamed_sog(text):
        # Their LOD tree, converted into ours on the fly (splatstream/sog_import.py): streamed coarse to fine.
        return StoreSource(encode_streamed_sog(text, encode_options, progress))
    if _is_rad(text):
        # Spark's LoD tree of splats, converted into our tiles on the fly (splatstream/rad_import.py).
        return StoreSource(encode_rad(text, encode_options, progress))
    if os.path.basename(text) == TILESET_NAME or (os.path.isdir(text) and os.path.isfile(
            os.path.join(text, TILESET_NAME)) and not os.path.isfile(os.path.join(text, MANIFEST_NAME))):
        # export-3dtiles' output: said 'not a scene directory ... pass the splat file itself' (its tileset.json:
        # 'unrecognised file format'), no word of what it is or what draws it.
        raise InputError(text, None, "a 3D Tiles tileset (`splatstream export-3dtiles`), which CesiumJS draws "
                         "(`splatstream serve` serves it); `view` streams the scene directory it was exported from")
    if os.path.isdir(text):
        if not os.path.isfile(os.path.join(text, MANIFEST_NAME)) and \
                os.path.isfile(os.path.join(text, SOG_META_NAME)):
            # An unbundled SOG's directory, as `convert`, `render` and `encode` read it (its meta.json).
            return StoreSource(encode_splat_file(os.path.join(text, SOG_META_NAME), encode_options, progress,
                                                 drop_invalid))
        if not os.path.isfile(os.path.join(text, MANIFEST_NAME)):
            raise InputError(text, None, f"not a scene directory (no {MANIFEST_NAME}; encode a splat file with "
                             f"`splatstream encode`, or pass the splat file itself)")
        _no_splats_to_drop(drop_invalid, text)
        return StoreSource(DirectoryStore(text))
    if os.path.basename(text) == MANIFEST_NAME:
        _no_splats_to_drop(drop_invalid, text)
        return StoreSource(DirectoryStore(os.path.dirname(os.path.abspath(text))))
    return StoreSource(encode_splat_file(text, encode_options, progress, drop_invalid))


def _no_splats_to_drop(drop_invalid: bool, where: str) -> None:
    """`view --drop-invalid` of an encoded scene (its splats were screened when it was encoded): refused, not
    ignored."""
    if drop_invalid:
        raise UsageError(f"--drop-invalid: drops invalid splats of a splat file; {where} is an encoded scene")


def _is_rad(path: str) -> bool:
    """A Spark RAD file, by its magic."""
    if not os.path.isfile(path):
        return False
    with open(path, "rb") as f:
        return is_rad(f.read(4))


def _is_streamed_sog(path: str) -> bool:
    """A PlayCanvas streamed SOG: a lod-meta.json, or a directory holding one (and no manifest of ours)."""
    if os.path.isdir(path):
        return os.path.isfile(os.path.join(path, "lod-meta.json")) and \
            not os.path.isfile(os.path.join(path, MANIFEST_NAME))
    return os.path.basename(path).lower() == "lod-meta.json"


def encode_splat_file(path: str, encode_options=None, progress: Progress | None = None,
                      drop_invalid: bool = False) -> MemoryStore:
    """Read a splat file of any supported format and encode it in memory (LOD on unless the options say so;
    `drop_invalid`: its invalid splats dropped, not refused)."""
    opts = encode_options if encode_options is not None else EncodeOptions(lod=True)
    opts = replace(opts, reorder_input=True)  # the Gaussians are ours: the LOD builder may permute them in place
    if progress:
        progress("read", 0.0)
    g = read_gaussians(path, drop_invalid=drop_invalid)
    if progress:
        progress("read", 1.0)
    if opts.up is None:
        stated = declared_up(path)
        if stated is not None:
            opts = replace(opts, up=stated.up)
    return encode_in_memory(g, opts, progress, name=path)
