#!/usr/bin/env python3
"""What a budgeted view would read of a smaller root manifest (issue 31, branch smallroot31), for the cuts a
bench/small_budget_bytes.py run of the unpaged scene drew, with that run's payload bytes.

Layouts, each from the tree's shape (`--share`: the root manifest down to the shallowest level holding at least
that share of the scene's splats, level a):

* `pages15`: format 1.5's pages (format.md 6.1) with k = a + 1, as split_pages writes them: a view reads the root
  manifest and the page of every head above a drawn tile (the least today's client could read of them: no page
  the cut does not go through, no payload fetched and given up; its real reads: small_budget_bytes.py on a
  `bench/bench_pages.py --repage SCENE OUT --default-levels K` copy).
* `shared`: the same levels, but ONE page file holding every tile below the root manifest (a format the spec does
  not have: a page named by every head of its layer).
* `bands`: the root manifest to level a, then one page file for each `--band` levels of the whole tree below it
  (not in the spec either; pages31's "band pages").
* `shares` (`--band-shares 0.02,0.10`, branch bandpage): level bands from the tree's shape, the root manifest to
  the shallowest level holding the first share of the splats, a first band page to the level holding the next
  share, and so on, the last band page to the leaves (issue 31's two-band layout: root, band 1, band 2).
  Two readings: `shares` reads a band where a drawn tile or an ancestor of one lies in it (the floor: a client
  that asks for a band only where the cut goes into it); `shares_rule` also reads band j (and the root tile's
  payload for the first frame, as today's client does while a page it wants loads) in every view where a
  `--pages-run`'s real client, on a format 1.5 copy whose pages hang from the heads of band j - 1's last level
  (`bench_pages.py --repage SCENE OUT --default-levels EDGE+1`), read any page: today's page rule (client.md
  1.11) wants band j wherever it wants one of those heads' pages (a head crossing the frustum, whose children
  may all lie outside, or one whose least children fit the budget), at the budgets that run measured.

For `shared` and `bands` the part sizes are measured (the tiles packed as the encoder packs a page, the root with
the manifest's keys and a page entry per part); a part is read where a drawn tile or an ancestor of one lies in
it. Where a cut under `--fill-min-kb` waits for a page, today's client fetches the root tile's payload for the
first frame (client.md 1.11): counted. Round trips to convergence: the manifest, each part the cut goes through,
the payloads.

    PYTHONPATH=. python bench/small_root_estimate.py SCENE_DIR BEFORE.json [--share 0.02] [--band 2] [--out OUT.json]
        [--band-shares 0.02,0.10 [--pages-run K5.json --pages-run K7.json]]
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys

import msgpack

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from splatstream.format.manifest import parse_manifest  # noqa: E402
from splatstream.format.manifest.paging import pack_page, split_pages  # noqa: E402
from splatstream.format.manifest.wire import pack_manifest  # noqa: E402


def level_holding(m, share: float) -> int:
    """The shallowest level whose tiles hold at least `share` of the scene's splats."""
    per_level = [0] * m.levels
    for t in m.tiles:
        per_level[t.level] += t.splats
    return next((lv for lv, n in enumerate(per_level) if n >= share * m.leaf_splats), m.levels - 1)


def part_layout(m, raw: bytes, edges: list[int]) -> tuple[list[int], dict[int, int]]:
    """Each part's bytes (the root manifest first) and the part of each level, for parts ending at `edges`."""
    keys = len(raw) - len(msgpack.unpackb(raw, raw=False)["tile_table_zstd"])
    bounds = [-1, *edges, m.levels - 1]
    sizes, part = [], {}
    for i in range(len(bounds) - 1):
        tiles = [t for t in m.tiles if bounds[i] < t.level <= bounds[i + 1]]
        for lv in range(bounds[i] + 1, bounds[i + 1] + 1):
            part[lv] = i
        body = len(pack_page(m.version, m.root, tiles))
        sizes.append(body + (keys + 40 * (len(bounds) - 2) if i == 0 else 0))  # the root: a page entry a part
    return sizes, part


def band_edges(m, shares: list[float]) -> list[int]:
    """The last level of the root manifest and of each band page but the last: the levels holding each share."""
    edges = sorted({level_holding(m, s) for s in shares})
    return [e for e in edges if e < m.levels - 1]


