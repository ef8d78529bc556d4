"""The aiohttp application: routes, thin handlers, error and CORS handling (format_spec/http.md)."""
from __future__ import annotations

import asyncio
import gzip
import hashlib
import json
import logging
import os
import socket
import time
from collections.abc import Iterable

from aiohttp import web
from aiohttp.abc import AbstractAccessLogger

from . import http as h
from . import tilesets
from .limits import RETRY_AFTER_SECONDS, ConnectionGuard, Limits
from .paths import PathRejected, parse_scene_path, unservable_path
from .scenes import Forbidden, NotFound, OpenedFile, OutOfResources, SceneRoot
from .throttle import Link
from .tilesets import TilesetPath, open_tileset_file, parse_tileset_path

log = logging.getLogger("splatstream.server")

SERVER_NAME = "splatstream"
CLIENT_MAX_SIZE = 1024  # request bodies: nothing we serve takes one
HANDLER_LIMITS = {"max_line_size": 8190, "max_field_size": 8190, "max_headers": 64}
SHUTDOWN_TIMEOUT = 30.0  # seconds in-flight responses get to finish after SIGTERM
# sendfile in pieces, each to be taken by the client within the send timeout (so a client that stops reading is
# cut off): from SEND_CHUNK_MIN, doubled while the client reads a piece in under 1/16 of the timeout (halved over
# 1/4), up to SEND_CHUNK_MAX (each piece costs a few event-loop round trips: 1 MiB pieces throughout took about 2.5x
# the server CPU of one sendfile call per file; growing pieces, within noise of it).
SEND_CHUNK_MIN = 1 << 20
SEND_CHUNK_MAX = 64 << 20

SCENE_ROOT = web.AppKey("scene_root", SceneRoot)
CORS = web.AppKey("cors", "CorsPolicy")
LIMITS = web.AppKey("limits", Limits)
HANDLER_ARGS = web.AppKey("handler_args", dict)


class CorsPolicy:
    """Which Origins may read our responses. '*' allows every origin (no credentials are ever involved)."""

    def __init__(self, origins: Iterable[str] = ()):
        self.origins = frozenset(o.rstrip("/") for o in origins)
        self.any = "*" in self.origins
        self.enabled = bool(self.origins)

    def allow(self, origin: str | None) -> str | None:
        if origin is None or not self.enabled:
            return None
        if self.any:
            return "*"
        return origin if origin in self.origins else None


# -- responses -----------------------------------------------------------------------------------------------------
def json_response(request: web.Request, payload: object, *, status: int = 200, cache: str = h.CACHE_REVALIDATE,
                  headers: dict[str, str] | None = None, etag: bool = False) -> web.Response:
    body = json.dumps(payload, separators=(",", ":")).encode()
    hdrs = {"Content-Type": f"{h.JSON_TYPE}; charset=utf-8", "Cache-Control": cache, "Vary": "Accept-Encoding"}
    if headers:
        hdrs.update(headers)
    if etag:
        # Weak: the same JSON goes out gzipped or not, so the tag names the content, not the bytes.
        tag = h.weak_etag(hashlib.sha256(body).hexdigest()[:32])
        hdrs["ETag"] = tag
        if request.method in ("GET", "HEAD") and h.none_match(request.headers.get("If-None-Match"), tag):
            return web.Response(status=304, headers=hdrs)
    if len(body) >= h.GZIP_MIN_BYTES and h.accepts_gzip(request.headers.get("Accept-Encoding")):
        body = gzip.compress(body, compresslevel=6, mtime=0)
        hdrs["Content-Encoding"] = "gzip"
    return web.Response(body=body, status=status, headers=hdrs)


def error_response(request: web.Request, status: int, message: str,
                   headers: dict[str, str] | None = None) -> web.Response:
    return json_response(request, h.error_body(status, message), status=status, cache=h.CACHE_NONE, headers=headers)


