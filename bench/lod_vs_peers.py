#!/usr/bin/env python3
"""LOD against peers at a splat budget (issue 31): peer LOD levels of exactly N splats against our streamed cut.

For every real scene of at least --min-splats splats and every budget (fractions of its splats, or absolute counts):

* peers: PlayCanvas splat-transform's adaptive decimator (`--decimate-adaptive N`, pairwise merges by a field-L2
  cost with moment matching) builds a level of exactly N splats, each level from the next finer one (a chained LOD
  pyramid, as splat-transform's streamed-SOG workflow builds its levels); the levels are PLY files cached under
  --cache-dir, so a re-run only redoes our side. Optionally (--peer-sog) each level is also written as .sog for its
  size. The tools come from bench/peers/package.json (install: `cd bench/peers && npm ci`).
* ours: the scene encoded with the default preset (`splatstream encode IN OUT`, into --our-scene-dir/SCENE unless
  it already holds a manifest), then streamed per view exactly as `splatstream view OUT --headless --max-splats N
  --no-prefetch --eye .. --target .. --up .. --fov-y .. --size WxH` streams it (the view command's own option
  parsing and StreamingSession, in a subprocess), until converged; the float image of the converged frame, the
  splats drawn, the bytes downloaded and the bytes of the tiles drawn (their payloads in the manifest).

Everything is rendered with our GL renderer (client_gl, EGL) from the same orbit views (splatstream.camera.
scene_orbit_views around the detected up axis, elevation 25 deg, with the near/far rule of `splatstream view`):
peer levels and the full-detail scene uploaded as very-high (f32x4) textures. PSNR/SSIM as `splatstream eval`
(splatstream.metrics, RGB clamped to [0, 1]) against the full-detail render; "mean" PSNR is of the mean MSE.

    .venv/bin/python bench/lod_vs_peers.py                       # everything (peers cached after the first run)
    .venv/bin/python bench/lod_vs_peers.py --scenes donut,guitar --skip-peers --our-scene-dir /tmp/new_lod
    # our side only into a new directory, the peer rows from an earlier run, our encodes with extra options:
    .venv/bin/python bench/lod_vs_peers.py --scenes donut --skip-peers \
        --peers-from bench/results/lod_vs_peers_viewscale \
        --encode-args='--lod-merge auto' --our-scene-dir /tmp/ours --out-dir bench/results/NEW

Writes --out-dir/SCENE.json per scene, --out-dir/table.md and --out-dir/plot.png (PSNR against splats drawn).
Scenes marked no_images (biker: its licence forbids derived images) never have a render written to disk.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass

import numpy as np

# the views compared to 1e-12 relative: camera.look_at_near_far's arithmetic moved the orbit's eyes and near planes
# by an ulp between commits (statue-angel's stored peer rows); one rule with the eval reports' merge
from eval_merge import same_cameras  # bench/ is not a package: run from it or with it on sys.path

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
DATA = "/work/shared/data/real"
DEFAULT_BUDGETS = (0.02, 0.06, 0.25, 0.50)
STATUES = ("angel-kneeling", "angel-with-candlestick", "angel", "massa", "narcissus", "st-peter", "trumpet")


@dataclass(frozen=True)
class Scene:
    name: str
    source: str  # relative to --data-dir
    no_images: bool = False  # licence forbids derived images: nothing rendered is written to disk
    shipped_levels: tuple[int, ...] = ()  # LOD levels the source itself carries (streamed SOG), measured too
    outside: bool = False  # not in ../shared/data: only when named (--scenes), its source under --data-dir


SCENES: dict[str, Scene] = {s.name: s for s in [
    Scene("donut", "donut_sh0_no_normals.ply"),
    Scene("winter_fountain", "winter_fountain.splat"),
    Scene("guitar", "guitar.compressed.ply"),
    Scene("biker", "biker.compressed.ply", no_images=True),
    Scene("flowers", "flowers_lod/lod-meta.json", shipped_levels=(1, 2, 3)),
    *[Scene(f"statue-{s}", f"statues/{s}.sog") for s in STATUES],
    # Issue 31's own scene, held out (nothing was tuned on it): PlayCanvas engine examples/assets/splats/playbot
    # (CC-BY-4.0, Stephane Agullo, https://superspl.at/view?id=ee6d8bc4), 500,000 splats, SH2, 7 shipped levels.
    Scene("playbot", "playbot/lod-meta.json", shipped_levels=(1, 2, 3, 4, 5, 6), outside=True),
    # A third held-out scene (issues 31/32, branch heldout57): PlayCanvas engine examples/assets/splats/
    # playcanvas-logo (engine repository MIT), 307,128 splats, SH0, a SOG version 1 (meta.json + WebP planes).
    Scene("playcanvas-logo", "playcanvas-logo/meta.json", outside=True),
]}


def say(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def run(cmd: list[str], **kw) -> float:
    """Run a command (its output to our stderr); seconds taken."""
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=sys.stderr, **kw)
    return time.perf_counter() - t


def cli(*argv: str) -> list[str]:
    return [sys.executable, "-m", "cli", *argv]


# --- cameras and metrics -----------------------------------------------------------------------------------------

def view_cameras(positions: np.ndarray, up, views: int, size: int):
    """The orbit views of `splatstream eval`, with the near/far planes `splatstream view --eye/--target` derives."""
    from splatstream.camera import Camera, scene_orbit_views

    return [Camera(c.eye, c.target, c.up, c.fov_y_deg, size, size, *_near_far(c.eye, c.target))
            for c in scene_orbit_views(positions, views, size, size, up=up, elevation_deg=25.0)]


def _near_far(eye, target) -> tuple[float, float]:
    from splatstream.camera import look_at_near_far

    return look_at_near_far(eye, target)


def camera_key(cameras) -> str:
    blob = json.dumps([c.to_dict() for c in cameras], sort_keys=True).encode()
    return hashlib.sha256(blob).hexdigest()[:12]


def quality(img: np.ndarray, ref: np.ndarray) -> tuple[float, float]:
    from splatstream.metrics import psnr_from_mse, ssim

    a = np.clip(img.astype(np.float64), 0, 1)
    b = np.clip(ref.astype(np.float64), 0, 1)
    return psnr_from_mse(float(np.mean((a - b) ** 2))), float(ssim(a, b))


def mean_psnr(psnrs: list[float]) -> float:
    from splatstream.metrics import psnr_from_mse

    return psnr_from_mse(float(np.mean([10 ** (-p / 10) if math.isfinite(p) else 0.0 for p in psnrs])))


def render_views(source, cameras) -> list[np.ndarray]:
    from client_gl.offscreen import render_image

    return [np.asarray(render_image(source, cam), dtype=np.float32) for cam in cameras]


# --- peers ----------------------------------------------------------------------------------------------------------

class Peers:
    """splat-transform from bench/peers (node_modules/.bin), with its versions."""

    def __init__(self, node_dir: str):
        self.bin = os.path.join(node_dir, "node_modules", ".bin")
        self.st = os.path.join(self.bin, "splat-transform")
        if not os.path.exists(self.st):
            raise SystemExit(f"{self.st} missing: cd {node_dir} && npm ci")
        self.env = dict(os.environ, PATH=self.bin + os.pathsep + os.environ.get("PATH", ""))
        self.versions = {
            "splat-transform": self._out([self.st, "--version"]),
            "node": self._out(["node", "--version"]),
        }

    def _out(self, cmd: list[str]) -> str:
        r = subprocess.run(cmd, check=True, capture_output=True, text=True, env=self.env)
        return (r.stdout.strip() or r.stderr.strip()).splitlines()[-1]  # splat-transform prints it on stderr

    def decimate(self, src: str, n: int, out: str) -> tuple[list[str], float]:
        cmd = ["splat-transform", "-w", "-g", "cpu", "--no-tty", src, "--decimate-adaptive", str(n), out]
        return cmd, run(cmd, env=self.env)

    def to_sog(self, src: str, out: str) -> tuple[list[str], float]:
        cmd = ["splat-transform", "-w", "-g", "cpu", "--no-tty", "-q", src, out]
        return cmd, run(cmd, env=self.env)


def peer_levels(peers: Peers, scene_dir: str, full: str, counts: list[int], want_sog: bool) -> list[dict]:
    """Build (or reuse) the adaptive-decimation level of each count, finest first, each from the finer one."""
    levels = []
    src = full
    for n in sorted(counts, reverse=True):
        ply = os.path.join(scene_dir, f"st-adaptive_{n}.ply")
        meta_path = ply + ".json"
        meta = json.load(open(meta_path)) if os.path.exists(meta_path) and os.path.exists(ply) else None
        if meta is not None and meta.get("input") != os.path.basename(src):  # built from another level: redo
            meta = None
        if meta is None:
            say(f"  splat-transform --decimate-adaptive {n} <- {os.path.basename(src)}")
            cmd, secs = peers.decimate(src, n, ply)
            shown = [os.path.basename(a) if a in (src, ply) else a for a in cmd]
            meta = {"command": " ".join(shown),
                    "input": os.path.basename(src), "seconds": round(secs, 2), "versions": peers.versions}
            json.dump(meta, open(meta_path, "w"), indent=1)
        if want_sog and "sog_bytes" not in meta:
            sog = ply[:-4] + ".sog"
            say(f"  splat-transform {os.path.basename(ply)} -> .sog")
            _, secs = peers.to_sog(ply, sog)
            meta["sog_bytes"], meta["sog_seconds"] = os.path.getsize(sog), round(secs, 2)
            json.dump(meta, open(meta_path, "w"), indent=1)
        meta.update(path=ply, splats_target=n, ply_bytes=os.path.getsize(ply))
        levels.append(meta)
        src = ply
    return levels


# --- Spark ------------------------------------------------------------------------------------------------------

SPARK_C0 = 0.28209479177387814


def spark_tree(node_bin: str, full: str, prefix: str) -> dict:
    """Spark's quality LoD tree of the scene (bench/peers/spark_lod.mjs, cached), decoded from its ExtSplats arrays
    (rust/spark-lib/src/splat_encode.rs: encode_ext_splat, encode_lod_tree)."""
    if not os.path.exists(prefix + ".json"):
        os.makedirs(os.path.dirname(prefix), exist_ok=True)
        say("  spark bhatt-lod (node bench/peers/spark_lod.mjs)")
        secs = run([os.path.join(node_bin, "node"), os.path.join(HERE, "peers", "spark_lod.mjs"), full, prefix])
        meta = json.load(open(prefix + ".json"))
        meta["seconds"] = round(secs, 2)
        json.dump(meta, open(prefix + ".json", "w"), indent=1)
    meta = json.load(open(prefix + ".json"))
    n = meta["nodes"]
    e0 = np.fromfile(prefix + ".ext0.u32", np.uint32)[:4 * n].reshape(n, 4)
    e1 = np.fromfile(prefix + ".ext1.u32", np.uint32)[:4 * n].reshape(n, 4)
    lt = np.fromfile(prefix + ".lodTree.u32", np.uint32)[:4 * n].reshape(n, 4)

    def f16(words: np.ndarray, high: bool) -> np.ndarray:
        return ((words >> 16) if high else (words & 0xFFFF)).astype(np.uint16).view(np.float16).astype(np.float32)

    sh_words = [np.fromfile(f"{prefix}.{k}.u32", np.uint32)[:4 * n].reshape(n, 4)
                for k in ("sh1", "sh2", "sh3a", "sh3b") if k in meta["fields"]]
    coeffs = {0: 0, 1: 3, 2: 8, 3: 15}[meta.get("maxShDegree", 0)]
    sh_rest = (np.concatenate([_ext_rgb(w) for w in sh_words], axis=1)[:, :coeffs] if coeffs and sh_words
               else np.zeros((n, 0, 3), np.float32))
    q = e1[:, 3]
    u, v, r = (q & 0x3FF).astype(np.float32), ((q >> 10) & 0x3FF).astype(np.float32), (q >> 20).astype(np.float32)
    x, y = u / 1023 * 2 - 1, v / 1023 * 2 - 1
    z = 1 - np.abs(x) - np.abs(y)
    t = np.maximum(-z, 0)
    x, y = np.where(x >= 0, x - t, x + t), np.where(y >= 0, y - t, y + t)
    norm = np.sqrt(x * x + y * y + z * z)
    half = r / 4095 * 0.5 * np.pi
    sin = np.sin(half)
    return {
        "meta": meta, "n": n,
        "positions": e0[:, :3].copy().view(np.float32),
        "opacity": f16(e0[:, 3], False),
        "rgb": np.stack([f16(e1[:, 0], False), f16(e1[:, 0], True), f16(e1[:, 1], False)], 1),
        "ln_scales": np.stack([f16(e1[:, 1], True), f16(e1[:, 2], False), f16(e1[:, 2], True)], 1),
        "quat_wxyz": np.stack([np.cos(half), x / norm * sin, y / norm * sin, z / norm * sin], 1),
        "lod_center": np.stack([f16(lt[:, 0], False), f16(lt[:, 0], True), f16(lt[:, 1], False)], 1),
        "size": f16(lt[:, 1], True),
        "sh_rest": sh_rest,
        "child_count": (lt[:, 2] & 0xFFFF).astype(np.int64),
        "child_start": lt[:, 3].astype(np.int64),
    }


def _ext_rgb(words: np.ndarray) -> np.ndarray:
    """(N, k) shared-exponent RGB words (splat_encode.rs decode_ext_rgb) -> (N, k, 3) float32."""
    base = ((words >> 27) & 0x1F).astype(np.int32)
    div = np.exp2((base - 15).astype(np.float32)) / 255.0
    rgb = np.stack([(words >> s) & 0xFF for s in (0, 8, 16)], -1).astype(np.float32) * div[..., None]
    signs = np.stack([(words >> b) & 1 for b in (24, 25, 26)], -1).astype(bool)
    return np.where(signs, -rgb, rgb).astype(np.float32)


def spark_cut(tree: dict, cam, max_splats: int, behind: float = 0.2, cone_foveate: float = 0.4,
              cone_fov0: float = 90.0, cone_fov: float = 120.0) -> np.ndarray:
    """The cut Spark's runtime draws for a camera at a splat budget (rust/spark-rs/src/lod_tree.rs
    traverse_lod_trees and compute_pixel_scale, SparkRenderer's default foveation and one-pixel limit): from the
    root, refine the node of the largest size/distance while the count stays within the budget."""
    import heapq

    eye = np.asarray(cam.eye, np.float64)
    fwd = np.asarray(cam.target, np.float64) - eye
    fwd /= np.linalg.norm(fwd)
    limit = 2 * math.tan(math.radians(cam.fov_y_deg) / 2) / cam.height
    dot0 = math.cos(math.radians(cone_fov0 / 2))
    dot1 = min(math.cos(math.radians(cone_fov / 2)), dot0)
    centers, sizes = tree["lod_center"].astype(np.float64), tree["size"].astype(np.float64)
    cc, cs = tree["child_count"], tree["child_start"]

    def scale(idx: np.ndarray) -> np.ndarray:
        delta = centers[idx] - eye
        dist = np.maximum(np.linalg.norm(delta, axis=1), 1e-6)
        ps = sizes[idx] / dist
        d = delta @ fwd / dist
        fov = np.where(d >= dot0, 1.0, np.where(d >= dot1, cone_foveate + (1 - cone_foveate) * (d - dot1) /
                                                max(dot0 - dot1, 1e-9),
                                                behind + (cone_foveate - behind) * np.maximum(d, 0) / dot1))
        return np.where(delta @ fwd <= 0, behind, fov) * ps

    out: list[int] = []
    frontier = [(-float(scale(np.array([0]))[0]), 0)]
    count = 1
    while frontier:
        neg, i = frontier[0]
        if -neg <= limit:
            break
        if cc[i] == 0:
            heapq.heappop(frontier)
            out.append(i)
            continue
        if count - 1 + cc[i] > max_splats:
            break
        heapq.heappop(frontier)
        kids = np.arange(cs[i], cs[i] + cc[i])
        for k, ps in zip(kids.tolist(), scale(kids).tolist(), strict=True):
            if ps <= limit:
                out.append(k)
            else:
                heapq.heappush(frontier, (-ps, k))
        count += int(cc[i]) - 1
    out.extend(i for _, i in frontier)
    return np.asarray(out, np.int64)


def spark_gaussians(tree: dict, idx: np.ndarray, mode: str = "inflate"):
    """Gaussians of Spark LoD nodes. Merged nodes carry Spark's extended opacity a in 1..2 (encoding 1..5), which
    Spark's default kernel draws as a flat-topped disc (splatFragment.glsl: 1 - (1 - g)^exp((a'^2 - 1) / e)) that a
    3DGS renderer cannot draw. Two standard stand-ins bracket it: "inflate", Spark's own `lodInflate` option
    (splatVertex.glsl: opacity 1, scales times exp((a'^2 - 1) / e)^(1/3); wider than the disc), and "clamp"
    (opacity 1, scales as stored; narrower)."""
    from splatstream.gaussians import Gaussians

    a = tree["opacity"][idx].astype(np.float64)
    ext = np.minimum(a * 4 - 3, 5.0)
    grow = np.where(a > 1, (ext * ext - 1) / math.e / 3, 0.0) if mode == "inflate" else np.zeros_like(a)
    op = np.clip(np.where(a > 1, 1.0, a), 1e-6, 1 - 1e-6)
    return Gaussians(positions=tree["positions"][idx], rotations=tree["quat_wxyz"][idx],
                     log_scales=tree["ln_scales"][idx] + grow[:, None],
                     opacity_logits=np.log(op / (1 - op)), sh_dc=(tree["rgb"][idx] - 0.5) / SPARK_C0,
                     sh_rest=tree["sh_rest"][idx])


# --- ours -----------------------------------------------------------------------------------------------------------

def ensure_encoded(full: str, out: str, extra: list[str] | None = None) -> dict:
    """`splatstream encode FULL OUT [EXTRA]` (default preset) unless OUT already holds a manifest."""
    from splatstream.format.names import MANIFEST_NAME

    info_path = os.path.join(out, "lod_vs_peers_encode.json")
    if os.path.exists(os.path.join(out, MANIFEST_NAME)):
        return json.load(open(info_path)) if os.path.exists(info_path) else {"reused": True}
    if os.path.exists(out):
        shutil.rmtree(out)
    say(f"  splatstream encode {full} {out}")
    extra = list(extra or [])
    secs = run(cli("encode", full, out, *extra))
    info = {"command": " ".join(["splatstream encode", os.path.basename(full), "OUT", *extra]),
            "seconds": round(secs, 2)}
    json.dump(info, open(info_path, "w"), indent=1)
    return info


def our_views(scene_out: str, n: int, cameras, size: int, workdir: str, view_args: str = "") -> list[dict]:
    """Stream the scene at a splat budget from each camera, in a subprocess (its own GL context); per view the
    float image (loaded back), the record and the drawn tile ids. `view_args`: more `view` options, one string."""
    cams_path = os.path.join(workdir, "cameras.json")
    json.dump([c.to_dict() for c in cameras], open(cams_path, "w"))
    subprocess.run([sys.executable, os.path.abspath(__file__), "_view_worker", scene_out, str(n), cams_path,
                    workdir, str(size), view_args], check=True, stdout=sys.stderr)
    out = []
    for i in range(len(cameras)):
        rec = json.load(open(os.path.join(workdir, f"view{i}.json")))
        rec["image"] = np.load(os.path.join(workdir, f"view{i}.npy"))
        out.append(rec)
    return out


def view_argv(scene: str, n: int, size: int, eye, target, up, fov_y_deg: float, timeout_s: int = 120) -> list[str]:
    """`splatstream view SCENE --headless --max-splats N` from one of the benchmark's cameras, at size x size."""
    return ["view", scene, "--headless", "--max-splats", str(n), "--size", f"{size}x{size}",
            "--eye=" + ",".join(map(repr, eye)), "--target=" + ",".join(map(repr, target)),
            "--up=" + ",".join(map(repr, up)), "--fov-y=" + repr(fov_y_deg), "--timeout", str(timeout_s)]


def drawn_tile_bytes(manifest, tile_ids) -> tuple[int, int]:
    """The payload bytes of the drawn tiles (every group), and of their base group alone."""
    every = base = 0
    for tid in tile_ids:
        for name, group in manifest.tile(int(tid)).groups.items():
            every += group.bytes
            if name == "base":
                base += group.bytes
    return every, base


def stream_until_converged(session, camera, timeout_s: float, what: str):
    """Draw frames of a StreamingSession from one camera until it has converged (what `view --headless` waits
    for), or exit naming `what` after timeout_s seconds; the last frame's record."""
    from client_gl.gpu.gl import wait_for_gpu

    t0 = time.perf_counter()
    while True:
        rec = session.frame(camera)
        wait_for_gpu()
        if session.converged:
            return rec
        if time.perf_counter() - t0 > timeout_s:
            raise SystemExit(f"{what}: not converged after {timeout_s} s")
        if not rec.uploaded_bytes:
            session.wait(0.005)


def view_worker(scene_out: str, n: int, cams_path: str, workdir: str, size: int, view_args: str = "") -> None:
    """What `splatstream view SCENE --headless --max-splats N --no-prefetch --eye/--target/--up/--fov-y --size`
    does (its own argument parsing and options), keeping the float image and the drawn tile ids."""
    from cli.commands import view as view_cmd
    from cli.commands.args import parse_size
    from cli.main import build_parser
    from client_gl.offscreen import create_context
    from client_gl.streaming import StreamingSession
    from splatstream.camera import Camera

    cams = [Camera.from_dict(c) for c in json.load(open(cams_path))]
    ctx = create_context()
    from splatstream.format.manifest import parse_manifest
    from splatstream.format.names import MANIFEST_NAME

    manifest = parse_manifest(open(os.path.join(scene_out, MANIFEST_NAME), "rb").read())
    for i, cam in enumerate(cams):
        argv = (view_argv(scene_out, n, size, cam.eye, cam.target, cam.up, cam.fov_y_deg) + ["--no-prefetch", "--quiet"]
                + shlex.split(view_args))
        args = build_parser().parse_args(argv)
        options = view_cmd._options(args)
        camera = view_cmd._fixed_camera(args, parse_size(args.size))
        session = StreamingSession.open(scene_out, ctx, options)
        try:
            rec = stream_until_converged(session, camera, args.timeout, f"view {i}")
            image = np.asarray(session.read_image(), dtype=np.float32)[..., :3]
            draw = list(session.last.draw)
            stats = session.fetcher.stats()
            drawn_bytes, drawn_base = drawn_tile_bytes(manifest, draw)
            report = {"argv": ["splatstream", *argv], "drawn_splats": rec.drawn_splats,
                      "drawn_tiles": len(draw), "drawn_tile_ids": [int(x) for x in draw],
                      "drawn_tile_bytes": drawn_bytes, "drawn_tile_base_bytes": drawn_base,
                      "bytes_downloaded": stats.bytes_downloaded, "converged_s": session.metrics.converged_s,
                      "frames": len(session.metrics.frames), "resident_tiles": rec.resident_tiles,
                      "gl_renderer": ctx.info.get("GL_RENDERER", "?")}
        finally:
            session.close()
        np.save(os.path.join(workdir, f"view{i}.npy"), image)
        json.dump(report, open(os.path.join(workdir, f"view{i}.json"), "w"))
    ctx.release()


# --- per scene ------------------------------------------------------------------------------------------------------

def budget_counts(n: int, budgets: list[float]) -> list[int]:
    return [int(b) if b > 1 else max(1, int(round(b * n))) for b in budgets]


def unique_budgets(n: int, budgets: list[float]) -> tuple[list[float], list[int]]:
    """The budgets and their splat counts, each count once (its first budget kept): a fraction and a count that
    name the same N (0.5 and 250000 of 500,000 splats) would otherwise measure it twice and rebuild the chained
    peer level of N from itself."""
    kept: dict[int, float] = {}
    for b, nb in zip(budgets, budget_counts(n, budgets), strict=True):
        kept.setdefault(nb, b)
    return list(kept.values()), list(kept)


def measure(images: list[np.ndarray], refs: list[np.ndarray]) -> dict:
    q = [quality(a, b) for a, b in zip(images, refs, strict=True)]
    ps = [p for p, _ in q]
    ss = [s for _, s in q]
    return {"psnr_mean": _num(mean_psnr(ps)), "psnr_worst": _num(min(ps)), "ssim_mean": round(float(np.mean(ss)), 5),
            "psnr_per_view": [_num(p) for p in ps], "ssim_per_view": [round(s, 5) for s in ss]}


def _num(v: float) -> float | None:
    return None if not math.isfinite(v) else round(float(v), 3)


def run_scene(scene: Scene, args, peers: Peers | None) -> dict | None:
    from splatstream.evaluate import path_size
    from splatstream.io import read_gaussians
    from splatstream.orientation import detect_up

    sdir = os.path.join(args.cache_dir, scene.name)
    os.makedirs(sdir, exist_ok=True)
    full = os.path.join(sdir, "full.ply")
    src = os.path.join(args.data_dir, scene.source)
    if not os.path.exists(full):
        say(f"{scene.name}: splatstream convert {src} -> full.ply")
        run(cli("convert", src, full, "-q"))
    g = read_gaussians(full)
    n = len(g)
    if n < args.min_splats:
        say(f"{scene.name}: {n} splats < {args.min_splats}, skipped")
        return None
    cameras = view_cameras(g.positions, detect_up(g).up, args.views, args.size)
    key = camera_key(cameras)
    budgets, counts = unique_budgets(n, args.budgets)
    say(f"{scene.name}: {n:,} splats, SH{g.sh_degree}, budgets {counts}")

    ref_path = os.path.join(sdir, f"ref_{key}.npy")
    if os.path.exists(ref_path):
        refs = list(np.load(ref_path))
    else:
        t = time.perf_counter()
        refs = render_views(g, cameras)
        np.save(ref_path, np.stack(refs))
        say(f"  full-detail renders: {time.perf_counter() - t:.1f} s")
    if not scene.no_images and args.save_images:
        _save_pngs(os.path.join(sdir, "png"), "full", refs)

    result = {"scene": scene.name, "source": scene.source, "splats": n, "sh_degree": g.sh_degree,
              "input_bytes": path_size(src),  # an unbundled SOG's meta.json counts its planes too
              "full_ply_bytes": os.path.getsize(full), "budgets": budgets, "budget_splats": counts,
              "size": [args.size, args.size], "views": args.views,
              "cameras": [c.to_dict() for c in cameras],
              "camera_rule": "splatstream.camera.scene_orbit_views(positions, views, size, size, up=detect_up, "
                             "elevation_deg=25); near/far as `splatstream view --eye/--target`: "
                             "min(0.01, 0.01 d), max(1000, 100 d)",
              "coverage": round(float(np.mean([np.mean(r.max(axis=2) > 1e-3) for r in refs])), 4),
              "peers": [], "spark": [], "spark_clamp": [], "shipped": [], "ours": []}
    del g

    if peers is not None:
        levels = peer_levels(peers, sdir, full, counts, args.peer_sog)
        for lv in sorted(levels, key=lambda x: x["splats_target"]):
            mpath = lv["path"] + f".metrics_{key}.json"
            if os.path.exists(mpath) and os.path.getmtime(mpath) >= os.path.getmtime(lv["path"]):
                m = json.load(open(mpath))
            else:
                gl = read_gaussians(lv["path"])
                imgs = render_views(gl, cameras)
                m = measure(imgs, refs) | {"splats": len(gl)}
                json.dump(m, open(mpath, "w"))
                if not scene.no_images and args.save_images:
                    _save_pngs(os.path.join(sdir, "png"), f"st_{lv['splats_target']}", imgs)
                del gl
            row = {"label": "splat-transform --decimate-adaptive", "budget": lv["splats_target"],
                   "splats_drawn": m["splats"], "ply_bytes": lv["ply_bytes"], "sog_bytes": lv.get("sog_bytes"),
                   "build_seconds": lv["seconds"], "built_from": lv["input"], "command": lv["command"],
                   "versions": peers.versions, **{k: v for k, v in m.items() if k != "splats"}}
            result["peers"].append(row)
            say(f"  peer {row['budget']:>8,}: {row['psnr_mean']} dB (worst {row['psnr_worst']}), "
                f"SSIM {row['ssim_mean']}, {row['ply_bytes']:,} B ply")

    if peers is not None and scene.shipped_levels:
        for lv in scene.shipped_levels:
            ply = os.path.join(sdir, f"shipped_L{lv}.ply")
            if not os.path.exists(ply):
                say(f"  splat-transform -L {lv} {scene.source} -> {os.path.basename(ply)}")
                run(["splat-transform", "-w", "--no-tty", "-q", "-L", str(lv), src, ply], env=peers.env)
            mpath = ply + f".metrics_{key}.json"
            if os.path.exists(mpath) and os.path.getmtime(mpath) >= os.path.getmtime(ply):
                m = json.load(open(mpath))
            else:
                gl = read_gaussians(ply)
                m = measure(render_views(gl, cameras), refs) | {"splats": len(gl)}
                json.dump(m, open(mpath, "w"))
                del gl
            row = {"label": f"shipped level {lv} of {scene.source}", "level": lv, "budget": None,
                   "splats_drawn": m["splats"], **{k: v for k, v in m.items() if k != "splats"}}
            result["shipped"].append(row)
            say(f"  shipped L{lv} {row['splats_drawn']:>8,}: {row['psnr_mean']} dB (worst {row['psnr_worst']})")

    if peers is not None and args.spark:
        prefix = os.path.join(sdir, "spark", "tree")
        tree = spark_tree(peers.bin, full, prefix)
        for mode, series in (("inflate", "spark"), ("clamp", "spark_clamp")):
            for nb in counts:
                mpath = prefix + (".metrics" if mode == "inflate" else f".{mode}_metrics") + f"_{nb}_{key}.json"
                if os.path.exists(mpath) and os.path.getmtime(mpath) >= os.path.getmtime(prefix + ".json"):
                    m = json.load(open(mpath))
                else:
                    imgs, drawn = [], []
                    for cam in cameras:
                        idx = spark_cut(tree, cam, nb)
                        drawn.append(len(idx))
                        imgs += render_views(spark_gaussians(tree, idx, mode), [cam])
                    m = measure(imgs, refs) | {"splats_drawn_per_view": drawn}
                    json.dump(m, open(mpath, "w"))
                    if not scene.no_images and args.save_images:
                        _save_pngs(os.path.join(sdir, "png"), f"spark_{mode}_{nb}", imgs)
                meta = tree["meta"]
                row = {"label": f"spark bhatt-lod, per-view cut, merged nodes as {mode}", "budget": nb,
                       "splats_drawn": int(round(float(np.mean(m["splats_drawn_per_view"])))),
                       "tree_nodes": meta["nodes"], "lod_base": meta["lodBase"],
                       "build_seconds": meta.get("seconds"), "sh_degree_drawn": meta.get("maxShDegree", 0),
                       "versions": {"spark": meta["spark"], "node": meta["node"]},
                       "command": "node bench/peers/spark_lod.mjs full.ply tree (bhatt_lod(1.75)); cut per view as "
                                  f"traverse_lod_trees; merged nodes drawn as {mode}", **m}
                result[series].append(row)
                say(f"  {series} {nb:>8,}: {row['psnr_mean']} dB (worst {row['psnr_worst']}), "
                    f"SSIM {row['ssim_mean']}, drawn {m['splats_drawn_per_view']}")
        del tree

    if not args.skip_ours:
        out = os.path.join(args.our_scene_dir, scene.name)
        enc = ensure_encoded(full, out, shlex.split(args.encode_args))
        result["ours_encode"] = enc | {"dir": out, "bytes_on_disk": path_size(out)}
        for nb in counts:
            with tempfile.TemporaryDirectory(prefix="lvp-") as work:
                t = time.perf_counter()
                recs = our_views(out, nb, cameras, args.size, work, args.view_args)
                secs = time.perf_counter() - t
            m = measure([r["image"] for r in recs], refs)
            if not scene.no_images and args.save_images:
                _save_pngs(os.path.join(sdir, "png"), f"ours_{nb}", [r["image"] for r in recs])
            drawn = [r["drawn_splats"] for r in recs]
            row = {"label": "splatstream view --headless --max-splats", "budget": nb,
                   "splats_drawn": int(round(float(np.mean(drawn)))), "splats_drawn_per_view": drawn,
                   "bytes_downloaded_mean": int(np.mean([r["bytes_downloaded"] for r in recs])),
                   "bytes_downloaded_per_view": [r["bytes_downloaded"] for r in recs],
                   "drawn_tile_bytes_mean": int(np.mean([r["drawn_tile_bytes"] for r in recs])),
                   "drawn_tile_base_bytes_mean": int(np.mean([r["drawn_tile_base_bytes"] for r in recs])),
                   "drawn_tiles_per_view": [r["drawn_tiles"] for r in recs],
                   "drawn_tile_ids_per_view": [r["drawn_tile_ids"] for r in recs],
                   "converged_s_per_view": [r["converged_s"] for r in recs],
                   "command": " ".join(recs[0]["argv"][:6]) + " --no-prefetch --eye .. --target .. --up .. "
                              f"--fov-y .. --size {args.size}x{args.size}",
                   "gl_renderer": recs[0]["gl_renderer"], "seconds": round(secs, 1), **m}
            result["ours"].append(row)
            say(f"  ours {nb:>8,}: {row['psnr_mean']} dB (worst {row['psnr_worst']}), SSIM {row['ssim_mean']}, "
                f"drawn {drawn}, {row['bytes_downloaded_mean']:,} B downloaded ({secs:.0f} s)")
    return result


def _save_pngs(d: str, stem: str, imgs: list[np.ndarray]) -> None:
    from PIL import Image

    os.makedirs(d, exist_ok=True)
    for i, img in enumerate(imgs):
        Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(os.path.join(d, f"{stem}_v{i}.png"))


# --- outputs --------------------------------------------------------------------------------------------------------

def write_table(results: list[dict], path: str) -> str:
    lines = ["| scene | splats | budget | splat-transform PSNR (worst) | SSIM | PLY / SOG bytes | "
             "Spark drawn | Spark PSNR inflate (worst) | SSIM | Spark PSNR clamp (worst) | SSIM | "
             "ours drawn | ours PSNR (worst) | SSIM | "
             "ours downloaded | ours drawn-tile bytes |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]

    def db(r):
        return "-" if r is None else f"{_f(r['psnr_mean'])} ({_f(r['psnr_worst'])})"

    def ss(r):
        return "-" if r is None else f"{r['ssim_mean']:.4f}"

    for res in results:
        peers = {r["budget"]: r for r in res["peers"]}
        spark = {r["budget"]: r for r in res.get("spark", [])}
        clamp = {r["budget"]: r for r in res.get("spark_clamp", [])}
        ours = {r["budget"]: r for r in res["ours"]}
        for b, nb in zip(res["budgets"], res["budget_splats"], strict=True):
            p, k, c, o = peers.get(nb), spark.get(nb), clamp.get(nb), ours.get(nb)
            pb = "-" if p is None else f"{p['ply_bytes']:,}" + (f" / {p['sog_bytes']:,}" if p.get("sog_bytes") else "")
            lines.append(
                f"| {res['scene']} | {res['splats']:,} | {budget_label(b, nb)} | {db(p)} | {ss(p)} | {pb} | "
                f"{'-' if k is None else _drawn(k)} | {db(k)} | {ss(k)} | {db(c)} | {ss(c)} | "
                f"{'-' if o is None else _drawn(o)} | {db(o)} | {ss(o)} | "
                f"{'-' if o is None else format(o['bytes_downloaded_mean'], ',')} | "
                f"{'-' if o is None else format(o['drawn_tile_bytes_mean'], ',')} |")
    shipped = [(res["scene"], r) for res in results for r in res.get("shipped", [])]
    if shipped:
        lines += ["", "Levels a source ships itself (its streamed SOG's own LOD levels, splat-transform -L):", "",
                  "| scene | level | splats | PSNR (worst) | SSIM |", "|---|---:|---:|---:|---:|"]
        lines += [f"| {name} | {r['level']} | {r['splats_drawn']:,} | {db(r)} | {ss(r)} |" for name, r in shipped]
    text = "\n".join(lines) + "\n"
    with open(path, "w") as f:
        f.write(text)
    return text


def budget_label(budget: float, splats: int) -> str:
    """'10,000 (2 %)' for a fraction of the scene, '8,406' for a count (budgets > 1 are splat counts)."""
    return f"{splats:,} ({budget * 100:g} %)" if budget <= 1 else f"{splats:,}"


def _f(v) -> str:
    return "inf" if v is None else f"{v:.2f}"


def _drawn(o: dict) -> str:
    d = o.get("splats_drawn_per_view") or [o["splats_drawn"]]
    s = f"{min(d):,}" if min(d) == max(d) else f"{min(d):,}-{max(d):,}"
    return s + (" (over)" if max(d) > o["budget"] else "")


def plot(results: list[dict], path: str) -> None:
    """PSNR (mean over views) against splats drawn (log axis), one panel per scene; peers vs ours (and a result's
    "ours_default" rows, where it has them, as a second series of ours). Pillow only."""
    from PIL import Image, ImageDraw, ImageFont

    cols = min(4, max(1, len(results)))
    rows = math.ceil(len(results) / cols)
    pw, ph = 380, 290
    img = Image.new("RGB", (4 * pw, rows * ph + 40), "white")  # 4 panels wide: the title whole, one scene too
    d = ImageDraw.Draw(img)
    try:
        font = ImageFont.load_default(size=12)
        big = ImageFont.load_default(size=15)
    except TypeError:
        font = big = ImageFont.load_default()
    d.text((10, 10), "PSNR (dB, mean of views vs full detail) against splats drawn (log); red: splat-transform "
           "levels, green: Spark cuts (dark: lodInflate, light: clamped), blue: splatstream view "
           "--max-splats; orange: a source's own levels; grey ticks: budgets",
           fill="black", font=big)
    if any(r.get("ours_default") for r in results):  # a second encode of ours beside it (bench/cpurefine31_table.py)
        d.text((10, 26), "light blue: our default encode; blue: the encode compared with it", fill="black", font=font)
    colours = {"peers": (220, 50, 47), "spark": (40, 160, 60), "spark_clamp": (150, 210, 150),
               "shipped": (240, 150, 30), "ours_default": (140, 180, 235), "ours": (38, 100, 210)}
    series = ("peers", "spark", "spark_clamp", "shipped", "ours_default", "ours")  # ours_default: a second encode
    for k, res in enumerate(results):
        ox, oy = (k % cols) * pw, 40 + (k // cols) * ph
        left, right, top, bottom = ox + 50, ox + pw - 15, oy + 25, oy + ph - 40
        pts = {s: [(r["splats_drawn"], r["psnr_mean"]) for r in res.get(s, []) if r["psnr_mean"] is not None]
               for s in series}
        allp = [p for s in series for p in pts[s]]
        if not allp:
            continue
        xs = [x for x, _ in allp] + list(res["budget_splats"])
        ys = [y for _, y in allp]
        x0, x1 = 10 ** math.floor(math.log10(min(xs))), 10 ** math.ceil(math.log10(max(xs)))
        y0, y1 = 5 * math.floor(min(ys) / 5), 5 * math.ceil(max(ys) / 5 + 1e-9)
        if y1 - y0 < 10:
            y1 = y0 + 10

        def px(x, _x0=x0, _x1=x1, _l=left, _r=right):
            return _l + (math.log10(x) - math.log10(_x0)) / (math.log10(_x1) - math.log10(_x0)) * (_r - _l)

        def py(y, _y0=y0, _y1=y1, _t=top, _b=bottom):
            return _b - (y - _y0) / (_y1 - _y0) * (_b - _t)

        for dec in range(int(round(math.log10(x0))), int(round(math.log10(x1))) + 1):
            for m in (1, 2, 5):
                x = m * 10.0 ** dec
                if x0 <= x <= x1:
                    d.line([(px(x), top), (px(x), bottom)], fill=(230, 230, 230))
                    lab = f"{x / 1e6:g}M" if x >= 1e6 else f"{x / 1e3:g}k" if x >= 1e3 else f"{x:,.0f}"
                    d.text((px(x) - d.textlength(lab, font=font) / 2, bottom + 4), lab, fill="black", font=font)
        for y in range(int(y0), int(y1) + 1, 5):
            d.line([(left, py(y)), (right, py(y))], fill=(230, 230, 230))
            d.text((left - 8 - d.textlength(str(y), font=font), py(y) - 7), str(y), fill="black", font=font)
        for nb in res["budget_splats"]:
            d.line([(px(nb), bottom - 6), (px(nb), bottom)], fill=(120, 120, 120), width=2)
        d.rectangle([left, top, right, bottom], outline="black")
        title = f"{res['scene']} ({res['splats']:,} splats, SH{res['sh_degree']})"
        d.text((left + (right - left) / 2 - d.textlength(title, font=font) / 2, oy + 6), title, fill="black",
               font=font)
        d.text((left + (right - left) / 2 - 30, bottom + 20), "splats drawn", fill=(90, 90, 90), font=font)
        for s in series:
            c = [(px(x), py(y)) for x, y in sorted(pts[s])]
            if len(c) > 1:
                d.line(c, fill=colours[s], width=2)
            for cx, cy in c:
                if s in ("peers", "shipped"):
                    d.ellipse([cx - 4, cy - 4, cx + 4, cy + 4], fill=colours[s], outline="black")
                elif s.startswith("spark"):
                    d.polygon([(cx, cy - 5), (cx - 5, cy + 4), (cx + 5, cy + 4)], fill=colours[s], outline="black")
                else:
                    d.rectangle([cx - 4, cy - 4, cx + 4, cy + 4], fill=colours[s], outline="black")
    img.save(path)


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv and argv[0] == "_view_worker":
        view_worker(argv[1], int(argv[2]), argv[3], argv[4], int(argv[5]), argv[6] if len(argv) > 6 else "")
        return 0
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    inside = [n for n, s in SCENES.items() if not s.outside]
    ap.add_argument("--scenes", default=",".join(inside),
                    help=f"comma list (default every scene of ../shared/data: {', '.join(inside)}; outside it, "
                         f"named only: {', '.join(n for n in SCENES if n not in inside)})")
    ap.add_argument("--budgets", default=",".join(map(str, DEFAULT_BUDGETS)),
                    help="comma list: fractions of the scene's splats (<= 1) or splat counts (default 0.02,0.06,"
                         "0.25,0.5)")
    ap.add_argument("--views", type=int, default=4, help="orbit views (default 4)")
    ap.add_argument("--size", type=int, default=384, help="square image size in pixels (default 384)")
    ap.add_argument("--data-dir", default=DATA)
    ap.add_argument("--cache-dir", default=os.path.join(HERE, "peers_cache"),
                    help="canonical PLYs, peer levels and their metrics, full-detail renders (git-ignored)")
    ap.add_argument("--our-scene-dir", default=None,
                    help="our encoded scenes, one directory per scene (encoded there unless it holds a manifest; "
                         "default CACHE/ours)")
    ap.add_argument("--out-dir", default=os.path.join(HERE, "results", "lod_vs_peers"))
    ap.add_argument("--peers-node-dir", default=os.path.join(HERE, "peers"))
    ap.add_argument("--min-splats", type=int, default=45000)
    ap.add_argument("--skip-peers", action="store_true", help="only our side (peer rows from earlier JSON kept)")
    ap.add_argument("--peers-from", default=None,
                    help="with --skip-peers: the peer rows (splat-transform, Spark, shipped levels) of DIR/SCENE.json "
                         "where --out-dir has no JSON of the scene yet (the same cameras required, floats to 1e-12 "
                         "relative)")
    ap.add_argument("--encode-args", default="",
                    help="extra arguments of our `splatstream encode` (e.g. '--lod-merge auto'; a scene directory "
                         "that already holds a manifest is reused as it is)")
    ap.add_argument("--view-args", default="",
                    help="extra options of our `splatstream view` (e.g. '--sh-bands all'), one string")
    ap.add_argument("--skip-ours", action="store_true")
    ap.add_argument("--no-spark", dest="spark", action="store_false",
                    help="without Spark's LoD (its tree build and per-view cuts)")
    ap.add_argument("--peer-sog", action="store_true", help="also write each peer level as .sog for its size")
    ap.add_argument("--save-images", action="store_true", help="PNGs of every render under CACHE/SCENE/png")
    ap.add_argument("--report-only", action="store_true", help="only the table and plot from --out-dir's JSONs")
    args = ap.parse_args(argv)
    args.budgets = [float(b) for b in args.budgets.split(",")]
    args.our_scene_dir = args.our_scene_dir or os.path.join(args.cache_dir, "ours")
    names = [] if args.report_only else [s for s in args.scenes.split(",") if s]
    for s in names:
        if s not in SCENES:
            ap.error(f"unknown scene {s} (known: {', '.join(SCENES)})")
    os.makedirs(args.out_dir, exist_ok=True)
    peers = None if args.skip_peers or not names else Peers(args.peers_node_dir)
    from splatstream.evaluate import source_version

    results = []
    for i, name in enumerate(names):
        say(f"== scene {i + 1}/{len(names)}: {name}")
        t = time.perf_counter()
        res = run_scene(SCENES[name], args, peers)
        if res is None:
            continue
        jpath = os.path.join(args.out_dir, f"{name}.json")
        old_path = jpath
        if not os.path.exists(jpath) and peers is None and args.peers_from:
            old_path = os.path.join(args.peers_from, f"{name}.json")
        if os.path.exists(old_path) and (peers is None or not args.spark):  # keep the peer rows measured before
            old = json.load(open(old_path))
            if not same_cameras(old.get("cameras"), res["cameras"]):
                say(f"   {old_path}: other cameras, its peer rows not kept")
            else:
                if peers is None:
                    res["peers"] = old.get("peers", [])
                    res["peer_versions"] = old.get("peer_versions")
                for k in ("spark", "spark_clamp", "shipped"):
                    if not res[k]:
                        res[k] = old.get(k, [])
        if peers is not None:
            res["peer_versions"] = peers.versions
        if args.skip_ours and os.path.exists(jpath):
            old = json.load(open(jpath))
            if same_cameras(old.get("cameras"), res["cameras"]):
                res["ours"], res["ours_encode"] = old.get("ours", []), old.get("ours_encode")
        res["splatstream"] = source_version()
        res["machine"] = {"python": platform.python_version(), "cpus": os.cpu_count(), "platform": platform.platform()}
        res["seconds"] = round(time.perf_counter() - t, 1)
        with open(jpath, "w") as f:
            json.dump(res, f, indent=1)
        results.append(res)
        say(f"   wrote {jpath} ({res['seconds']} s)")
    # the table and the plot cover every scene with a JSON in --out-dir (earlier runs included), in SCENES order
    allres = []
    for name in SCENES:
        p = os.path.join(args.out_dir, f"{name}.json")
        if os.path.exists(p):
            allres.append(json.load(open(p)))
    print(write_table(allres, os.path.join(args.out_dir, "table.md")))
    plot(allres, os.path.join(args.out_dir, "plot.png"))
    say(f"wrote {args.out_dir}/table.md and plot.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
