"""Connection limits of `splatstream serve` (format_spec/http.md section 11): timeouts, a connection cap with a
small reserve answered 503 (and /healthz), eviction of idle connections at the cap, a file-descriptor budget,
and rate-limited logging of what abusive clients can make happen again and again.

aiohttp provides the idle keep-alive timeout (`keepalive_timeout`, which recent versions also run from the
connection's opening) and the request size limits. It has no timeout of its own for reading a request's headers
(a slow client may take the whole keep-alive timeout to send them), none for a client that stops reading a
response, and no cap on open connections (`loop.create_server` accepts until the process runs out of file
descriptors, and asyncio then logs a traceback per failed accept). So each connection's protocol is a
`GuardedHandler` (aiohttp's RequestHandler plus the state those rules need), made by a `ConnectionGuard`, which
is the protocol factory of the listening socket and so sees every connection before aiohttp does. One timer per
guard (not per connection) enforces the timeouts. Payloads sent with sendfile have their own send timeout
(server.app.SendfileResponse): a transport must not be closed under a running sendfile.
"""
from __future__ import annotations

import asyncio
import errno
import logging
import resource
import select
import socket
import time
from dataclasses import dataclass, replace

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.web_protocol import RequestHandler

log = logging.getLogger("splatstream.server")

# Descriptors a worker needs besides its connections: std streams, the listening socket, the event loop's epoll
# and self-pipe, the interpreter's own files, a manifest being read, with room to spare.
FD_BASE = 64
MIN_CONNECTIONS = 4
MAX_RESERVE = 64
LISTEN_BACKLOG = 1024  # the kernel's queue of connections not yet accepted
MAX_ACCEPT_BATCH = 128
RETRY_AFTER_SECONDS = 2
LOG_INTERVAL_SECONDS = 10.0  # a repeated warning is written at most this often (with a count of the ones left out)
ORPHAN_SECONDS = 10.0  # a protocol made but never connected (the accept failed after the factory ran) is forgotten


