"""Regenerate the test vectors, from the repository root:

    PYTHONPATH=. python format_spec/vectors/make_vectors.py [NAME ...]

NAME: high, medium, medium-low, low, very-low, paged, table, levels, refined, compact, digest16, relbox16 (default:
all). tests/test_spec_vectors.py encodes the presets' scenes again with `encode_vector` (`levels`, `refined` with
`encode_record_vector`, `compact`, `digest16` and `relbox16` with `encode_compact_vector`) and fails when what the
encoder writes today no longer matches the vector."""
import json
import pathlib
import shutil
import sys

from splatstream.encode import EncodeOptions, encode_gaussians
from splatstream.format.layout import morton_order
from splatstream.format.manifest import LevelRefinement, LodRefinement
from splatstream.lod_refine import REFINE_METHOD, UNREFINED, VARIANT_FIELDS, level_cuts, with_values
from splatstream.ply import read_gaussians_ply
from splatstream.scene_decode import decode_scene

HERE = pathlib.Path(__file__).resolve().parent
# The bundled copy of the shared data's scene (the same bytes: tests/data/real/README.md), so a fresh clone can
# regenerate the vectors.
SOURCE = HERE.parents[1] / "tests" / "data" / "real" / "fruit_drops_sh3.ply"
PRESETS = ["high", "medium", "medium-low", "low", "very-low"]
SPLATS = 260
# A paged scene (format.md 6.1, version 1.5): an LOD tree of 600 splats (SH degree 1) in leaves of at most 64, one
# level in the root manifest and in each page, so it has a page below every interior tile.
PAGED_SPLATS = 600
# The grid merge named, as the vectors were written with it (the in-memory default became auto, issue 31): readers
# cannot tell merges apart (lod.md 6), so the vectors' bytes stay as they were.
PAGED = {"max_leaf_splats": 64, "page_tiles": 1, "page_levels": 1, "sh_degree": 1, "lod_merge": "grid"}

# The LOD records of format 1.10 and 1.11 (format.md 6): `paged`'s 600 splats and tree in one manifest (not paged), as
# today's encoder writes them: `levels` records the viewing scale per level (lod.viewing_scale_levels_px, 1.10),
# `refined` is the same encode with a refinement record (lod.refinement, 1.11) from REFINER below.
# Both keep the 1.8 tile table (compact_table=False), so they stay vectors of those two versions.
TREE = {"max_leaf_splats": 64, "sh_degree": 1, "lod_merge": "grid", "compact_table": False}
# The compact tile table of format 1.12 (format.md 6.2): the same tree as `levels`, paged two levels to a file so that
# the root manifest and its pages all hold `tile_table_zstd` (f32 bounds rounded outward, zstd-compressed).
# Written with the whole SHA-256 (short_digests=False), so it stays a 1.12 vector.
COMPACT = {"max_leaf_splats": 64, "sh_degree": 1, "lod_merge": "grid", "page_tiles": 1, "page_levels": 2}
# `digest16`: the same encode as format 1.15 writes it (format.md 6.2, "Short digests"): the compact tables name
# payloads and pages by the first 16 bytes of their SHA-256 (`digest16`, files `data/<32 hex>.bin`); written with
# f32 boxes (relative_boxes=False), so it stays a 1.15 vector.
# `relbox16`: the same encode as format 1.16 writes it (format.md 6.2, "Boxes relative to the parent's"): each box
# as u8 steps of its parent's (`box8`), the root's and the pages' top tiles' as f32 (`anchor_box`), the radii as u8
# steps of the half diagonal (`radius8`, `radius_far`).
COMPACT_VECTORS = {"compact": {"short_digests": False}, "digest16": {"relative_boxes": False}, "relbox16": {}}
# `refined`'s record (informative metadata: fixed values, not a GPU's): every merged level tried B and C; the first
# merged level kept B, the levels above it stayed as built.
REFINED_PSNR = ((UNREFINED, 30.0), ("B", 31.5), ("C", 31.25))
REFINED_OPACITY_SCALE = 0.5  # what B "found" on the first merged level: its opacity logits halved (a B field)


