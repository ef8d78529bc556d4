"""Issue 32 (axis32): `norm11` positions with each chunk's shortest axis in the 10-bit field, as a probe (no format).

    PYTHONPATH=. python bench/norm11s_probe.py SCENE --renderer ref --json OUT.json [eval options] -- CONFIG ...

CONFIG as bench/eval_probe.py's; `position=norm11s` names the probe's texel format: norm11's texels (format.md 4.2)
with the fields permuted per 256-splat chunk so that field 1 (10 bits) holds the chunk's axis of smallest extent
(its stored max - min as float32, ties to y, then z, then x; a chunk shortest in y keeps norm11's layout) and fields
0 and 2 (11 bits) the other two, lower axis first. No byte is added: a reader knows the order from the chunk's range.
The format exists only in this process (registered here, numpy encoder and decoder patched), so only the numpy
reference renderer draws it correctly: pass `--renderer ref` (the GL client would read norm11's field order).
AXIS32_ONLY=x (z, x,z) permutes only the chunks shortest in those axes (a diagnosis).
`--position-error SCENE ...` prints, instead, the RMS position error per axis of norm11 and norm11s on each scene
(one tile in Morton order, as eval encodes it) and the count of chunks shortest in y, z and x.
"""
from __future__ import annotations

import os
import sys

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from splatstream.format import codec, decode, presets, texformats, transport  # noqa: E402
from splatstream.format.manifest import validate  # noqa: E402

TIE_ORDER = (1, 2, 0)  # field 1's axis among equal extents: y, then z, then x
# AXIS32_ONLY=x (or z, or x,z): permute only chunks whose shortest axis is one of these (a diagnosis, both sides).
ONLY = (None if not os.environ.get("AXIS32_ONLY") else
        tuple("xyz".index(a) for a in os.environ["AXIS32_ONLY"].split(",")))
FIELD_AXES = np.array([[1, 0, 2], [0, 1, 2], [0, 2, 1]], np.intp)  # the axis per field, by the shortest axis x, y, z


def shortest_axis_order(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(chunks, 3) stored min and max -> (chunks, 3) the axis each field holds."""
    extent = np.asarray(hi, np.float32).reshape(-1, 3) - np.asarray(lo, np.float32).reshape(-1, 3)
    shortest = np.asarray(TIE_ORDER, np.intp)[np.argmin(extent[:, TIE_ORDER], axis=1)]
    if ONLY is not None:  # diagnosis: permute only the chunks shortest in these axes, the rest as norm11
        shortest = np.where(np.isin(shortest, ONLY), shortest, 1)
    return FIELD_AXES[shortest]


def install() -> None:
    """Register norm11s in this process: the format tables, the numpy encoder's texels and the numpy decoder."""
    if "norm11s" in texformats.FORMATS:
        return
    texformats.FORMATS["norm11s"] = texformats.TexelFormat("norm11s", 32, 3, (2047, 1023, 2047), "R32UI", shuffle=4,
                                                           same_texels_as="norm11")
    texformats.TEXEL_DTYPES["norm11s"] = texformats.TEXEL_DTYPES["norm11"]
    for module in (texformats, presets, validate):
        module.VALUE_FORMATS = (*module.VALUE_FORMATS, "norm11s")
    transport.FIELD_LAYOUTS["norm11s"] = transport.FIELD_LAYOUTS["norm11"]  # tables built from FORMATS at import
    transport.FIELDS1_HEADER_BYTES["norm11s"] = transport.FIELDS1_HEADER_BYTES["norm11"]
    last_range: dict[str, np.ndarray] = {}
    chunk_ranges, texture_blob, decode_plane = codec.chunk_ranges, codec._texture_blob, codec.decode_plane

    def recorded_ranges(values, range_dtype, limits=None):
        lo, hi = chunk_ranges(values, range_dtype, limits)
        last_range["lo"], last_range["hi"] = lo, hi
        return lo, hi

    def permuted_blob(t, fmt_name, chunks, width, height):
        if fmt_name == "norm11s":  # encode_plane's last chunk_ranges call is this layer's (no tile step here)
            axes = shortest_axis_order(last_range["lo"], last_range["hi"])
            t = np.take_along_axis(t.reshape(chunks, -1, 3), axes[:, None, :], axis=2).reshape(-1, 3)
            fmt_name = "norm11"
        return texture_blob(t, fmt_name, chunks, width, height)

    def unpermuted_plane(plane, n):
        if plane.format != "norm11s":
            return decode_plane(plane, n)
        src = codec.chunk_texel_index(max(1, -(-n // codec.CHUNK_SIZE)), plane.width)[:n]
        texels = np.frombuffer(plane.layers[0], texformats.TEXEL_DTYPES["norm11"])[src]
        fields = texformats.unpack_texels("norm11", texels)[:, :3]
        lo = plane.ranges[:, 0, 0].astype(np.float32)
        hi = plane.ranges[:, 1, 0].astype(np.float32)
        chunk = np.arange(n) // codec.CHUNK_SIZE
        t = np.empty_like(fields)
        np.put_along_axis(t, shortest_axis_order(lo, hi)[chunk], fields, axis=1)
        return (lo[chunk] + t * (hi - lo)[chunk]).astype(np.float32)[:, None, :]

    codec.chunk_ranges, codec._texture_blob = recorded_ranges, permuted_blob
    codec.decode_plane = decode.decode_plane = unpermuted_plane


def position_error(paths: list[str]) -> None:
    from splatstream.format.layout import morton_order
    from splatstream.format.planes import PlaneSpec
    from splatstream.io import read_gaussians
    spec = PlaneSpec("position", "position", 3, 1, "<f4")
    for path in paths:
        p = read_gaussians(path).positions
        p = p[morton_order(p)][:, None, :].astype(np.float32)
        row = [os.path.basename(path)]
        for fmt in ("norm11", "norm11s"):
            plane = codec.encode_plane(p, spec, fmt)
            e = (codec.decode_plane(plane, len(p)) - p)[:, 0].astype(np.float64)
            row.append(f"{fmt} rms x y z " + " ".join(f"{v:.3e}" for v in np.sqrt((e ** 2).mean(0)))
                       + f" all {np.sqrt((e ** 2).sum(1).mean()):.3e}")
        r = plane.ranges[:, :, 0]
        shortest = shortest_axis_order(r[:, 0], r[:, 1])[:, 1]
        row.append("chunks shortest in x y z " + " ".join(str(int((shortest == a).sum())) for a in range(3)))
        print(" | ".join(row), flush=True)


if __name__ == "__main__":
    install()
    if sys.argv[1:2] == ["--position-error"]:
        position_error(sys.argv[2:])
        sys.exit(0)
    from eval_probe import run
    sys.exit(run(sys.argv[1:]))