class SendfileResponse(web.StreamResponse):
    """Sends `count` bytes of an open file from `offset` with sendfile(2); headers are set by the caller.

    Never compressed (payloads are zstd already), Content-Length always known, the file closed when done.
    """

    def __init__(self, opened: OpenedFile, offset: int, count: int, *, status: int, headers: dict[str, str]):
        super().__init__(status=status, headers=headers)
        self.content_length = count
        self._opened = opened
        self._offset = offset
        self._count = count
        self._started = False

    def read_body(self) -> bytes:
        """The bytes this response would send, read now (and the file closed): server/throttle.py paces them."""
        try:
            parts, offset, end = [], self._offset, self._offset + self._count
            while offset < end:
                chunk = os.pread(self._opened.fd, min(1 << 24, end - offset), offset)
                if not chunk:
                    raise ConnectionResetError("file shrank while being sent")
                parts.append(chunk)
                offset += len(chunk)
            return b"".join(parts)
        finally:
            self._opened.close()

    async def prepare(self, request):  # type: ignore[override]
        if self._started:
            return await super().prepare(request)
        self._started = True
        try:
            writer = await super().prepare(request)
            if request.method == "HEAD" or self._count == 0 or writer is None:
                return writer
            transport = request.transport
            if transport is None:
                raise ConnectionResetError("connection lost")
            send_timeout = request.app[LIMITS].send_timeout if LIMITS in request.app else None
            offset, end = self._offset, self._offset + self._count
            with os.fdopen(self._opened.fd, "rb", closefd=False) as fobj:
                try:
                    # In pieces, each given the send timeout: a client that stops reading is cut off (an aborted
                    # transport under a running sendfile would leave it waiting forever, so it is cancelled first).
                    loop = asyncio.get_running_loop()
                    chunk = SEND_CHUNK_MIN
                    while offset < end:
                        n = min(chunk, end - offset)
                        started = loop.time()
                        if transport.is_closing():
                            raise ConnectionResetError("the client closed the connection")
                        try:
                            await asyncio.wait_for(loop.sendfile(transport, fobj, offset, n), send_timeout)
                        except TimeoutError:
                            transport.abort()
                            raise ConnectionResetError(f"the client took less than {n} bytes in {send_timeout} s") \
                                from None
                        except RuntimeError:  # "Transport is closing": the client went away meanwhile
                            if transport.is_closing():
                                raise ConnectionResetError("the client closed the connection") from None
                            raise
                        offset += n
                        took = loop.time() - started
                        if send_timeout is None or took < send_timeout / 16:
                            chunk = min(2 * chunk, SEND_CHUNK_MAX)
                        elif took > send_timeout / 4:
                            chunk = max(chunk // 2, SEND_CHUNK_MIN)
                except NotImplementedError:  # e.g. TLS transports: flow control (pause_writing) applies instead
                    while offset < end:
                        chunk = os.pread(self._opened.fd, min(1 << 20, end - offset), offset)
                        if not chunk:
                            raise ConnectionResetError("file shrank while being sent") from None
                        await writer.write(chunk)
                        offset += len(chunk)
            await super().write_eof()
            return writer
        finally:
            self._opened.close()


def file_response(request: web.Request, opened: OpenedFile, content_type: str, cache: str) -> web.StreamResponse:
    """Conditional (If-Match, If-None-Match), range (Range, If-Range) and HEAD handling for one open file."""
    etag = h.strong_etag(opened.etag_token)
    headers = {"ETag": etag, "Cache-Control": cache, "Accept-Ranges": "bytes"}
    size = opened.size
    if not h.match(request.headers.get("If-Match"), etag):
        opened.close()
        return error_response(request, 412, "If-Match does not match the current ETag", {"ETag": etag})
    if h.none_match(request.headers.get("If-None-Match"), etag):
        opened.close()
        return web.Response(status=304, headers=headers)
    headers["Content-Type"] = content_type
    status, offset, count = 200, 0, size
    # Range is one field, If-Range one validator (RFC 9110 14.2, 13.1.5): a request with two of either was answered
    # with the first one's range (newuser64); it is ignored as several ranges in one field are: 200, the whole file.
    ranges, if_ranges = request.headers.getall("Range", []), request.headers.getall("If-Range", [])
    if request.method == "GET" and len(ranges) == 1 and len(if_ranges) <= 1 and \
            h.if_range_allows(if_ranges[0] if if_ranges else None, etag):
        try:
            rng = h.parse_range(ranges[0], size)
        except h.RangeNotSatisfiable:
            opened.close()
            return error_response(request, 416, f"range not satisfiable: the file has {size} bytes",
                                  {"ETag": etag, "Accept-Ranges": "bytes", "Content-Range": f"bytes */{size}"})
        if rng is not None:
            status, offset, count = 206, rng.start, rng.length
            headers["Content-Range"] = rng.content_range(size)
    if opened.data is not None and count > 0:  # (aiohttp's Response leaves out 'Content-Length: 0' on HEAD)
        body = opened.data if count == size else opened.data[offset:offset + count]
        opened.close()
        return web.Response(body=body, status=status, headers=headers)
    return SendfileResponse(opened, offset, count, status=status, headers=headers)


# -- handlers ------------------------------------------------------------------------------------------------------
async def scene_file(request: web.Request) -> web.StreamResponse:
    tp = parse_tileset_path(request.rel_url.raw_path)  # exported 3D Tiles (server/tilesets.py)
    if tp is not None:
        return tileset_file(request, tp)
    sp = parse_scene_path(request.rel_url.raw_path)
    opened = request.app[SCENE_ROOT].open(sp)
    if sp.kind == "payload":
        return file_response(request, opened, h.PAYLOAD_TYPE, h.CACHE_IMMUTABLE)
    return file_response(request, opened, h.MANIFEST_TYPE, h.CACHE_REVALIDATE)


def tileset_file(request: web.Request, tp: TilesetPath) -> web.StreamResponse:
    opened = open_tileset_file(request.app[SCENE_ROOT], tp)
    if tp.kind == "content":
        return file_response(request, opened, tilesets.CONTENT_TYPE, h.CACHE_IMMUTABLE)
    if tp.kind == "external":  # an external tileset (one page of a paged scene's tree): immutable like content
        return file_response(request, opened, tilesets.TILESET_TYPE, h.CACHE_IMMUTABLE)
    return file_response(request, opened, tilesets.TILESET_TYPE, h.CACHE_REVALIDATE)


async def list_scenes(request: web.Request) -> web.Response:
    scenes = request.app[SCENE_ROOT].list_scenes()
    return json_response(request, {"scenes": scenes}, etag=True)


async def healthz(request: web.Request) -> web.Response:
    return json_response(request, {"status": "ok"}, cache=h.CACHE_NONE)


async def options(request: web.Request) -> web.Response:
    """OPTIONS, including CORS preflight: CORS headers for allowed origins are added by `_on_prepare`."""
    headers = {"Allow": h.ALLOWED_METHODS, "Cache-Control": h.CACHE_NONE}
    policy: CorsPolicy = request.app[CORS]
    method = request.headers.get("Access-Control-Request-Method")
    if method is not None and policy.allow(request.headers.get("Origin")) and method in ("GET", "HEAD"):
        headers.update({
            "Access-Control-Allow-Methods": h.ALLOWED_METHODS,
            "Access-Control-Allow-Headers": h.CORS_ALLOW_HEADERS,
            "Access-Control-Max-Age": h.CORS_MAX_AGE,
        })
    return web.Response(status=204, headers=headers)


# -- cross-cutting -------------------------------------------------------------------------------------------------
@web.middleware
async def overflow_middleware(request: web.Request, handler) -> web.StreamResponse:
    """A connection of the reserve beyond the cap (server.limits) gets one answer: /healthz as usual, anything
    else 503 with Retry-After; then it is closed."""
    if not getattr(request.protocol, "overflow", False):
        return await handler(request)
    if request.path == "/healthz":
        response = await handler(request)
    else:
        response = error_response(request, 503, "server busy: too many open connections; retry later",
                                  {"Retry-After": str(RETRY_AFTER_SECONDS)})
    response.force_close()
    return response


@web.middleware
async def errors_middleware(request: web.Request, handler) -> web.StreamResponse:
    """Every error leaves as {"error": {"status", "message"}}; unexpected exceptions as a bare 500."""
    try:
        return await handler(request)
    except PathRejected as exc:
        return error_response(request, exc.status, exc.message)
    except NotFound as exc:
        return error_response(request, 404, str(exc))
    except Forbidden as exc:
        return error_response(request, 403, str(exc))
    except OutOfResources as exc:
        return error_response(request, 503, str(exc), {"Retry-After": str(RETRY_AFTER_SECONDS)})
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        headers = {}
        if exc.status == 405:
            headers["Allow"] = h.ALLOWED_METHODS
            message = f"method {request.method} is not allowed here; allowed: {h.ALLOWED_METHODS}"
        elif exc.status == 404:
            problem = unservable_path(request.rel_url.raw_path)
            if problem is not None:
                return error_response(request, 400, problem)
            message = "not found: scenes are under /scenes/<scene id>/, the scene list at /api/scenes"
        else:
            message = exc.reason
        return error_response(request, exc.status, message, headers)
    except (asyncio.CancelledError, ConnectionError):
        raise
    except Exception:
        log.exception("unexpected error serving %s %s", request.method, request.path_qs[:200])
        return error_response(request, 500, "internal server error")


async def _on_prepare(request: web.Request, response: web.StreamResponse) -> None:
    response.headers["Server"] = SERVER_NAME
    policy: CorsPolicy = request.app[CORS]
    if not policy.enabled:
        return
    if not policy.any:
        vary = response.headers.get("Vary")
        response.headers["Vary"] = f"{vary}, Origin" if vary else "Origin"
    allowed = policy.allow(request.headers.get("Origin"))
    if allowed:
        response.headers["Access-Control-Allow-Origin"] = allowed
        response.headers["Access-Control-Expose-Headers"] = h.CORS_EXPOSE_HEADERS


def create_app(root: str | os.PathLike, cors_origins: Iterable[str] = (),
               throttle: Link | None = None) -> web.Application:
    # throttle: a simulated link for tests and benchmarks (server/throttle.py), outermost so errors are paced too.
    middlewares = [throttle.middleware()] if throttle is not None else []
    app = web.Application(middlewares=[*middlewares, overflow_middleware, errors_middleware],
                          client_max_size=CLIENT_MAX_SIZE)
    app[SCENE_ROOT] = SceneRoot(root)
    app[CORS] = CorsPolicy(cors_origins)
    app.on_response_prepare.append(_on_prepare)
    for path, handler in (("/healthz", healthz), ("/api/scenes", list_scenes), ("/scenes/{tail:.+}", scene_file)):
        app.router.add_get(path, handler)  # also HEAD
        app.router.add_route("OPTIONS", path, options)
    return app


class AccessLog(AbstractAccessLogger):
    """One line per request, Common Log Format plus the response time in seconds, written to file descriptor
    `fd` (stderr).

    Cheaper than aiohttp's default logger (no logging.Logger, no format parsing per request): lines are kept
    and written together, at most FLUSH_SECONDS late (`flush()` is also called on a timer and at shutdown),
    always whole lines in one write(), so the lines of several worker processes never interleave.
    """

    FLUSH_SECONDS = 0.5
    FLUSH_BYTES = 32 << 10
    fd = 2
    _lines: list[str] = []
    _size = 0
    _last_flush = 0.0
    _stamp_second = -1
    _stamp = ""

    def log(self, request, response, duration: float) -> None:
        now = time.time()
        size = 0 if request.method == "HEAD" else (response.content_length or 0)
        second = int(now)
        if second != AccessLog._stamp_second:
            AccessLog._stamp_second = second
            AccessLog._stamp = time.strftime("%d/%b/%Y:%H:%M:%S +0000", time.gmtime(second))
        target = request.raw_path[:512]  # as the client sent it, like nginx's $request
        if '"' in target:
            target = target.replace('"', "%22")
        version = request.version
        line = (f'{request.remote or "-"} - - [{AccessLog._stamp}] "{request.method} {target} HTTP/{version.major}.'
                f'{version.minor}" {response.status} {size} {duration:.6f}\n')
        AccessLog._lines.append(line)
        AccessLog._size += len(line)
        if AccessLog._size >= self.FLUSH_BYTES or now - AccessLog._last_flush >= self.FLUSH_SECONDS:
            AccessLog.flush()

    @classmethod
    def flush(cls) -> None:
        cls._last_flush = time.time()
        if not cls._lines:
            return
        data = "".join(cls._lines).encode("utf-8", "replace")
        cls._lines.clear()
        cls._size = 0
        try:
            while data:
                data = data[os.write(cls.fd, data):]
        except OSError:
            pass  # a closed or full log must not take the server down

    @property
    def enabled(self) -> bool:
        return self.logger is not None


def create_runner(app: web.Application, access_log: bool = True, shutdown_timeout: float = SHUTDOWN_TIMEOUT,
                  limits: Limits | None = None) -> web.AppRunner:
    """The runner of `app`; start serving with `start_site` (not aiohttp's sites: see server.limits)."""
    limits = (limits or Limits()).with_reserve()
    handler_args = dict(access_log_class=AccessLog, access_log=log if access_log else None,
                        keepalive_timeout=limits.keepalive_timeout, **HANDLER_LIMITS)
    app[LIMITS] = limits
    app[HANDLER_ARGS] = handler_args
    return web.AppRunner(app, shutdown_timeout=shutdown_timeout, **handler_args)


async def start_site(runner: web.AppRunner, sock: socket.socket) -> ConnectionGuard:
    """Accept connections on the listening `sock` through a ConnectionGuard (after `runner.setup()`); call the
    guard's close() before `runner.cleanup()`."""
    guard = ConnectionGuard(runner, runner.app[LIMITS], runner.app[HANDLER_ARGS])
    await guard.listen(sock)
    return guard
