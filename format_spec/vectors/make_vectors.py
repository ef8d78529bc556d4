"""Regenerate the test vectors: python format_spec/vectors/make_vectors.py (from the repository root)."""
import json
import pathlib
import shutil

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.format.layout import morton_order
from splatstream.ply import read_gaussians_ply
from splatstream.scene_decode import decode_scene

HERE = pathlib.Path(__file__).resolve().parent
SOURCE = HERE.parents[1].parent / "shared" / "data" / "real" / "fruit_drops_sh3.ply"
PRESETS = ["high", "medium", "low", "very-low"]
SPLATS = 260
# A paged scene (format.md 6.1, version 1.5): an LOD tree of 600 splats (SH degree 1) in leaves of at most 64, one
# level in the root manifest and in each page, so it has a page below every interior tile.
PAGED_SPLATS = 600
PAGED = {"max_leaf_splats": 64, "page_tiles": 1, "page_levels": 1, "sh_degree": 1}


def expected_values(g) -> dict:
    return {
        "splats": len(g),
        "positions": g.positions.tolist(),
        "rotations": g.rotations.tolist(),
        "log_scales": g.log_scales.tolist(),
        "opacities": g.opacities.tolist(),
        "sh_dc": g.sh_dc.tolist(),
        "sh_rest": g.sh_rest.tolist(),
    }


def paged_vector(source) -> None:
    g = source.subset(morton_order(source.positions)[:PAGED_SPLATS])
    out = HERE / "paged"
    shutil.rmtree(out, ignore_errors=True)
    encode_gaussians(g, out, EncodeOptions(preset="medium", name="vector-paged", zstd_level=3, **PAGED))
    (out / "expected.json").write_text(json.dumps(expected_values(decode_scene(out))) + "\n")
    print("wrote", out)


def main() -> None:
    source = read_gaussians_ply(SOURCE)
    paged_vector(source)
    g = source.subset(morton_order(source.positions)[:SPLATS])
    for preset in PRESETS:
        out = HERE / preset
        shutil.rmtree(out, ignore_errors=True)
        encode_gaussians(g, out, EncodeOptions(preset=preset, name=f"vector-{preset}", zstd_level=3))
        (out / "expected.json").write_text(json.dumps(expected_values(decode_scene(out))) + "\n")
        print("wrote", out)


if __name__ == "__main__":
    main()
