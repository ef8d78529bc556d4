"""Where an encoded scene's bytes go, for the SOG statues with palette planes and the LOD tree (issue 32): per
section of the full-detail leaves (B/splat: each section's stored bytes compressed alone at the preset's zstd level,
`leaf_sections_alone_b_per_splat`, the sum within a few % of the payloads, which share one zstd frame; and each
payload's file bytes shared out by its sections' raw sizes, as the manifest's `attributes` are, which says little
here: a 16-bit position texel is twice a palette index's raw bytes), the manifest, the palettes (scene palettes in
the manifest; palette sections in payloads), and the whole tree.

    python bench/sog_palette_lod.py INPUT --json OUT.json [--scene LABEL=DIR ...] -- CONFIG [CONFIG ...]

Each CONFIG (bench/eval_probe.py's "LABEL:PRESET[,ATTR=FORMAT][,pos_g=G][,transport=keyed]") is encoded with the
encoder's defaults (the LOD tree) and measured; `--scene` measures a scene encoded already (an eval's
`--encoded` directory). A CONFIG label holding `tilepal` is encoded with per-tile palettes (format 1.6: the
encoder's scene palettes switched off), to price what the scene palettes save; one holding `onetile` without the
LOD tree (one tile, as `splatstream eval` without --lod encodes).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
from collections import defaultdict

import zstandard

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from sh_coding_probe import parse_config, register  # noqa: E402

from splatstream.encode import EncodeOptions, encode_gaussians  # noqa: E402
from splatstream.encode import plan as encode_plan  # noqa: E402
from splatstream.format.names import MANIFEST_NAME  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import open_store, read_manifest  # noqa: E402


def measure(scene_dir: str, splats: int, level: int = 16) -> dict:
    """Bytes of an encoded scene by section (leaves), palettes, manifest and tree, per splat of the input."""
    store = open_store(scene_dir)
    m = read_manifest(store)
    alone = defaultdict(int)
    cctx = zstandard.ZstdCompressor(level=level)
    for t in m.leaves:
        for entry in t.groups.values():
            raw = zstandard.ZstdDecompressor().decompress(store.read_payload(entry))
            for s in entry.sections:
                alone[s.name] += len(cctx.compress(raw[s.offset:s.offset + s.size]))
    manifest_bytes = os.path.getsize(os.path.join(scene_dir, MANIFEST_NAME))
    leaf = defaultdict(float)
    palette_sections = {"leaves": 0.0, "tree": 0.0}
    own_palette_tiles = 0
    for t in m.tiles:
        for entry in t.groups.values():
            has = False
            for s in entry.sections:
                share = entry.bytes * s.size / max(1, entry.raw_bytes)
                if s.name.endswith(".palette"):
                    palette_sections["tree"] += share
                    has = True
                    if t.is_leaf:
                        palette_sections["leaves"] += share
                if t.is_leaf:
                    leaf[s.name] += share
            own_palette_tiles += has
    codebook = sum(p.bytes for p in m.sh_codebook.groups.values()) if m.sh_codebook else 0
    leaf_payloads = m.leaf_bytes_on_disk
    scene_palette_bytes = sum(len(v) for v in (m.palettes or {}).values())
    return {
        "version": list(m.version), "tiles": len(m.tiles), "leaves": len(m.leaves),
        "leaf_payload_bytes": leaf_payloads, "manifest_bytes": manifest_bytes,
        "full_detail_bytes": leaf_payloads + manifest_bytes, "tree_bytes": m.bytes_on_disk,
        "full_detail_b_per_splat": (leaf_payloads + manifest_bytes) / splats,
        "leaf_payload_b_per_splat": leaf_payloads / splats, "tree_b_per_splat": m.bytes_on_disk / splats,
        "scene_palette_bytes": scene_palette_bytes, "palette_section_bytes": palette_sections,
        "tiles_with_own_palettes": own_palette_tiles, "codebook_bytes": codebook,
        "leaf_sections_b_per_splat": {k: v / splats for k, v in sorted(leaf.items())},
        "leaf_sections_alone_b_per_splat": {k: v / splats for k, v in sorted(alone.items())},
        "zstd_level_alone": level,
    }


def main() -> None:
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    ap = argparse.ArgumentParser()
    ap.add_argument("input")
    ap.add_argument("--json", required=True)
    ap.add_argument("--scene", action="append", default=[], help="LABEL=DIR: an encoded scene to measure")
    args = ap.parse_args(argv[:cut])
    g = read_gaussians(args.input)
    out = {"input": os.path.basename(args.input), "splats": len(g), "rows": {}}
    for item in args.scene:
        label, path = item.split("=", 1)
        out["rows"][label] = measure(path, len(g))
    fit = encode_plan.scene_palettes
    for config in argv[cut + 1:]:
        label, preset, extra = parse_config(config)
        name = register(label, preset, extra)
        encode_plan.scene_palettes = (lambda parts: None) if "tilepal" in label else fit
        try:
            with tempfile.TemporaryDirectory() as tmp:
                scene = os.path.join(tmp, "scene")
                encode_gaussians(g, scene, EncodeOptions(preset=name, lod="onetile" not in label),
                                 source_name=args.input)
                out["rows"][label] = measure(scene, len(g))
        finally:
            encode_plan.scene_palettes = fit
    for label, r in out["rows"].items():
        print(f"{label:>16}: full detail {r['full_detail_b_per_splat']:6.3f} B/splat (leaves "
              f"{r['leaf_payload_b_per_splat']:6.3f}, manifest {r['manifest_bytes']} B), tree "
              f"{r['tree_b_per_splat']:6.3f}, {r['tiles']} tiles, own palettes in {r['tiles_with_own_palettes']}",
              flush=True)
    with open(args.json, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