@dataclass(frozen=True)
class Limits:
    """Per worker process. `reserve` connections beyond `max_connections` (a few more for a few event-loop
    turns) get one request each: /healthz is answered, anything else 503."""

    max_connections: int = 1024
    header_timeout: float = 10.0  # a request's headers must be complete this long after its first byte (or connect)
    keepalive_timeout: float = 30.0  # an idle keep-alive connection is closed after this (aiohttp's own timer)
    send_timeout: float = 60.0  # a response the client stops reading for this long is aborted
    reserve: int = 0  # 0: derived from max_connections (see `with_reserve`)

    def with_reserve(self) -> Limits:
        if self.reserve > 0:
            return self
        return replace(self, reserve=max(2, min(MAX_RESERVE, self.max_connections // 8)))

    @property
    def accept_batch(self) -> int:
        """Connections asyncio accepts per wake-up, all of them before any is connected to its protocol: no more
        than the reserve (at most 1/8 of the cap), so that making room for a batch, in the cap or in the
        reserve, only ever closes connections older than the batch, whose sockets can be checked for a request
        that has arrived, never one of the batch itself (a health check among them, for instance)."""
        return min(MAX_ACCEPT_BATCH, self.with_reserve().reserve)

    @property
    def max_overflow(self) -> int:
        """Connections beyond the cap at once: the reserve, plus three accept batches (see ConnectionGuard)."""
        return self.with_reserve().reserve + 3 * self.accept_batch

    def fds_needed(self) -> int:
        """Descriptors for a full worker: per connection its socket and a payload being sent, the connections
        accepted in one wake-up (before older ones are closed to make room), and FD_BASE."""
        r = self.with_reserve()
        return FD_BASE + 2 * (r.max_connections + r.max_overflow) + self.accept_batch


class FdLimitTooLow(Exception):
    pass


def fit_to_fd_limit(limits: Limits) -> tuple[Limits, int, bool]:
    """(limits that fit RLIMIT_NOFILE, the limit, whether max_connections was lowered).

    Raises the soft limit towards the hard one when the requested connections need more (as Go's runtime and
    nginx's worker_rlimit_nofile do); if the hard limit is still too low, lowers max_connections to fit, so
    connections never exhaust the descriptors (accept() would fail, and nothing, health checks included, could
    be answered). FdLimitTooLow when not even MIN_CONNECTIONS fit.
    """
    limits = limits.with_reserve()
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    need = limits.fds_needed()
    if need > soft and (hard == resource.RLIM_INFINITY or hard > soft):
        target = need if hard == resource.RLIM_INFINITY else min(need, hard)
        try:
            resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
            soft = target
        except (ValueError, OSError):
            pass
    if need <= soft:
        return limits, soft, False
    cap = limits.max_connections
    while cap >= MIN_CONNECTIONS:
        fitted = replace(limits, max_connections=cap, reserve=0).with_reserve()
        if fitted.fds_needed() <= soft:
            return fitted, soft, True
        cap = min(cap - 1, int(cap * (soft - FD_BASE) / fitted.fds_needed()))
    minimum = replace(limits, max_connections=MIN_CONNECTIONS, reserve=0).fds_needed()
    raise FdLimitTooLow(f"the file descriptor limit ({soft}, ulimit -n) is too low to serve: at least {minimum} "
                        f"are needed")


class RateLimitedLog:
    """Writes a message of a kind at most once per `interval` seconds, with the number left out since."""

    def __init__(self, interval: float = LOG_INTERVAL_SECONDS):
        self.interval = interval
        self._last: dict[str, float] = {}
        self._left_out: dict[str, int] = {}

    def __call__(self, kind: str, level: int, message: str, *args: object) -> None:
        now = time.monotonic()
        last = self._last.get(kind)
        if last is not None and now - last < self.interval:
            self._left_out[kind] = self._left_out.get(kind, 0) + 1
            return
        self._last[kind] = now
        n = self._left_out.pop(kind, 0)
        if n:
            message += f" ({n} more like this in the last {now - last:.0f} s)"
        log.log(level, message, *args)


rate_limited = RateLimitedLog()


class GuardedHandler(RequestHandler):
    """aiohttp's per-connection protocol, plus what the guard needs to know: whether a request is being answered,
    since when the connection waits for one and whether its first bytes came, whether writing is paused."""

    def __init__(self, guard: ConnectionGuard, overflow: bool, **kwargs):
        super().__init__(guard.server, loop=guard.loop, **kwargs)
        self.guard = guard
        self.overflow = overflow  # one of the reserve: answers one request (/healthz, else 503) and closes
        now = guard.loop.time()
        self.created = now
        self.busy = False  # a request is being answered
        self.waiting_since = now  # waiting for the next request since
        self.got_bytes = False  # bytes of the next request came
        self.header_since: float | None = now  # the header timeout runs from here (connect, or a request's 1st byte)
        self.paused_since: float | None = None  # the client stopped reading (the transport's buffer is full)
        self.closing_since: float | None = None
        self.conn_transport: asyncio.Transport | None = None  # aiohttp clears self.transport when it closes

    # -- asyncio protocol callbacks --------------------------------------------------------------------------------
    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.conn_transport = transport  # type: ignore[assignment]
        super().connection_made(transport)

    def connection_lost(self, exc: BaseException | None) -> None:
        self.guard.forget(self)
        super().connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        if not self.busy and data and not self.got_bytes:
            self.got_bytes = True
            self.guard.idle.pop(self, None)
            if self.header_since is None:
                self.header_since = self.guard.loop.time()  # the first byte of the next request
        super().data_received(data)

    def pause_writing(self) -> None:
        self.paused_since = self.guard.loop.time()
        super().pause_writing()

    def resume_writing(self) -> None:
        self.paused_since = None
        super().resume_writing()

    # -- aiohttp hooks ---------------------------------------------------------------------------------------------
    def request_started(self) -> None:
        self.busy = True
        self.got_bytes = False
        self.header_since = None
        self.guard.idle.pop(self, None)

    def log_access(self, request, response, time) -> None:  # noqa: A002 - aiohttp's signature
        """Called by aiohttp once a response is written (or the client went away): the connection is idle."""
        self.busy = False
        self.waiting_since = self.guard.loop.time()
        if not self.overflow and self in self.guard.normal:
            self.guard.idle[self] = None  # (the newest idle connection: last in line for eviction)
        super().log_access(request, response, time)

    def log_exception(self, *args, **kw) -> None:
        """Requests the HTTP parser refuses are the client's fault: one line at INFO, no traceback. Everything
        else (a server fault) stays an ERROR with its traceback."""
        exc = kw.get("exc_info")
        if isinstance(exc, HttpProcessingError) and (exc.code or 400) < 500:
            first = str(exc.message).strip().splitlines()[0] if str(exc.message).strip() else type(exc).__name__
            self.logger.info("refused a request from %s: %s %s", self._peer(), exc.code, first[:200])
            return
        super().log_exception(*args, **kw)

    def _peer(self) -> str:
        peer = self.conn_transport.get_extra_info("peername") if self.conn_transport else None
        return str(peer[0]) if isinstance(peer, tuple) else "-"


class ConnectionGuard:
    """The protocol factory of a listening socket: caps connections, evicts idle ones, enforces the timeouts."""

    def __init__(self, runner: web.AppRunner, limits: Limits, handler_args: dict):
        assert runner.server is not None, "runner.setup() first"
        self.server = runner.server
        self.loop = asyncio.get_running_loop()
        self.limits = limits.with_reserve()
        self.handler_args = handler_args
        self.normal: dict[GuardedHandler, None] = {}  # insertion-ordered sets
        self.overflow: dict[GuardedHandler, None] = {}
        self.idle: dict[GuardedHandler, None] = {}  # the idle ones of `normal`, longest idle first
        self.refused = 0
        self.evicted = 0
        self.timed_out = 0
        self._listener: asyncio.base_events.Server | None = None
        self._sweeper: asyncio.TimerHandle | None = None
        self.sweep_seconds = max(0.05, min(1.0, self.limits.header_timeout / 4, self.limits.send_timeout / 4))
        # The request factory is the one place aiohttp calls for every request it parsed, before answering it.
        inner = self.server.request_factory

        def request_factory(message, payload, protocol, writer, task):
            if isinstance(protocol, GuardedHandler):
                protocol.request_started()
            return inner(message, payload, protocol, writer, task)

        self.server.request_factory = request_factory

    async def listen(self, sock: socket.socket) -> None:
        self._listener = await self.loop.create_server(self, sock=sock, backlog=self.limits.accept_batch)
        # asyncio uses one number for the kernel's backlog and for how many connections it accepts per wake-up;
        # keep the deep kernel queue for bursts while accepting in batches that fit the descriptor budget.
        sock.listen(LISTEN_BACKLOG)
        self._sweeper = self.loop.call_later(self.sweep_seconds, self._sweep)

    def close(self) -> None:
        """Stop accepting (runner.cleanup() then closes the connections)."""
        if self._listener is not None:
            self._listener.close()
        if self._sweeper is not None:
            self._sweeper.cancel()
            self._sweeper = None

    @property
    def open_connections(self) -> int:
        return len(self.normal) + len(self.overflow)

    # -- a new connection ------------------------------------------------------------------------------------------
    def __call__(self) -> asyncio.Protocol:
        lim = self.limits
        if len(self.normal) >= lim.max_connections:
            self._evict_idle()
        if len(self.normal) < lim.max_connections:
            handler = self._make(self.normal, overflow=False)
            self.idle[handler] = None
            return handler
        rate_limited("cap", logging.WARNING, "all %d connection slots are busy: idle connections are closed to "
                     "make room, and new ones beyond a reserve of %d are answered 503 (see --max-connections)",
                     lim.max_connections, lim.reserve)
        if len(self.overflow) >= lim.reserve:
            self._evict_waiting_overflow()
        # Beyond the reserve when no reserve connection could be closed, because their requests have arrived but
        # not been read yet (a connection's first bytes are read three event-loop turns after its accept: the
        # accept task, then connection_made, then the read, and each turn may accept a batch). Those are answered
        # and closed within those turns, so this excess is as short-lived.
        if len(self.overflow) < lim.max_overflow:
            return self._make(self.overflow, overflow=True)
        self.refused += 1
        return _Refuse()

    def _make(self, pool: dict, overflow: bool) -> GuardedHandler:
        handler = GuardedHandler(self, overflow, **self.handler_args)
        pool[handler] = None
        return handler

    def _evict_idle(self) -> None:
        """Close the normal connection idle longest (no request in progress, no byte of the next one), as nginx
        reuses keep-alive connections when it runs out of them.

        One whose socket is readable is passed over: its request has arrived but not been read yet (a health
        check accepted in the same burst as a flood of idle connections must not be evicted before it is read)."""
        while self.idle:
            conn = next(iter(self.idle))
            if conn.conn_transport is None:
                return  # not connected yet (nor is any newer one): nothing here to evict
            del self.idle[conn]
            if conn.busy:
                continue
            if _readable(conn.conn_transport):
                continue  # (out of the idle line: data_received follows, and starts its header timeout)
            self._close_for_room(conn)
            return

    def _evict_waiting_overflow(self) -> None:
        """Close the reserve connection that has waited longest for its one request (the reserve is small)."""
        for conn in self.overflow:  # (in the order they came: each gets one request, so longest waiting first)
            if not conn.busy and conn.conn_transport is not None \
                    and not _readable(conn.conn_transport):
                self._close_for_room(conn)
                return

    def _close_for_room(self, conn: GuardedHandler) -> None:
        self.evicted += 1
        self.forget(conn)
        conn.force_close()

    def forget(self, conn: GuardedHandler) -> None:
        self.normal.pop(conn, None)
        self.overflow.pop(conn, None)
        self.idle.pop(conn, None)

    # -- timeouts --------------------------------------------------------------------------------------------------
    def _sweep(self) -> None:
        now = self.loop.time()
        lim = self.limits
        for pool in (self.normal, self.overflow):
            for conn in list(pool):
                t = conn.conn_transport
                if t is None:
                    if now - conn.created > ORPHAN_SECONDS:
                        self.forget(conn)
                    continue
                if t.is_closing():
                    # Closed by aiohttp while data is still buffered for a client that does not read it.
                    if conn.closing_since is None:
                        conn.closing_since = now
                    elif now - conn.closing_since > lim.send_timeout:
                        self.timed_out += 1
                        t.abort()
                elif conn.paused_since is not None and now - conn.paused_since > lim.send_timeout:
                    self.timed_out += 1
                    t.abort()
                elif not conn.busy and conn.header_since is not None and now - conn.header_since > lim.header_timeout:
                    self.timed_out += 1
                    conn.force_close()
        self._sweeper = self.loop.call_later(self.sweep_seconds, self._sweep)


def _readable(transport: asyncio.BaseTransport) -> bool:
    sock = transport.get_extra_info("socket")
    if sock is None:
        return False
    poller = select.poll()  # (not select(): descriptors may exceed FD_SETSIZE)
    poller.register(sock.fileno(), select.POLLIN)
    return bool(poller.poll(0))


class _Refuse(asyncio.Protocol):
    """Beyond the cap and its reserve, with every reserve connection busy: a fixed 503, then close."""

    BODY = (b'{"error":{"status":503,"message":"server busy: too many connections; retry later"}}')
    RESPONSE = (b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: application/json; charset=utf-8\r\n"
                b"Content-Length: " + str(len(BODY)).encode() + b"\r\nCache-Control: no-store\r\n"
                b"Retry-After: " + str(RETRY_AFTER_SECONDS).encode() + b"\r\nConnection: close\r\n"
                b"Server: splatstream\r\n\r\n" + BODY)

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.write(self.RESPONSE)  # type: ignore[attr-defined]
        transport.close()


def accept_error_handler(loop: asyncio.AbstractEventLoop, context: dict) -> None:
    """The event loop's exception handler: a failed accept() (out of descriptors or memory) is one rate-limited
    line; asyncio would log a traceback for each of up to a backlog's worth of retries per wake-up."""
    exc = context.get("exception")
    if isinstance(exc, OSError) and exc.errno in (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM) and \
            "accept" in str(context.get("message", "")):
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
        rate_limited("accept", logging.WARNING, "cannot accept connections: %s (file descriptor limit %d); "
                     "retrying every second", exc.strerror or exc, soft)
        return
    loop.default_exception_handler(context)
