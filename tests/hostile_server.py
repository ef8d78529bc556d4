"""A hostile HTTP server for the streaming client (issue 37): real aiohttp on a real loopback socket, in its own
thread, serving real scene directories and misbehaving in one chosen way. Used by tests/test_hostile.py (the
short campaign, in CI) and bench/fuzz.py --network (every mode against `view --headless` and the fetcher).

    srv = HostileServer(root).start()
    srv.set_mode(Mode("drip", target="manifest"))
    url = srv.url("fruit")
    ...
    srv.stop()

A Mode names a fault, what it hits (`target`: "manifest", "payload": every payload, "root": the payloads of the
first payload requested, or "all") and how often: `times` failed answers per file, then correct ones (transient),
or None: for ever (permanent). Faults:

* "drip": the body one byte per `drip_s` seconds (headers at once).
* "stall": headers and half the body, then nothing.
* "reset": headers and a few bytes, then the connection is aborted (RST).
* "truncate": Content-Length of the whole file, half the body, then the connection is closed.
* "wrong": the right length, other bytes (a checksum mismatch).
* "gzip": the body gzipped with `Content-Encoding: gzip`, as a CDN that compresses everything would.
* "404", "500", "503": that status (503 with Retry-After: 1).
* "redirect_loop": 302 to the same URL.
* "huge_manifest": Content-Length of 100 MiB, then zeros.
* "manifest_bomb": a 64 MiB msgpack array of empty maps as the manifest.
* "nested_manifest": a manifest of 200,000 nested msgpack arrays.
* "reencode": the first `times` payload requests are answered, then the scene is swapped for `alt` (another
  scene directory): the old payloads answer 404 and the manifest is the new one (http.md 10).

Every request is recorded as (path, status).
"""
from __future__ import annotations

import asyncio
import gzip
import hashlib
import os
from dataclasses import dataclass
from pathlib import Path

from aiohttp import web
from conftest import read_manifest_dict, settle_totals
from fault_server import LoopbackServer

from splatstream.format.names import MANIFEST_NAME, PAYLOAD_NAME_RE

FAULTS = ("drip", "stall", "reset", "truncate", "wrong", "gzip", "404", "500", "503", "redirect_loop",
          "huge_manifest", "manifest_bomb", "nested_manifest", "reencode")


@dataclass(frozen=True)
class Mode:
    fault: str
    target: str = "payload"      # "manifest", "payload", "root" or "all"
    times: int | None = None     # failed answers per file, then correct ones; None: for ever
    drip_s: float = 1.0
    alt: str | None = None       # "reencode": the scene directory that replaces the served one

    def __post_init__(self) -> None:
        if self.fault not in FAULTS:
            raise ValueError(f"unknown fault {self.fault!r} (expected one of {', '.join(FAULTS)})")


