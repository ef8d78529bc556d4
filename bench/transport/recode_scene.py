"""Bytes of an encoded scene directory under the transport coding (splatstream/transport.py), without writing it.

    python bench/transport/recode_scene.py SCENE_DIR [...]            (prints one JSON line per scene)
    python bench/transport/recode_scene.py --eval EVAL.json [--markdown OUT.md]
        adds `transport_disk_bytes_per_splat` to every row of a `splatstream eval --encoded DIR --json` report
        whose encoded directory is kept, and prints the table (PSNR is unchanged: the GPU bytes are identical).

Counted as the proposed integration stores it (format_spec/transport_draft.md): each payload stays one zstd frame
(level 3) over its sections, 16-byte aligned, each texels section through transport.filter_section (`fields1` or
today's shuffle), ranges shuffled as today; plus the manifest as written today (the filter name is already in it).
"""
from __future__ import annotations

import argparse
import json
import os
from collections import defaultdict

import numpy as np
import zstandard

from splatstream.manifest import MANIFEST_NAME, load_manifest
from splatstream.texformats import shuffle_bytes, unshuffle_bytes
from splatstream.transport import filter_section

ALIGN = 16


def recode(scene_dir: str, filters: str = "transport") -> dict:
    """filters: "transport" (filter_section) or "today" (today's shuffle filters; only the block flushes differ)."""
    m = load_manifest(scene_dir)
    entries = [(("sh" if g.startswith("sh") else "base"), e) for t in m["tiles"] for g, e in t["groups"].items()]
    entries += [("sh_codebook", e) for e in (m.get("sh_codebook") or {}).get("groups", {}).values()]
    seen: set[str] = set()
    total = 0
    sections = 0
    per_attr: dict[str, int] = defaultdict(int)
    for group, e in entries:
        if e["file"] in seen:
            continue
        seen.add(e["file"])
        raw = np.frombuffer(zstandard.ZstdDecompressor().decompress(open(os.path.join(scene_dir, e["file"]), "rb")
                                                                    .read()), np.uint8)
        stored = []
        for s in e["sections"]:
            sections += 1
            element = 1 if s["filter"] == "none" else int(s["filter"][7:])
            buf = raw[s["offset"]:s["offset"] + s["size"]]
            if s["kind"] == "texels":
                unit = buf.size // s["layers"]
                gpu = np.concatenate([unshuffle_bytes(buf[i * unit:(i + 1) * unit], element)
                                      for i in range(s["layers"])])
                if filters == "transport":
                    data, _ = filter_section(gpu, s["format"], s["width"], s["height"], s["layers"])
                else:
                    data = buf.tobytes()
            else:
                data = shuffle_bytes(unshuffle_bytes(buf, element), element).tobytes()
            attr = "sh_codebook" if group == "sh_codebook" else \
                ("sh" if s["name"].startswith("sh") else s["name"].split(".")[0])
            stored.append((attr, data))
        content = b"".join(d + bytes(-len(d) % ALIGN) for _, d in stored)
        # one frame, one zstd block run per section (a block flush at every section end): each section gets its
        # own literal tables, which measured 4-5 % smaller than letting sections share blocks on fruit_drops
        cobj = zstandard.ZstdCompressor(level=3, write_content_size=True).compressobj(size=len(content))
        payload = 0
        for _, d in stored:
            payload += len(cobj.compress(d + bytes(-len(d) % ALIGN)))
            payload += len(cobj.flush(zstandard.COMPRESSOBJ_FLUSH_BLOCK))
        payload += len(cobj.flush())
        total += payload
        for attr, data in stored:  # shared out by stored size, as the manifest's attribute table does
            per_attr[attr] += payload * len(data) / max(1, len(content))
    manifest = os.path.getsize(os.path.join(scene_dir, MANIFEST_NAME))
    n = m["splats"]
    return {"scene_dir": scene_dir, "splats": n, "today_bytes": m["bytes_on_disk"],
            "transport_bytes": total + manifest, "manifest_bytes": manifest,
            "today_bytes_per_splat": m["bytes_on_disk"] / n, "transport_bytes_per_splat": (total + manifest) / n,
            "transport_attribute_bytes_per_splat": {a: v / n for a, v in per_attr.items()}}


def fmt_psnr(v) -> str:
    return "inf" if v is None else f"{v:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("dirs", nargs="*")
    ap.add_argument("--eval")
    ap.add_argument("--markdown")
    ap.add_argument("--filters", choices=["transport", "today"], default="transport")
    args = ap.parse_args()
    for d in args.dirs:
        print(json.dumps(recode(d, args.filters)))
    if not args.eval:
        return
    report = json.load(open(args.eval))
    lines = [f"{os.path.basename(report['input']['path'])}: {report['input']['splats']:,} splats, "
             f"{len(report['cameras'])} views at {report['size'][0]}x{report['size'][1]}, {report['renderer']}", "",
             "| row | pos | rot | scl | col | sh | GPU B/splat | disk today | disk transport | PSNR (worst) | SSIM |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in report["rows"]:
        if row["kind"] == "attribution":
            continue
        if row.get("encoded_dir"):
            r = recode(row["encoded_dir"])
            row["transport_disk_bytes_per_splat"] = r["transport_bytes_per_splat"]
            row["transport_attribute_bytes_per_splat"] = r["transport_attribute_bytes_per_splat"]
        f = row["formats"]
        sh = f.get("sh", "-") + (f" VQ{row['sh_codebook_entries']}" if row.get("sh_codebook_entries") else "")
        transport = row.get("transport_disk_bytes_per_splat")
        lines.append(f"| {row['label']} | {f.get('position', '')} | {f.get('rotation', '')} | {f.get('scale', '')} | "
                     f"{f.get('color', '')} | {sh if f else ''} | "
                     f"{'' if row['gpu_bytes_per_splat'] is None else format(row['gpu_bytes_per_splat'], '.2f')} | "
                     f"{row['disk_bytes_per_splat']:.2f} | "
                     f"{format(transport, '.2f') if transport is not None else row['disk_bytes_per_splat']:>} | "
                     f"{fmt_psnr(row['psnr_mean'])} ({fmt_psnr(row['psnr_worst'])}) | {row['ssim_mean']:.4f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    json.dump(report, open(args.eval, "w"), indent=1)
    if args.markdown:
        open(args.markdown, "w").write(text)


if __name__ == "__main__":
    main()
