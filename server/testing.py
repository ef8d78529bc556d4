"""For the server's tests and benchmark: synthetic scene directories (a valid manifest, random payloads named by
their SHA-256; not real splat data, use splatstream.encoder for that), a real server on loopback in a thread, and
plain HTTP/1.1 requests sent exactly as written."""
from __future__ import annotations

import asyncio
import http.client
import os
import random
import socket
import threading
from collections.abc import Sequence

from splatstream.atomic import atomic_directory
from splatstream.manifest import DATA_DIR, FORMAT_NAME, FORMAT_VERSION, MANIFEST_NAME, pack_manifest, payload_name
from splatstream.manifest import sha256_hex as _sha

ORIGIN = "https://viewer.example"


def fake_manifest(name: str, groups: Sequence[tuple[str, int]], splats: int = 1000) -> dict:
    """A manifest with one tile whose groups are (sha256 hex, bytes)."""
    return {
        "format": FORMAT_NAME,
        "version": list(FORMAT_VERSION),
        "name": name,
        "splats": splats,
        "sh_degree": 0,
        "preset": "medium",
        "bounds": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]},
        "tiles": [{
            "id": 0, "level": 0, "children": [], "splats": splats,
            "groups": {f"g{i}": {"file": payload_name(sha), "bytes": n, "sha256": sha}
                       for i, (sha, n) in enumerate(groups)},
        }],
    }


def write_fake_scene(directory: str | os.PathLike, sizes: Sequence[int], seed: int = 0, name: str | None = None,
                     atomic: bool = True) -> list[str]:
    """Create (or atomically replace) a scene directory with payloads of the given sizes; their sha256 hexes."""
    rng = random.Random(seed)
    directory = os.fspath(directory)

    def fill(target: str) -> list[str]:
        os.makedirs(os.path.join(target, DATA_DIR), exist_ok=True)
        groups = []
        for n in sizes:
            data = rng.randbytes(n)
            sha = _sha(data)
            with open(os.path.join(target, payload_name(sha)), "wb") as f:
                f.write(data)
            groups.append((sha, n))
        m = fake_manifest(name or os.path.basename(directory), groups)
        with open(os.path.join(target, MANIFEST_NAME), "wb") as f:
            f.write(pack_manifest(m))
        return [sha for sha, _ in groups]

    if not atomic:
        return fill(directory)
    with atomic_directory(directory) as tmp:
        return fill(tmp)


class ServerThread:
    """A real server on 127.0.0.1:<free port>, its event loop in a daemon thread."""

    def __init__(self, root: str | os.PathLike, cors=(ORIGIN,), shutdown_timeout: float = 5.0, limits=None):
        from .app import create_app, create_runner, start_site  # aiohttp only where a server runs
        from .run import bind

        self.app = create_app(root, cors_origins=cors)
        self.runner = create_runner(self.app, access_log=False, shutdown_timeout=shutdown_timeout, limits=limits)
        self.sock = bind("127.0.0.1", 0)
        self.port = self.sock.getsockname()[1]
        self.loop = asyncio.new_event_loop()
        ready = threading.Event()

        def main():
            asyncio.set_event_loop(self.loop)

            async def start():
                await self.runner.setup()
                self.guard = await start_site(self.runner, self.sock)

            self.loop.run_until_complete(start())
            ready.set()
            self.loop.run_forever()

        self.thread = threading.Thread(target=main, daemon=True)
        self.thread.start()
        assert ready.wait(10)

    def stop(self) -> None:
        async def stop():
            self.guard.close()
            await self.runner.cleanup()

        asyncio.run_coroutine_threadsafe(stop(), self.loop).result(10)
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)


def request(port: int, path: str, method: str = "GET", headers: dict | None = None, body: bytes | None = None):
    """One request with the path sent exactly as given; (status, headers, body)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    try:
        conn.putrequest(method, path, skip_host=False, skip_accept_encoding=True)
        for k, v in (headers or {}).items():
            conn.putheader(k, v)
        if body is not None:
            conn.putheader("Content-Length", str(len(body)))
        conn.endheaders(body)
        resp = conn.getresponse()
        data = resp.read()
        return resp.status, resp.headers, data
    finally:
        conn.close()


def raw_request(port: int, data: bytes) -> bytes:
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(data)
        out = b""
        while chunk := s.recv(65536):
            out += chunk
        return out
