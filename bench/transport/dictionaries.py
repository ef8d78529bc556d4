"""Does a zstd dictionary per attribute help the transport streams of LOD tiles?

Encodes a scene with LOD (tiles of at most --leaf splats), codes every texels section with transport.encode_section,
trains one zstd dictionary per section name on the raw (pre-zstd) streams of the even tiles and compresses the odd
tiles' streams with and without it. Prints bytes per splat of the odd tiles.

    python bench/transport/dictionaries.py SCENE.ply [--preset medium] [--leaf 65536] [--dict-size 16384]
"""
from __future__ import annotations

import argparse
import os
import tempfile
from collections import defaultdict

import zstandard
from collect import dump_sections  # noqa: I001 (bench script next to this one)

from splatstream.encoder import EncodeOptions, encode_gaussians
from splatstream.io import read_gaussians
from splatstream.transport import encode_section


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("scene")
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--leaf", type=int, default=65536)
    ap.add_argument("--dict-size", type=int, default=16384)
    args = ap.parse_args()
    g = read_gaussians(args.scene)
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "scene")
        encode_gaussians(g, out, EncodeOptions(preset=args.preset, max_leaf_splats=args.leaf))
        arrays, meta = dump_sections(out)
    streams: dict[str, list[tuple[int, bytes, int]]] = defaultdict(list)
    for s in meta:
        if s["kind"] != "texels" or not s["payload"].startswith("tile"):
            continue
        coded, d = encode_section(arrays[s["key"]], s["format"], s["width"], s["height"], s["layers"])
        if d["coding"] != "fields-zstd":
            continue
        tile = int(s["payload"].split(".")[0][4:])
        streams[s["name"]].append((tile, zstandard.ZstdDecompressor().decompress(coded), len(coded)))
    for name, items in streams.items():
        train = [raw for tile, raw, _ in items if tile % 2 == 0]
        test = [(raw, size) for tile, raw, size in items if tile % 2 == 1]
        if len(train) < 2 or not test:
            continue
        samples = []
        for raw in train:  # zstd trains on many small samples: cut each stream into 16 KB pieces
            samples += [raw[i:i + 16384] for i in range(0, len(raw), 16384)]
        try:
            dictionary = zstandard.train_dictionary(args.dict_size, samples)
        except zstandard.ZstdError as exc:
            print(f"{name:10s}: no dictionary ({exc})")
            continue
        with_dict = sum(len(zstandard.ZstdCompressor(level=3, dict_data=dictionary).compress(raw)) for raw, _ in test)
        plain = sum(size for _, size in test)
        print(f"{name:10s} {len(test)} tiles: {plain} bytes without, {with_dict} with a {args.dict_size}-byte "
              f"dictionary ({(with_dict - plain) / plain * 100:+.1f} %)")


if __name__ == "__main__":
    main()
