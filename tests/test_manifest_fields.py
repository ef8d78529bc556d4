"""Every field of a real manifest, damaged: the one validator names it as format.md 6 "Validation" says, and the
lazily checked payload entries (the streaming client's parse) say exactly what the eager parse says.

A seeded loop (no hypothesis in the venv): for every key and list item of the `low` (SH codebook) and `medium`
test vectors' manifests, a few damages drawn from DAMAGES (deleted, wrong type, out of range, unknown key
beside it); the manifest is resealed (checksum, so the damage is what the validator meets) and parsed eagerly
and lazily, every payload entry read.
"""
import copy
import pathlib
import random
import re

import pytest
from conftest import read_manifest_dict

from splatstream.errors import FormatError
from splatstream.format.manifest import pack_manifest_dict, parse_manifest

VECTORS = pathlib.Path(__file__).resolve().parents[1] / "format_spec" / "vectors"
SEED = 33
DELETE = object()
# Replacement values: each is wrong for most fields (and harmless for a few, which the loop lets pass).
DAMAGES = [DELETE, None, "x", -1, 1 << 40, 2.5, float("nan"), True, [], {}, [1, 2], {"k": 1}]
# Fields whose damage shows in another field by a cross-check of format.md 6 (the tree, the totals, a group's
# sections against the scene's formats, degree and codebook, a tile's texture against its sections).
CROSS = {"root", "splats", "tiles", "gpu_bytes", "leaf_bytes_on_disk", "bytes_on_disk"}
MESSAGE = re.compile(r"^m: (?P<field>[A-Za-z_][\w.\[\]]*): (?P<problem>.+)$")
EXPECTED_STARTS = ("expected", "missing", "unexpected", "unknown")
EXPECTED_PARTS = (", but ", " expected ", " must ", " exceeds ", "overlap", "not a multiple", "outside",
                  "zero-length", "coincide", "appears twice", "no tile", "parent", "cannot hold", "is a version",
                  "has 3 components")
TOP = re.compile(r"^m: (?P<problem>unknown key.+)$")  # the manifest map itself has no field name


def paths(value, prefix=()):
    """Every key and list item below `value`, as paths of keys and indices."""
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for k, v in items:
        yield prefix + (k,)
        yield from paths(v, prefix + (k,))


def dotted(path) -> str:
    out = ""
    for k in path:
        out += f"[{k}]" if isinstance(k, int) else (f".{k}" if out else k)
    return out


def _get(d, path):
    for k in path:
        d = d[k]
    return d


def damaged(d: dict, path, value) -> dict:
    d = copy.deepcopy(d)
    parent = d
    for k in path[:-1]:
        parent = parent[k]
    if value is DELETE:
        if isinstance(parent, list):
            del parent[path[-1]]
        else:
            del parent[path[-1]]
    else:
        parent[path[-1]] = value
    return d


def cases(vector: str, per_field: int = 3):
    d = read_manifest_dict(VECTORS / vector)
    rng = random.Random(f"{SEED}:{vector}")
    for path in paths(d):
        if path[-1] in ("checksum", "format", "version") and len(path) == 1:
            continue  # the checksum is resealed; format and version have their own tests (test_manifest.py)
        for value in rng.sample(DAMAGES, per_field):
            yield path, value
        value = _get(d, path)
        if type(value) is int:  # off by a little: right type, wrong value (sizes, offsets, counts, ids)
            yield path, value + rng.choice((-16, -1, 1, 16))
        parent = path[:-1]
        if not isinstance(path[-1], int) and rng.random() < 0.2:  # an unknown key beside this one
            yield parent + ("unknown_key",), 0


def outcome(data: bytes, lazy: bool) -> str | None:
    """The FormatError's message (None: accepted), reading every payload entry of a lazily parsed manifest."""
    try:
        m = parse_manifest(data, "m", lazy_payloads=lazy)
        for t in m.tiles:
            for name in t.groups:
                t.groups[name]
    except FormatError as exc:
        return str(exc)
    return None


def related(field: str, path: str) -> bool:
    """The reported field is the damaged one, one of its enclosing maps or lists, one inside it (a damaged map
    names its bad member), another field of the same tile, a cross-check's field, or a texel format the damaged
    version does not have."""
    if not field:  # the manifest map itself
        return "." not in path and "[" not in path
    top = re.split(r"[.\[]", field)[0]
    same_tile = re.match(r"tiles\[\d+\]", field) and re.match(r"tiles\[\d+\]", path) and \
        re.match(r"tiles\[\d+\]", field)[0] == re.match(r"tiles\[\d+\]", path)[0]
    return (field == path or path.startswith(field + ".") or path.startswith(field + "[")
            or field.startswith(path + ".") or field.startswith(path + "[") or bool(same_tile) or top in CROSS
            or field.endswith(".children") or (path.startswith("tiles") and top == "sh_codebook")
            or (top == "tiles" or path.split(".")[0] in ("formats", "sh_degree", "sh_codebook", "chunk_size"))
            # a lowered version is named on the format it no longer allows (cube565 below 1.13, format.md 4.2)
            or (path.startswith("version") and top == "formats"))


@pytest.mark.parametrize("vector", ["low", "medium"])
def test_every_damaged_field_is_named_the_same_eagerly_and_lazily(vector):
    base = read_manifest_dict(VECTORS / vector)
    checked = refused = 0
    for path, value in cases(vector):
        d = damaged(base, path, value)
        try:
            data = pack_manifest_dict(d)
        except (TypeError, ValueError):
            continue
        eager = outcome(data, lazy=False)
        lazy = outcome(data, lazy=True)
        where = f"{dotted(path)} = {'<deleted>' if value is DELETE else repr(value)}"
        assert lazy == eager, f"{where}: eager {eager!r}, lazy {lazy!r}"
        checked += 1
        if eager is None:
            continue
        refused += 1
        m = MESSAGE.match(eager) or (TOP.match(eager) if len(path) == 1 else None)
        assert m, f"{where}: {eager!r} does not name the file and a field"
        problem = m["problem"]
        field = m.groupdict().get("field") or ""
        assert related(field, dotted(path)), f"{where}: {eager!r} names another field"
        if value is DELETE and path[-1] != "unknown_key" and not isinstance(path[-1], int):
            assert problem == "missing" or field != dotted(path), f"{where}: {eager!r}"
        if field == dotted(path) and value is not DELETE:
            # what was expected: the type or range, or the value it must equal (and why)
            assert problem.startswith(EXPECTED_STARTS) or any(p in problem for p in EXPECTED_PARTS), \
                f"{where}: {eager!r}"
        if path[-1] == "unknown_key":
            assert "unknown key 'unknown_key'" in problem, f"{where}: {eager!r}"
    assert checked > 900 and refused > 0.8 * checked, (checked, refused)