class HostileServer(LoopbackServer):
    def __init__(self, root: str | os.PathLike, port: int = 0):
        super().__init__(root, port)
        self.root = Path(root)
        self.mode: Mode | None = None
        self._count: dict[str, int] = {}
        self._first_payload: str | None = None
        self._payloads_served = 0
        self._swapped: dict[str, Path] = {}

    # -- control (any thread) -------------------------------------------------------------------------------------
    def set_mode(self, mode: Mode | None) -> None:
        with self._lock:
            self.mode = mode
            self._count.clear()
            self._first_payload = None
            self._payloads_served = 0
            self._swapped.clear()
            self.log.clear()

    # -- serving (server thread) ----------------------------------------------------------------------------------
    def _fault_for(self, key: str) -> str | None:
        """The fault this request gets (None: answer correctly); counts attempts per file."""
        with self._lock:
            mode = self.mode
            if mode is None or mode.fault == "reencode":
                return None
            if key != "manifest" and self._first_payload is None:
                self._first_payload = key
            hit = (mode.target == "all" or (mode.target == "manifest" and key == "manifest")
                   or (mode.target == "payload" and key != "manifest")
                   or (mode.target == "root" and key == self._first_payload))
            if not hit:
                return None
            n = self._count[key] = self._count.get(key, 0) + 1
            return mode.fault if mode.times is None or n <= mode.times else None

    def _scene_dir(self, scene: str) -> Path:
        with self._lock:
            return self._swapped.get(scene, self.root / scene)

    def _payload_served(self, scene: str) -> None:
        with self._lock:
            mode = self.mode
            if mode is None or mode.fault != "reencode":
                return
            self._payloads_served += 1
            if self._payloads_served >= (mode.times or 1) and scene not in self._swapped and mode.alt:
                self._swapped[scene] = Path(mode.alt)

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
        fault = self._fault_for(key)
        if fault == "manifest_bomb":  # 64 MiB: a map whose one array holds 67 million empty maps
            n = (64 << 20) - 32
            return await self._send(request, path, b"\x81\xa5tiles\xdd" + n.to_bytes(4, "big") + b"\x80" * n)
        if fault == "nested_manifest":
            depth = 200_000
            return await self._send(request, path, b"\x91" * depth + b"\xc0")
        if fault == "huge_manifest":
            resp = web.StreamResponse(status=200, headers={"Content-Type": "application/vnd.msgpack"})
            resp.content_length = 100 << 20
            await resp.prepare(request)
            self._record(path, 200)
            for _ in range(100):
                await resp.write(b"\0" * (1 << 20))
            await resp.write_eof()
            return resp
        if fault == "redirect_loop":
            self._record(path, 302)
            raise web.HTTPFound(location=path)
        if fault in ("404", "500", "503"):
            status = int(fault)
            self._record(path, status)
            headers = {"Retry-After": "1"} if status == 503 else None
            return web.Response(status=status, text=f"hostile {status}", headers=headers)
        file = self._scene_dir(scene) / tail
        if not file.is_file():
            self._record(path, 404)
            raise web.HTTPNotFound()
        data = file.read_bytes()
        if key != "manifest":
            self._payload_served(scene)
        etag = '"' + hashlib.sha256(data).hexdigest() + '"'
        if key == "manifest" and fault is None and request.headers.get("If-None-Match") == etag:
            self._record(path, 304)
            return web.Response(status=304, headers={"ETag": etag})
        headers = {"ETag": etag}
        if fault == "wrong":
            data = bytes(b ^ 0x5A for b in data)
        if fault == "gzip":
            data = gzip.compress(data)
            headers["Content-Encoding"] = "gzip"
        resp = web.StreamResponse(status=200, headers=headers)
        resp.content_type = "application/octet-stream"
        resp.content_length = len(data)
        await resp.prepare(request)
        self._record(path, 200)
        if fault == "drip":
            mode = self.mode
            for i in range(len(data)):
                await resp.write(data[i:i + 1])
                await asyncio.sleep(mode.drip_s if mode else 1.0)
        elif fault == "stall":
            await resp.write(data[:len(data) // 2])
            await asyncio.sleep(3600)
        elif fault == "reset":
            await resp.write(data[:min(16, len(data) // 2)])
            await asyncio.sleep(0.05)
            request.transport.abort()
            return resp
        elif fault == "truncate":
            await resp.write(data[:len(data) // 2])
            await asyncio.sleep(0.05)
            request.transport.close()
            return resp
        else:
            await resp.write(data)
        await resp.write_eof()
        return resp

    async def _send(self, request: web.Request, path: str, body: bytes) -> web.StreamResponse:
        resp = web.Response(status=200, body=body, content_type="application/vnd.msgpack")
        self._record(path, 200)
        return resp


# -- scene variants the server can serve (written beside the clean scene) ------------------------------------------


def _load_dict(scene: Path) -> dict:
    return read_manifest_dict(scene)  # a 1.8 tile table as tile maps (conftest.tile_maps)


def _write_dict(scene: Path, m: dict) -> None:
    from splatstream.format.manifest import pack_manifest_dict

    settle_totals(m)
    (scene / MANIFEST_NAME).write_bytes(pack_manifest_dict(m))


def undecodable_scene(src: Path, dst: Path) -> str:
    """A copy of scene `src` whose leaf payload (the first leaf's base) is a valid zstd frame of the right size
    holding bytes that do not decode (NaN positions), named and listed by its real SHA-256: checksum-valid,
    undecodable. Returns the bad payload's file name."""
    import shutil

    import zstandard

    from splatstream.format.names import payload_name

    shutil.copytree(src, dst)
    m = _load_dict(dst)
    leaf = next(t for t in m["tiles"] if not t["children"])
    entry = leaf["groups"]["base"]
    raw = b"\xff" * entry["raw_bytes"]  # 0xffff.. is NaN in every float plane, out of range in the others
    data = zstandard.ZstdCompressor(level=1).compress(raw)
    sha = hashlib.sha256(data).hexdigest()
    entry.update(sha256=sha, file=payload_name(sha), bytes=len(data))
    (dst / payload_name(sha)).write_bytes(data)
    _write_dict(dst, m)
    return payload_name(sha)


def texture_bomb_scene(src: Path, dst: Path, size: int = 8192) -> None:
    """A copy of scene `src` whose root tile (the first any client fetches) declares `size` x `size` textures
    (format.md 4.1 refuses it)."""
    import shutil

    shutil.copytree(src, dst)
    m = _load_dict(dst)
    tile = min(m["tiles"], key=lambda t: (t["level"], t["splats"]))
    for section in tile["groups"]["base"]["sections"]:
        if section["kind"] == "texels":
            section["width"] = section["height"] = size
    _write_dict(dst, m)
