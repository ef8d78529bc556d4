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
    PYTHONPATH=. python bench/small_budget_bytes.py SCENE_DIR LOD_VS_PEERS.json --budgets 0.06 --link 20:40 \
        --fill-min-kb 0,64,97.65625,128 --repeat 3 --view-args "--gpu-mem-mb 32" --out OUT.json

With `--link` the scene is served by `splatstream serve --throttle-mbps --latency-ms` on 127.0.0.1 and streamed
from its URL by a cold client (issue 31, fill31): each run also records the time to the first frame with splats
and to convergence (from the manifest request, StreamMetrics), and `--fill-min-kb` compares the client's small-cut
thresholds run by run, interleaved, `--repeat` times each (the JSON: each run, and per row the median and range);
`second_picture_s` is the first frame whose drawn tiles differ from the first picture's (coarse to fine: its first
refinement; none where the first picture was the converged one).

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


def measure_view(scene_dir: str, n: int, cam, size: int, prefetch: bool, ctx, tree, view_args: str = "",
                 url: str | None = None) -> dict:
    """One view streamed until converged: its bytes sorted (module doc) and its times (`first_frame_s`,
    `converged_s`, from the manifest request: StreamMetrics). url: stream from this server URL of the scene instead
    of the directory (with --no-cache: a cold client); the files are the directory's."""
    from lod_vs_peers import view_argv

    from cli.commands import view as view_cmd
    from cli.commands.args import parse_size
    from cli.main import build_parser
    from client_gl.gpu.gl import wait_for_gpu
    from client_gl.stream import sources
    from client_gl.streaming import StreamingSession

    raw, root, whole = tree
    log: list[tuple[str, int]] = []

    async def fetch_payload(self, entry, on_bytes=None):
        data = await orig_payload(self, entry, on_bytes)
        log.append((entry.file, len(data)))
        return data

    async def fetch_manifest(self, on_bytes=None):
        data = await orig_manifest(self, on_bytes)
        log.append(("manifest.msgpack", len(data)))
        return data

    async def revalidate_manifest(self, etag, on_bytes=None):  # HttpSource: what its fetcher asks the manifest with
        reply = await orig_manifest(self, etag, on_bytes)
        log.append(("manifest.msgpack", len(reply.data or b"")))
        return reply

    klass = sources.HttpSource if url else sources.StoreSource
    manifest_method = "revalidate_manifest" if url else "fetch_manifest"
    orig_payload, orig_manifest = klass.fetch_payload, getattr(klass, manifest_method)
    klass.fetch_payload = fetch_payload
    setattr(klass, manifest_method, revalidate_manifest if url else fetch_manifest)
    try:
        argv = view_argv(url or scene_dir, n, size, cam.eye, cam.target, cam.up, cam.fov_y_deg) + ["--quiet"]
        if url:
            argv.append("--no-cache")
        if not prefetch:
            argv.append("--no-prefetch")
        argv += shlex.split(view_args)
        args = build_parser().parse_args(argv)
        options = view_cmd._options(args)
        camera = view_cmd._fixed_camera(args, parse_size(args.size))
        session = StreamingSession.open(url or scene_dir, ctx, options)
        first_draw, second_s = None, None
        try:
            t0 = time.perf_counter()
            while True:
                rec = session.frame(camera)
                wait_for_gpu()
                if first_draw is None and rec.drawn_splats:
                    first_draw = list(session.last.draw)
                elif first_draw is not None and second_s is None and list(session.last.draw) != first_draw:
                    second_s = rec.t  # the first picture after the first one (coarse to fine: its first refinement)
                if session.converged:
                    break
                if time.perf_counter() - t0 > 300:
                    raise SystemExit("not converged after 300 s")
                if not rec.uploaded_bytes:
                    session.wait(0.005)
            draw = [int(t) for t in session.last.draw]
            downloaded = session.fetcher.stats().bytes_downloaded
            times = {k: session.metrics.to_json()[k] for k in ("first_frame_s", "converged_s", "bytes_first_frame",
                                                               "manifest_s", "pool_s", "built_s")}
            times["second_picture_s"] = second_s  # None: the first picture was the converged one
        finally:
            session.close()
    finally:
        klass.fetch_payload = orig_payload
        setattr(klass, manifest_method, orig_manifest)

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
    out["first_draw_tiles"] = len(first_draw)
    out.update(times)
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


