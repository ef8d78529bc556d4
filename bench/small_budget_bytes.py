#!/usr/bin/env python3
"""Where a budgeted view's bytes go (issue 31, "Fetch what can be drawn"): the real client streams an encoded scene
at a splat budget from the orbit views a lod_vs_peers JSON recorded (the same cameras), until converged, with every
file it reads logged, and sorts the bytes into the root manifest, manifest pages, the payloads of the tiles drawn
at convergence, the payloads of their ancestors fetched and not drawn (coarse-to-fine and the first frame's root,
client.md 4) and any other payload (prefetch); with the round trips (a file's depth: the manifest 1, a page or a
payload one more than the file that names it) before the first frame with splats and to convergence; and a floor
on what any manifest layout of the format could read for the same cut (`least_bytes`).

    PYTHONPATH=. python bench/small_budget_bytes.py SCENE_DIR LOD_VS_PEERS.json --budgets 0.02,0.06 \
        [--prefetch] [--view-args "--fill-gap 5"] [--out OUT.json]

`SCENE_DIR` is streamed as `splatstream view SCENE_DIR --headless --max-splats N [--no-prefetch]` streams it (the
view command's option parsing, in this process); the JSON gives the cameras and the scene's splats.
"""
from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(HERE))
sys.path.insert(0, HERE)


def _whole_tree(scene_dir: str):
    from splatstream.format.manifest import parse_manifest
    from splatstream.format.manifest.paging import resolve_pages

    raw = open(os.path.join(scene_dir, "manifest.msgpack"), "rb").read()
    root = parse_manifest(raw)
    whole = resolve_pages(root, lambda ref: open(os.path.join(scene_dir, ref.file), "rb").read(), scene_dir,
                          len(raw))
    return raw, root, whole


def measure_view(scene_dir: str, n: int, cam, size: int, prefetch: bool, ctx, tree, view_args: str = "") -> dict:
    from lod_vs_peers import view_argv

    from cli.commands import view as view_cmd
    from cli.commands.args import parse_size
    from cli.main import build_parser
    from client_gl.gpu.gl import wait_for_gpu
    from client_gl.stream import sources
    from client_gl.streaming import StreamingSession

    raw, root, whole = tree
    log: list[tuple[str, int]] = []
    orig_payload, orig_manifest = sources.StoreSource.fetch_payload, sources.StoreSource.fetch_manifest

    async def fetch_payload(self, entry, on_bytes=None):
        data = await orig_payload(self, entry, on_bytes)
        log.append((entry.file, len(data)))
        return data

    async def fetch_manifest(self, on_bytes=None):
        data = await orig_manifest(self, on_bytes)
        log.append(("manifest.msgpack", len(data)))
        return data

    sources.StoreSource.fetch_payload, sources.StoreSource.fetch_manifest = fetch_payload, fetch_manifest
    try:
        argv = view_argv(scene_dir, n, size, cam.eye, cam.target, cam.up, cam.fov_y_deg) + ["--quiet"]
        if not prefetch:
            argv.append("--no-prefetch")
        argv += shlex.split(view_args)
        args = build_parser().parse_args(argv)
        options = view_cmd._options(args)
        camera = view_cmd._fixed_camera(args, parse_size(args.size))
        session = StreamingSession.open(scene_dir, ctx, options)
        first_draw = None
        try:
            t0 = time.perf_counter()
            while True:
                rec = session.frame(camera)
                wait_for_gpu()
                if first_draw is None and rec.drawn_splats:
                    first_draw = list(session.last.draw)
                if session.converged:
                    break
                if time.perf_counter() - t0 > 300:
                    raise SystemExit("not converged after 300 s")
                if not rec.uploaded_bytes:
                    session.wait(0.005)
            draw = [int(t) for t in session.last.draw]
            downloaded = session.fetcher.stats().bytes_downloaded
        finally:
            session.close()
    finally:
        sources.StoreSource.fetch_payload, sources.StoreSource.fetch_manifest = orig_payload, orig_manifest

    # what each file is, and its depth in round trips
    by_id = {t.id: t for t in whole.tiles}
    parent = {c: t.id for t in whole.tiles for c in t.children}
    home: dict[int, int | None] = {t.id: None for t in root.tiles}  # tile -> head of the page holding it
    page_of: dict[str, int] = {}  # page file -> head
    for t in whole.tiles:
        if t.page is not None:
            page_of[t.page.file] = t.id
    for t in whole.tiles:
        if t.id in home:
            continue
        a = parent[t.id]
        while by_id[a].page is None:
            a = parent[a]
        home[t.id] = a
    depth_memo: dict[int | None, int] = {None: 1}

    def file_depth(head: int | None) -> int:  # depth of the file that holds tiles whose page head is `head`
        if head not in depth_memo:
            depth_memo[head] = file_depth(home[head]) + 1
        return depth_memo[head]

    payload_of = {g.file: (t.id, name) for t in whole.tiles for name, g in t.groups.items()}
    drawn = set(draw)
    ancestors = set()
    for t in draw:
        a = parent.get(t)
        while a is not None:
            ancestors.add(a)
            a = parent.get(a)
    # a page is used when it holds a tile drawn at convergence or an ancestor of one (the page the cut went through)
    used_heads = {home[t] for t in drawn | ancestors} - {None}
    out = {"manifest": 0, "pages": 0, "n_pages": 0, "pages_used": 0, "n_pages_used": 0, "drawn": 0, "ancestors": 0,
           "n_ancestors": 0, "other": 0, "n_other": 0, "rt_converged": 0}
    for f, nb in log:
        if f == "manifest.msgpack":
            out["manifest"] += nb
            d = 1
        elif f in page_of:
            out["pages"] += nb
            out["n_pages"] += 1
            if page_of[f] in used_heads:
                out["pages_used"] += nb
                out["n_pages_used"] += 1
            d = file_depth(page_of[f])
        else:
            tid, _ = payload_of[f]
            d = file_depth(home[tid]) + 1
            if tid in drawn:
                out["drawn"] += nb
            elif tid in ancestors:
                out["ancestors"] += nb
                out["n_ancestors"] += 1
            else:
                out["other"] += nb
                out["n_other"] += 1
        out["rt_converged"] = max(out["rt_converged"], d)
    out["rt_first_frame"] = max(file_depth(home[t]) + 1 for t in first_draw)
    out["drawn_tiles"] = len(draw)
    out["draw"] = sorted(draw)  # the cut drawn at convergence (the same cut: the same PSNR)
    out["drawn_tile_bytes"] = sum(g.bytes for t in draw for g in by_id[t].groups.values())
    out["downloaded"] = downloaded
    out["logged"] = sum(nb for _, nb in log)
    out["drawn_splats"] = sum(by_id[t].splats for t in draw)
    out["least"] = least_bytes(tree, draw, parent)
    out["least_without_root"] = least_bytes(tree, draw, parent, with_root=False)
    return out