def estimate(scene_dir: str, before_json: str, share: float, band: int, fill_min: int,
             band_shares: list[float] | None = None, pages_run: str | None = None) -> dict:
    raw = open(os.path.join(scene_dir, "manifest.msgpack"), "rb").read()
    m = parse_manifest(raw)
    if m.paged is not None:
        raise SystemExit(f"{scene_dir}: paged already; give an unpaged scene")
    by_id = {t.id: t for t in m.tiles}
    parent = {c: t.id for t in m.tiles for c in t.children}
    a = level_holding(m, share)
    k = a + 1
    p15 = split_pages(m, k)
    root15 = len(pack_manifest(p15.root))
    heads = sorted((t for t in m.tiles if (t.level + 1) % k == 0 and t.children), key=lambda t: (-t.level, t.id))
    page_of_head = {h.id: ref.bytes for h, (ref, _) in zip(heads, p15.pages, strict=True)}
    layouts = {"shared": part_layout(m, raw, [a]),
               "bands": part_layout(m, raw, list(range(a, m.levels - 1, band)))}
    edges = band_edges(m, band_shares) if band_shares else None
    if edges:
        layouts["shares"] = part_layout(m, raw, edges)
    # band j's reading by today's rule: a run on a format 1.5 copy whose pages hang from the heads of band j - 1's
    # last level (k = that level + 1), one run a band
    rule_runs: dict[int, dict[float, list[dict]]] = {}
    for path in pages_run or ():
        if not edges:
            raise SystemExit("--pages-run needs --band-shares")
        pr = json.load(open(path))
        k = parse_manifest(open(os.path.join(pr["scene_dir"], "manifest.msgpack"), "rb").read()).paged.page_levels
        if k - 1 not in edges:
            raise SystemExit(f"{path}: its pages hang from level {k - 1}, no band's edge ({edges})")
        rule_runs[edges.index(k - 1) + 1] = {r["fraction"]: r["views"] for r in pr["rows"]}
    root_bytes = by_id[m.root].groups["base"].bytes
    rows = []
    for row in json.load(open(before_json))["rows"]:
        views = row["views"]
        drawn = statistics.mean(v["drawn_tile_bytes"] for v in views)
        res = {"budget": row["budget"], "fraction": row["fraction"], "drawn": drawn,
               "today": statistics.mean(v["downloaded"] for v in views) / drawn,
               "today_rt": max(v["rt_converged"] for v in views)}
        reads = []
        for v in views:
            pages = set()
            for t in v["draw"]:
                up = parent.get(t)
                while up is not None:
                    if up in page_of_head:
                        pages.add(up)
                    up = parent.get(up)
            reads.append(v["downloaded"] - v["manifest"] + root15 + sum(page_of_head[h] for h in pages))
        res["pages15"] = statistics.mean(reads) / drawn
        for name, (sizes, part) in layouts.items():
            reads, rts = [], []
            for v in views:
                deepest = max(part[by_id[t].level] for t in v["draw"])
                extra = root_bytes if deepest > 0 and v["drawn_tile_bytes"] <= fill_min and \
                    v["ancestors"] == 0 and m.root not in v["draw"] else 0
                reads.append(v["downloaded"] - v["manifest"] + sum(sizes[:deepest + 1]) + extra)
                rts.append(2 + deepest)
            res[name] = statistics.mean(reads) / drawn
            res[name + "_rt"] = max(rts)
        if "shares" in layouts:
            sizes, part = layouts["shares"]
            for name in ("shares", "shares_rule") if rule_runs else ("shares",):
                reads, rts, parts_read, unused, other_cut = [], [], [], 0, 0
                for i, v in enumerate(views):
                    deepest = max(part[by_id[t].level] for t in v["draw"])
                    used = deepest
                    for j, runs in sorted(rule_runs.items()) if name == "shares_rule" else ():
                        rv = runs.get(row["fraction"])
                        if rv is None:
                            continue
                        other_cut += sorted(rv[i]["draw"]) != sorted(v["draw"])
                        if rv[i]["n_pages"] > 0 and deepest == j - 1:
                            deepest = j  # band j wanted by today's rule (a page of one of its heads), not used
                    unused += deepest - used
                    extra = root_bytes if deepest > 0 and v["drawn_tile_bytes"] <= fill_min and \
                        v["ancestors"] == 0 and m.root not in v["draw"] else 0
                    reads.append(v["downloaded"] - v["manifest"] + sum(sizes[:deepest + 1]) + extra)
                    rts.append(2 + deepest)
                    parts_read.append(deepest)
                res[name] = statistics.mean(reads) / drawn
                res[name + "_rt"] = max(rts)
                res[name + "_bands_read"] = parts_read  # per view: the last band read (0: the root alone)
                if name == "shares_rule":
                    res["rule_unused_bands"] = unused
                    res["rule_other_cut"] = other_cut  # views whose pages run drew another cut (0 expected)
        rows.append(res)
    return {"scene": os.path.basename(scene_dir.rstrip("/")), "whole_manifest": len(raw), "level": a,
            "pages15_root": root15, "pages15_pages": sum(page_of_head.values()),
            "shared_parts": layouts["shared"][0], "band_parts": layouts["bands"][0],
            "share_edges": edges, "share_parts": layouts["shares"][0] if edges else None, "rows": rows}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene_dir")
    ap.add_argument("before_json", help="bench/small_budget_bytes.py's JSON of the unpaged scene")
    ap.add_argument("--share", type=float, default=0.02)
    ap.add_argument("--band", type=int, default=2)
    ap.add_argument("--fill-min-kb", type=int, default=64)
    ap.add_argument("--band-shares", default=None, help="e.g. 0.02,0.10: the root, then band pages, by splat share")
    ap.add_argument("--pages-run", action="append", default=[],
                    help="small_budget_bytes.py's JSON of a format 1.5 copy paged below a band's last level "
                         "(`bench_pages.py --repage SCENE OUT --default-levels EDGE+1`); once a band")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    shares = [float(x) for x in args.band_shares.split(",")] if args.band_shares else None
    res = estimate(args.scene_dir, args.before_json, args.share, args.band, args.fill_min_kb << 10, shares,
                   args.pages_run)
    print(f"{res['scene']}: whole manifest {res['whole_manifest']:,} B; root to level {res['level']}: format 1.5 "
          f"root {res['pages15_root']:,} B + pages {res['pages15_pages']:,} B; shared {res['shared_parts']}; "
          f"bands {res['band_parts']}")
    for r in res["rows"]:
        print(f"  {r['fraction']:.2f}: today {r['today']:.3f} (rt {r['today_rt']}), pages15 (least) "
              f"{r['pages15']:.3f}, shared {r['shared']:.3f} (rt {r['shared_rt']}), bands {r['bands']:.3f} "
              f"(rt {r['bands_rt']})" + (f", shares {r['shares']:.3f} (rt {r['shares_rt']})" if "shares" in r
                                          else "") + (f", rule {r['shares_rule']:.3f}" if "shares_rule" in r else ""))
    if res["share_edges"]:
        print(f"  share edges {res['share_edges']}, parts {res['share_parts']}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