def _stats(values: list[float]) -> dict:
    v = sorted(x for x in values if x is not None)
    if not v:
        return {"median": None, "min": None, "max": None, "n": 0}
    mid = len(v) // 2
    median = v[mid] if len(v) % 2 else (v[mid - 1] + v[mid]) / 2
    return {"median": median, "min": v[0], "max": v[-1], "n": len(v)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_dir")
    ap.add_argument("bench_json", help="a lod_vs_peers SCENE.json: its cameras and splats")
    ap.add_argument("--budgets", default="0.02,0.06,0.25,0.5")
    ap.add_argument("--size", type=int, default=384)
    ap.add_argument("--prefetch", action="store_true", help="the default prefetch (else --no-prefetch)")
    ap.add_argument("--view-args", default="", help="more `splatstream view` options, one string")
    ap.add_argument("--link", default=None, metavar="MBIT:LATENCY_MS|loopback",
                    help="stream from `splatstream serve` of the scene's parent directory on 127.0.0.1 over this "
                         "simulated link (serve --throttle-mbps --latency-ms; e.g. 20:40, the reference link), a "
                         "cold client (--no-cache), instead of reading the directory: the times then are a "
                         "network's (first frame with splats, converged: from the manifest request)")
    ap.add_argument("--fill-min-kb", default=None, metavar="KB,KB,...",
                    help="view --fill-min-kb values to compare, interleaved run by run (each view and repeat runs "
                         "them in turn): one row per budget and value")
    ap.add_argument("--compare", default=None, metavar="ARGS|ARGS|...",
                    help="as --fill-min-kb, for any `splatstream view` options: each |-separated string is one row "
                         "(e.g. \"--fill-min-kb 64|--skip-levels\")")
    ap.add_argument("--repeat", type=int, default=1, help="runs of each view and value (timing: median and range)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    from client_gl.offscreen import create_context
    from splatstream.camera import Camera

    d = json.load(open(args.bench_json))
    cams = [Camera.from_dict(c) for c in d["cameras"]]
    splats = d["splats"]
    tree = _whole_tree(args.scene_dir)
    if args.fill_min_kb is not None and args.compare is not None:
        ap.error("--fill-min-kb and --compare: give one of them")
    # each row's extra view options, and its label in the JSON
    fills: list[str | None] = [None] if args.fill_min_kb is None else args.fill_min_kb.split(",")
    variants = [(f, "" if f is None else f" --fill-min-kb {f}") for f in fills] if args.compare is None else \
        [(v.strip(), " " + v.strip()) for v in args.compare.split("|")]
    server, url = None, None
    if args.link:
        from bench_stream import serve

        scene = os.path.abspath(args.scene_dir)
        server, base = serve(os.path.dirname(scene), args.link)
        url = f"{base}/scenes/{os.path.basename(scene)}"
    load_start = os.getloadavg()
    ctx = create_context()
    rows = []
    try:
        if url:  # one run first, not recorded: the process's first session imports and compiles what later ones reuse
            measure_view(args.scene_dir, max(1, int(round(0.02 * splats))), cams[0], args.size, args.prefetch, ctx,
                         tree, args.view_args, url)
        for b in (float(x) for x in args.budgets.split(",")):
            n = int(b) if b > 1 else max(1, int(round(b * splats)))
            runs: dict[str | None, list[dict]] = {f: [] for f, _ in variants}
            for rep in range(args.repeat):
                for i, c in enumerate(cams):
                    for f, extra in variants:
                        v = measure_view(args.scene_dir, n, c, args.size, args.prefetch, ctx, tree,
                                         args.view_args + extra, url)
                        v.update(view=i, repeat=rep)
                        runs[f].append(v)
            for f, _ in variants:
                rows.append(_row(d["scene"], n, b, f, runs[f], args, args.compare is not None))
    finally:
        ctx.release()
        if server is not None:
            import signal

            server.send_signal(signal.SIGTERM)
            server.wait(10)
    if args.out:
        json.dump({"scene": d["scene"], "scene_dir": args.scene_dir, "prefetch": args.prefetch, "link": args.link,
                   "repeat": args.repeat, "load_average_start": load_start, "load_average_end": os.getloadavg(),
                   "view_args": args.view_args, "fill_min_kb": args.fill_min_kb, "compare": args.compare,
                   "rows": rows},
                  open(args.out, "w"), indent=1)
    return 0


def _row(scene: str, n: int, b: float, fill: str | None, views: list[dict], args, variant: bool = False) -> dict:
    mean = {k: sum(v[k] for v in views) / len(views) for k in views[0]
            if k != "draw" and all(isinstance(w[k], (int, float)) for w in views)}
    row = {"budget": n, "fraction": b, "views": views,
           "ratio": mean["downloaded"] / mean["drawn_tile_bytes"],
           "ratio_no_manifest": (mean["downloaded"] - mean["manifest"]) / mean["drawn_tile_bytes"],
           "ratio_no_manifest_or_pages": (mean["downloaded"] - mean["manifest"] - mean["pages"])
           / mean["drawn_tile_bytes"], "least_ratio": mean["least"] / mean["drawn_tile_bytes"],
           "least_ratio_without_root": mean["least_without_root"] / mean["drawn_tile_bytes"]}
    if variant:
        row["variant"] = fill
    elif fill is not None:
        row["fill_min_kb"] = float(fill)
    timing = ""
    if args.link:
        row["first_frame_s"] = _stats([v["first_frame_s"] for v in views])
        row["converged_s"] = _stats([v["converged_s"] for v in views])
        row["second_picture_s"] = _stats([v["second_picture_s"] for v in views])
        ff, cv = row["first_frame_s"], row["converged_s"]
        timing = (f"; {args.link}: first frame {ff['median']:.3f} s ({ff['min']:.3f}-{ff['max']:.3f}), converged "
                  f"{cv['median']:.3f} s ({cv['min']:.3f}-{cv['max']:.3f}), n = {ff['n']}; second picture "
                  + (f"{sp['median']:.3f} s (n = {sp['n']})" if (sp := row['second_picture_s'])['n'] else "none"))
    label = "" if fill is None else f" [{fill}]" if variant else f" fill {float(fill):g} KiB"
    print(f"{scene} {n:>8,}{label}: {row['ratio']:.3f}x (payloads alone {row['ratio_no_manifest_or_pages']:.3f}x): "
          f"manifest {mean['manifest']:,.0f} B, pages {mean['pages']:,.0f} B ({mean['n_pages']:.1f}, used "
          f"{mean['n_pages_used']:.1f}: {mean['pages_used']:,.0f} B), drawn "
          f"{mean['drawn']:,.0f} B ({mean['drawn_tiles']:.1f} tiles), ancestors {mean['ancestors']:,.0f} B "
          f"({mean['n_ancestors']:.1f}), other {mean['other']:,.0f} B ({mean['n_other']:.1f}); round trips "
          f"first frame {sorted({v['rt_first_frame'] for v in views})}, converged "
          f"{sorted({v['rt_converged'] for v in views})}; floor {row['least_ratio']:.3f}x "
          f"({row['least_ratio_without_root']:.3f}x without the root){timing}", flush=True)
    return row


if __name__ == "__main__":
    raise SystemExit(main())
