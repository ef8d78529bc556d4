"""For the server's tests and benchmark: synthetic scene directories (a manifest that passes validation, random
payloads of chosen sizes named by their SHA-256; not real splat data, use splatstream.encode for that: the payload
bytes are never decoded by the server, only served), a real server on loopback in a thread, and plain HTTP/1.1
requests sent exactly as written."""
from __future__ import annotations

import asyncio
import http.client
import os
import random
import socket
import threading
from collections.abc import Sequence

from splatstream.atomic import atomic_directory
from splatstream.format.layout import ALIGN, texture_size
from splatstream.format.manifest import (
    AttributeSize,
    Box,
    CameraEntry,
    LodInfo,
    Manifest,
    PayloadEntry,
    Section,
    TileEntry,
    expected_sections,
    pack_manifest,
    writer_version,
)
from splatstream.format.names import DATA_DIR, MANIFEST_NAME, payload_name, sha256_hex
from splatstream.format.presets import PRESETS
from splatstream.format.texformats import FORMATS, blob_size

FORMATS_USED = PRESETS["very-high"]  # f32x4 everywhere: the largest raw size per chunk (about 16.5 KB)
CHUNK_RAW_BYTES = 4 * 16 * 16 * 16

ORIGIN = "https://viewer.example"


def _payload(sha: str, size: int) -> tuple[PayloadEntry, int, tuple[int, int]]:
    """A base payload entry whose section table can hold a file of `size` bytes; (entry, splats, texture)."""
    chunks = size // CHUNK_RAW_BYTES + 1
    width, height = texture_size(chunks)
    sections, offset = [], 0
    for name, props in expected_sections("base", False, FORMATS_USED, chunks):
        offset += (-offset) % ALIGN
        if props["kind"] == "texels":
            n = blob_size(FORMATS[props["format"]], width, height, props["layers"])
            sections.append(Section(name, "texels", offset, n, "shuffle4", format=props["format"], width=width,
                                    height=height, layers=props["layers"]))
        else:
            n = (4 if props["dtype"] == "f32" else 2) * chunks * 2 * props["shape"][2] * props["shape"][3]
            sections.append(Section(name, "range", offset, n, "shuffle4", dtype=props["dtype"],
                                    shape=tuple(props["shape"])))
        offset += n
    entry = PayloadEntry(payload_name(sha), sha, size, offset, sum(s.size for s in sections), tuple(sections))
    return entry, chunks * 256, (width, height)


def fake_manifest(name: str, groups: Sequence[tuple[str, int]]) -> Manifest:
    """A manifest naming the payloads (sha256 hex, bytes): payload 0 is the root tile's, the others its children's."""
    box = Box((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0))
    tiles = []
    for i, (sha, size) in enumerate(groups):
        entry, splats, texture = _payload(sha, size)
        children = tuple(range(1, len(groups))) if i == 0 else ()
        tiles.append(TileEntry(i, 0 if i == 0 else 1, children, splats, -(-splats // 256), texture, box,
                               (0.0, 0.0, 0.0), 1.8, 0.0 if children == () else 0.1, {"base": entry}))
    leaves = [t for t in tiles if t.is_leaf]
    splats = sum(t.splats for t in leaves)
    m = Manifest(
        version=writer_version(FORMATS_USED), generator="server.testing", name=name, splats=splats, leaf_splats=splats,
        sh_degree=0, preset="very-high", formats=dict(FORMATS_USED), chunk_size=256, chunk_order="morton",
        bounds=box, extent_bounds=box, up=(0.0, 0.0, 1.0),
        camera=CameraEntry((3.0, 3.0, 3.0), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 50.0), sh_codebook=None,
        lod=LodInfo(len(tiles) > 1, 65536, 4.0), root=0, tiles=tuple(tiles),
        gpu_bytes=sum(t.groups["base"].gpu_bytes for t in leaves), gpu_bytes_per_splat=1.0,
        leaf_bytes_on_disk=sum(t.groups["base"].bytes for t in leaves),
        attributes={a: AttributeSize(FORMATS_USED[a], 0, 0) for a in ("position", "rotation", "scale", "color")},
        encode_seconds=0.0)
    return m.with_bytes_on_disk(m.payload_bytes())


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
            sha = sha256_hex(data)
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

    def __init__(self, root: str | os.PathLike, cors=(ORIGIN,), shutdown_timeout: float = 5.0, limits=None,
                 throttle=None):
        from .app import create_app, create_runner, start_site  # aiohttp only where a server runs
        from .run import bind

        self.app = create_app(root, cors_origins=cors, throttle=throttle)
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
