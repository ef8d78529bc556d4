"""A simulated access link for tests and benchmarks (`splatstream serve --throttle-mbps R --latency-ms L`).

Not part of the protocol (format_spec/http.md section 13). One `Link` per server process is shared by every
connection, as a real access link is: response bodies leave in chunks, each chunk waiting for its transmission
time at `rate` on one virtual clock (first come, first served), so N parallel downloads share the rate instead
of each getting it. `latency` is added once per request, before the handler runs (one round trip of a far
server; the connection set-up is not delayed). Headers are not counted against the rate.
"""
from __future__ import annotations

import asyncio

from aiohttp import web

MBIT = 1_000_000 / 8  # bytes per second in one Mbit/s
BURST_S = 0.02


class Link:
    """A shared link of `rate_bytes_s` bytes per second (None: unlimited) with `latency_s` per request."""

    def __init__(self, rate_bytes_s: float | None, latency_s: float = 0.0):
        if rate_bytes_s is not None and rate_bytes_s <= 0:
            raise ValueError(f"link rate {rate_bytes_s}: expected a positive number of bytes per second")
        if latency_s < 0:
            raise ValueError(f"latency {latency_s}: expected 0 or more seconds")
        self.rate = rate_bytes_s
        self.latency_s = latency_s
        self._free_at = 0.0  # loop time at which the link has sent everything offered so far
        # Chunks of about 10 ms of the rate (1-16 KiB): fine-grained sharing without a timer per byte.
        self.chunk = 16384 if rate_bytes_s is None else int(min(16384, max(1024, rate_bytes_s * 0.01)))

    @classmethod
    def from_args(cls, mbps: float | None, latency_ms: float = 0.0) -> Link | None:
        """The link of `--throttle-mbps` / `--latency-ms`; None when neither asks for anything."""
        if mbps is None and not latency_ms:
            return None
        return cls(None if mbps is None else mbps * MBIT, latency_ms / 1000.0)

    def describe(self) -> str:
        rate = "unlimited" if self.rate is None else f"{self.rate / MBIT:g} Mbit/s shared"
        return f"simulated link: {rate}, +{self.latency_s * 1000:g} ms per request"

    async def transmit(self, n: int) -> None:
        """Wait until `n` more bytes have crossed the link (after everything offered before them)."""
        if self.rate is None or n <= 0:
            return
        now = asyncio.get_running_loop().time()
        # Up to BURST_S of unused link time is kept (a token bucket of that depth): the time a sender loses to
        # timer overshoot and writes is made up, so one stream still gets the full rate.
        self._free_at = max(now - BURST_S, self._free_at) + n / self.rate
        delay = self._free_at - now
        if delay > 0:
            await asyncio.sleep(delay)

    def middleware(self):
        link = self

        @web.middleware
        async def throttle(request: web.Request, handler) -> web.StreamResponse:
            if link.latency_s > 0:
                await asyncio.sleep(link.latency_s)
            response = await handler(request)
            if link.rate is None or request.method == "HEAD":
                return response
            body = _body_of(response)
            if body is None:
                return response
            return PacedResponse(link, body, response)

        return throttle


def _body_of(response: web.StreamResponse) -> bytes | None:
    """The bytes a handler's response would send, or None to leave the response alone (no body, or a kind of
    response this tool does not know how to pace)."""
    read_body = getattr(response, "read_body", None)  # server.app.SendfileResponse
    if callable(read_body):
        return read_body()
    if isinstance(response, web.Response) and isinstance(response.body, (bytes, bytearray)) and response.body:
        return bytes(response.body)
    return None


class PacedResponse(web.StreamResponse):
    """`response`'s status and headers with `body` sent through the link."""

    def __init__(self, link: Link, body: bytes, response: web.StreamResponse):
        headers = {k: v for k, v in response.headers.items() if k.lower() not in ("content-length",
                                                                                   "transfer-encoding")}
        super().__init__(status=response.status, reason=response.reason, headers=headers)
        self.content_length = len(body)
        self._link = link
        self._body_bytes = body
        self._sent = False

    async def prepare(self, request):  # type: ignore[override]
        writer = await super().prepare(request)
        if self._sent or writer is None:
            return writer
        self._sent = True
        view = memoryview(self._body_bytes)
        step = self._link.chunk
        for start in range(0, len(view), step):
            chunk = view[start:start + step]
            await self._link.transmit(len(chunk))
            await self.write(chunk)
        return writer