def refiner(g, tiles, up, progress):
    """A deterministic stand-in for refine_gpu (lod_refine.LodRefiner; numpy only, so the vector is the same on any
    machine): the first merged level's opacity logits halved and kept as B, the levels above kept as built."""
    cuts = level_cuts(tiles)
    first = cuts[-1].level  # the deepest merged level: its tiles' children are leaves
    refined = {t.id: with_values(t.gaussians, {"opacity_logits": t.gaussians.opacity_logits * REFINED_OPACITY_SCALE})
               for t in tiles if t.children and t.level == first}
    levels = tuple(LevelRefinement(c.level, "B" if c.level == first else UNREFINED, REFINED_PSNR) for c in cuts)
    return refined, LodRefinement(REFINE_METHOD, tuple((v, VARIANT_FIELDS[v]) for v in ("B", "C")), 384, 300, 96, 0,
                                  32, 1, levels)


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


def encode_vector(preset: str, out: pathlib.Path, source=None) -> None:
    """A preset's vector scene (without expected.json): the first SPLATS Morton-ordered splats of SOURCE, zstd 3."""
    source = read_gaussians_ply(SOURCE) if source is None else source
    g = source.subset(morton_order(source.positions)[:SPLATS])
    encode_gaussians(g, out, EncodeOptions(preset=preset, name=f"vector-{preset}", zstd_level=3))


def paged_vector(source, name: str) -> None:
    """The paged vector `name` (`paged`, or `table`: the same input and options, written by today's encoder, its root
    manifest and pages holding their tiles as tile tables, format.md 6.2, version 1.8)."""
    g = source.subset(morton_order(source.positions)[:PAGED_SPLATS])
    out = HERE / name
    shutil.rmtree(out, ignore_errors=True)
    encode_gaussians(g, out, EncodeOptions(preset="medium", name=f"vector-{name}", zstd_level=3, **PAGED))
    (out / "expected.json").write_text(json.dumps(expected_values(decode_scene(out))) + "\n")
    print("wrote", out)


def encode_record_vector(name: str, out: pathlib.Path, source=None) -> None:
    """The LOD record vector `name` (`levels` or `refined`, without expected.json)."""
    source = read_gaussians_ply(SOURCE) if source is None else source
    g = source.subset(morton_order(source.positions)[:PAGED_SPLATS])
    extra = {"lod_refiner": refiner} if name == "refined" else {}
    encode_gaussians(g, out, EncodeOptions(preset="medium", name=f"vector-{name}", zstd_level=3, **TREE, **extra))


RECORDS = ["levels", "refined"]


def encode_compact_vector(out: pathlib.Path, source=None, name: str = "compact") -> None:
    """A compact-table vector (`compact`: format 1.12; `digest16`: 1.15; `relbox16`: 1.16), without expected.json."""
    source = read_gaussians_ply(SOURCE) if source is None else source
    g = source.subset(morton_order(source.positions)[:PAGED_SPLATS])
    encode_gaussians(g, out, EncodeOptions(preset="medium", name=f"vector-{name}", zstd_level=3, **COMPACT,
                                           **COMPACT_VECTORS[name]))


def main(names: list[str]) -> None:
    unknown = set(names) - {*PRESETS, "paged", "table", *RECORDS, *COMPACT_VECTORS}
    if unknown:
        raise SystemExit(f"unknown vector {sorted(unknown)[0]!r} (choose from {', '.join(PRESETS)}, paged, table, "
                         f"{', '.join(RECORDS)}, {', '.join(COMPACT_VECTORS)})")
    source = read_gaussians_ply(SOURCE)
    for name in COMPACT_VECTORS:
        if not names or name in names:
            out = HERE / name
            shutil.rmtree(out, ignore_errors=True)
            encode_compact_vector(out, source, name)
            (out / "expected.json").write_text(json.dumps(expected_values(decode_scene(out))) + "\n")
            print("wrote", out)
    for name in RECORDS:
        if not names or name in names:
            out = HERE / name
            shutil.rmtree(out, ignore_errors=True)
            encode_record_vector(name, out, source)
            (out / "expected.json").write_text(json.dumps(expected_values(decode_scene(out))) + "\n")
            print("wrote", out)
    for name in ("paged", "table"):
        if not names or name in names:
            paged_vector(source, name)
    for preset in PRESETS:
        if names and preset not in names:
            continue
        out = HERE / preset
        shutil.rmtree(out, ignore_errors=True)
        encode_vector(preset, out, source)
        (out / "expected.json").write_text(json.dumps(expected_values(decode_scene(out))) + "\n")
        print("wrote", out)


if __name__ == "__main__":
    main(sys.argv[1:])
