"""A test-only HTTP server that serves real scene directories and injects faults on request (not a mock: real
aiohttp on a real loopback socket, in its own thread).

Faults are queued per payload SHA-256 (or "manifest") and consumed one per request, in order; once a queue is
empty the file is served correctly. Every request is recorded as (path, status).

* "500": answer 500.
* "corrupt": the right length, one byte flipped.
* "stall": headers and half of the body, then nothing (until the client gives up or the server stops).
* "truncate": Content-Length of the whole file, half of the body, then the connection is closed.
* "hang": no answer at all (no headers).
* "slow": the whole body, paced at `slow_bytes_per_s`.
"""
from __future__ import annotations

import asyncio
import hashlib
import os
import socket
import threading
from collections import defaultdict, deque

from aiohttp import web

from splatstream.format.names import MANIFEST_NAME, PAYLOAD_NAME_RE


class LoopbackServer:
    """Real aiohttp on a loopback socket in its own thread, serving GET /scenes/{scene}/{tail} through `_serve`
    (subclasses: FaultServer here, HostileServer in hostile_server.py). Every request is recorded as (path,
    status) by `_record`."""

    def __init__(self, root: str | os.PathLike, port: int = 0):
        self.root = os.fspath(root)
        self.log: list[tuple[str, int]] = []
        self.port = port
        self._lock = threading.Lock()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None
        self._handlers: set[asyncio.Task] = set()

    # -- control (test thread) ------------------------------------------------------------------------------------
    def requests(self, fragment: str = "") -> list[tuple[str, int]]:
        with self._lock:
            return [r for r in self.log if fragment in r[0]]

    def url(self, scene: str) -> str:
        return f"http://127.0.0.1:{self.port}/scenes/{scene}"

    def start(self):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(("127.0.0.1", self.port))
        sock.listen(128)
        sock.setblocking(False)
        self.port = sock.getsockname()[1]
        self._loop = asyncio.new_event_loop()
        ready = threading.Event()

        def main() -> None:
            asyncio.set_event_loop(self._loop)

            async def setup() -> None:
                app = web.Application()
                app.router.add_get("/scenes/{scene}/{tail:.+}", self._handle)
                self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=0.2)
                await self._runner.setup()
                await web.SockSite(self._runner, sock).start()

            self._loop.run_until_complete(setup())
            ready.set()
            self._loop.run_forever()
            self._loop.close()

        self._thread = threading.Thread(target=main, name=type(self).__name__, daemon=True)
        self._thread.start()
        if not ready.wait(30):
            raise RuntimeError(f"{type(self).__name__} did not start")
        return self

    def stop(self) -> None:
        """Stop at once, like a killed process: open connections are aborted, stalled handlers cancelled."""
        if self._loop is None:
            return

        async def down() -> None:
            for t in list(self._handlers):
                t.cancel()
            await self._runner.cleanup()

        asyncio.run_coroutine_threadsafe(down(), self._loop).result(30)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(30)
        self._loop = None

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # -- serving (server thread) ----------------------------------------------------------------------------------
    def _record(self, path: str, status: int) -> None:
        with self._lock:
            self.log.append((path, status))

    async def _handle(self, request: web.Request) -> web.StreamResponse:
        task = asyncio.current_task()
        self._handlers.add(task)
        try:
            return await self._serve(request)
        except ConnectionError:  # the client gave up on a dripping or stalled answer: nothing to say
            return web.Response(status=499)
        finally:
            self._handlers.discard(task)

    async def _serve(self, request: web.Request) -> web.StreamResponse:
        raise NotImplementedError


class FaultServer(LoopbackServer):
    def __init__(self, root: str | os.PathLike, port: int = 0, slow_bytes_per_s: float = 200_000):
        super().__init__(root, port)
        self.faults: dict[str, deque[str]] = defaultdict(deque)
        self.slow_bytes_per_s = slow_bytes_per_s

    # -- control (test thread) ------------------------------------------------------------------------------------
    def add_fault(self, sha_or_manifest: str, *faults: str) -> None:
        with self._lock:
            self.faults[sha_or_manifest].extend(faults)

    # -- serving (server thread) ----------------------------------------------------------------------------------
    def _next_fault(self, key: str) -> str | None:
        with self._lock:
            q = self.faults.get(key)
            return q.popleft() if q else None

    async def _serve(self, request: web.Request) -> web.StreamResponse:
        scene, tail = request.match_info["scene"], request.match_info["tail"]
        path = request.path
        if tail == MANIFEST_NAME:
            key = "manifest"
        elif tail.startswith("data/") and PAYLOAD_NAME_RE.match(tail[5:]):
            key = tail[5:-4]
        else:
            self._record(path, 404)
            raise web.HTTPNotFound()
        file = os.path.join(self.root, scene, tail)
        if not os.path.isfile(file):
            self._record(path, 404)
            raise web.HTTPNotFound()
        with open(file, "rb") as f:
            data = f.read()
        etag = '"' + hashlib.sha256(data).hexdigest() + '"'
        fault = self._next_fault(key)
        if fault == "500":
            self._record(path, 500)
            return web.Response(status=500, text="injected fault")
        if fault == "hang":
            self._record(path, 0)
            await asyncio.sleep(3600)
        if key == "manifest" and request.headers.get("If-None-Match") == etag and fault is None:
            self._record(path, 304)
            return web.Response(status=304, headers={"ETag": etag})
        if fault == "corrupt":
            data = data[:len(data) // 2] + bytes([data[len(data) // 2] ^ 0xFF]) + data[len(data) // 2 + 1:]
        resp = web.StreamResponse(status=200, headers={"ETag": etag, "Content-Type": "application/octet-stream"})
        resp.content_length = len(data)
        await resp.prepare(request)
        self._record(path, 200)
        if fault in ("stall", "truncate"):
            await resp.write(data[:len(data) // 2])
            if fault == "truncate":
                request.transport.close()
                return resp
            await asyncio.sleep(3600)
        if fault == "slow":
            step = max(1, int(self.slow_bytes_per_s / 50))
            for i in range(0, len(data), step):
                await resp.write(data[i:i + step])
                await asyncio.sleep(step / self.slow_bytes_per_s)
        else:
            await resp.write(data)
        await resp.write_eof()
        return resp