def least_bytes(tree, draw: list[int], parent: dict[int, int], with_root: bool = True) -> int:
    """A floor on what any manifest layout and fetch order of this format reads for the cut `draw` with the root
    drawn first (the first frame): the payloads of the drawn tiles and of the root, the whole manifest's keys
    other than its tiles (read once, whatever the layout), and the rows of the drawn tiles and their ancestors
    (which the reader must know to reach them) at the whole compact table's bytes a row: its digests at 32 B a
    payload, the rest its compressed share (optimistic: a part of a table compresses worse than the whole).
    with_root False: the same without the root's payload (a first frame drawn from the cut itself)."""
    import msgpack
    raw, root, whole = tree
    m = msgpack.unpackb(raw, raw=False)
    table = m.get("tile_table_zstd")
    keys = len(raw) - (len(table) if table is not None else 0)
    groups = len(whole.tiles[0].groups)
    rest_per_row = (len(table) - 32 * groups * len(whole.tiles)) / len(whole.tiles) if table is not None else 0.0
    by_id = {t.id: t for t in whole.tiles}
    rows = set(draw)
    for t in draw:
        a = parent.get(t)
        while a is not None:
            rows.add(a)
            a = parent.get(a)
    first = {root.root} if with_root else set()
    payloads = sum(g.bytes for t in set(draw) | first for g in by_id[t].groups.values())
    return int(keys + len(rows) * (32 * groups + rest_per_row) + payloads)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir")
    ap.add_argument("bench_json", help="a lod_vs_peers SCENE.json: its cameras and splats")
    ap.add_argument("--budgets", default="0.02,0.06,0.25,0.5")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--prefetch", action="store_true", help="the default prefetch (else --no-prefetch)")
    ap.add_argument("--view-args", default="", help="more `splatstream view` options, one string")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from client_gl.offscreen import create_context
    from splatstream.camera import Camera

    d = json.load(open(args.bench_json))
    cams = [Camera.from_dict(c) for c in d["cameras"]]
    splats = d["splats"]
    tree = _whole_tree(args.scene_dir)
    ctx = create_context()
    rows = []
    for b in (float(x) for x in args.budgets.split(",")):
        n = int(b) if b > 1 else max(1, int(round(b * splats)))
        views = [measure_view(args.scene_dir, n, c, args.size, args.prefetch, ctx, tree, args.view_args) for c in cams]
        mean = {k: sum(v[k] for v in views) / len(views) for k in views[0] if k != "draw"}
        row = {"budget": n, "fraction": b, "views": views,
               "ratio": mean["downloaded"] / mean["drawn_tile_bytes"],
               "ratio_no_manifest": (mean["downloaded"] - mean["manifest"]) / mean["drawn_tile_bytes"],
               "ratio_no_manifest_or_pages": (mean["downloaded"] - mean["manifest"] - mean["pages"])
               / mean["drawn_tile_bytes"], "least_ratio": mean["least"] / mean["drawn_tile_bytes"],
               "least_ratio_without_root": mean["least_without_root"] / mean["drawn_tile_bytes"]}
        rows.append(row)
        print(f"{d['scene']} {n:>8,}: {row['ratio']:.3f}x (payloads alone {row['ratio_no_manifest_or_pages']:.3f}x): "
              f"manifest {mean['manifest']:,.0f} B, pages {mean['pages']:,.0f} B ({mean['n_pages']:.1f}, used "
              f"{mean['n_pages_used']:.1f}: {mean['pages_used']:,.0f} B), drawn "
              f"{mean['drawn']:,.0f} B ({mean['drawn_tiles']:.1f} tiles), ancestors {mean['ancestors']:,.0f} B "
              f"({mean['n_ancestors']:.1f}), other {mean['other']:,.0f} B ({mean['n_other']:.1f}); round trips "
              f"first frame {[v['rt_first_frame'] for v in views]}, converged {[v['rt_converged'] for v in views]}; "
              f"floor {row['least_ratio']:.3f}x ({row['least_ratio_without_root']:.3f}x without the root)",
              flush=True)
    ctx.release()
    if args.out:
        json.dump({"scene": d["scene"], "scene_dir": args.scene_dir, "prefetch": args.prefetch, "rows": rows},
                  open(args.out, "w"), indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
