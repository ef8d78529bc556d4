"""PLY files: a general header/element reader, and the standard 3DGS PLY reader and writer.

The 3DGS conventions (property names, channel-major f_rest, logit opacity, log scales, (w, x, y, z)
quaternions) are those of the reference training code; see format_spec/foreign_formats.md.
"""
from __future__ import annotations

import os
import re
import warnings
from dataclasses import dataclass, field

import numpy as np

from .atomic import atomic_file
from .errors import InputError
from .gaussians import SH_REST_COEFFS, Gaussians, normalize_quaternions
from .progress import some_of
from .reader_support import DROP_INVALID_HINT, check_memory, model_bytes_per_splat, opacity_logits_from_unit

PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
MAX_HEADER_BYTES = 1 << 20
SH_REST_DEGREES = {0: 0, 9: 1, 24: 2, 45: 3}  # f_rest_* properties -> SH degree
REQUIRED = ["x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity",
            "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


class InfiniteOpacityWarning(UserWarning):
    """Opacity logits of +-inf (alpha 1 or 0) were read as finite logits; `count` says how many."""

    def __init__(self, message: str, count: int):
        super().__init__(message)
        self.count = count


@dataclass
class PlyElement:
    name: str
    count: int
    properties: list[tuple[str, str]] = field(default_factory=list)  # (name, numpy type code without order)

    def dtype(self, order: str) -> np.dtype:
        return np.dtype([(n, order + t) for n, t in self.properties])


@dataclass
class PlyHeader:
    format: str  # "binary_little_endian" | "binary_big_endian" | "ascii"
    elements: list[PlyElement]  # the fixed-size elements read, in file order (those before `unread`)
    size: int  # bytes up to and including the end_header line
    comments: list[str] = field(default_factory=list)
    # Elements from the first one with a list property on (a mesh's `face`): their rows vary in size, so they and
    # what follows them are not read, and where they hold rows (`unread_rows`) the file's length is checked only to
    # hold the elements before them (with none, as `element face 0` is written, it must still match exactly).
    unread: list[str] = field(default_factory=list)
    unread_rows: int = 0

    def element(self, name: str) -> PlyElement | None:
        return next((e for e in self.elements if e.name == name), None)


def read_header(path: str | os.PathLike, head: bytes | None = None) -> PlyHeader:
    """Parse a PLY header. Raises InputError naming the file and the offending line."""
    if head is None:
        with open(path, "rb") as f:
            head = f.read(MAX_HEADER_BYTES)
    if not head:
        raise InputError(path, None, "file is empty (expected a PLY header starting with 'ply')")
    if not head.startswith(b"ply\n") and not head.startswith(b"ply\r\n"):
        raise InputError(path, None, "not a PLY file (expected the first line to be 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise InputError(path, "header", f"no 'end_header' line in the first {len(head)} bytes")
    nl = head.find(b"\n", end)
    if nl < 0:
        raise InputError(path, "header", "file ends inside the 'end_header' line")
    try:
        lines = head[:end].decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise InputError(path, "header", "header is not ASCII text") from None
    fmt = None
    elements: list[PlyElement] = []
    comments: list[str] = []
    with_lists: list[str] = []  # the elements that have a list property, in order
    for lineno, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words:
            continue
        key = words[0]
        if key in ("comment", "obj_info"):
            comments.append(line[len(key):].strip())
        elif key == "format":
            if len(words) != 3 or words[1] not in ("binary_little_endian", "binary_big_endian", "ascii"):
                raise InputError(path, f"header line {lineno}",
                                 f"unsupported format {line!r} (expected binary_little_endian, "
                                 "binary_big_endian or ascii)")
            fmt = words[1]
        elif key == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(path, f"header line {lineno}", f"bad element line {line!r} "
                                 "(expected 'element NAME COUNT')")
            if any(e.name == words[1] for e in elements):
                # Readers look elements up by name: a second one would be silently ignored.
                raise InputError(path, f"header line {lineno}", f"element {words[1]!r} declared twice")
            elements.append(PlyElement(words[1], int(words[2])))
        elif key == "property":
            if not elements:
                raise InputError(path, f"header line {lineno}", "property before any element")
            if len(words) >= 2 and words[1] == "list":
                # `element face 0` / `property list uchar int vertex_indices` after the splats, as mesh tools
                # write it, was refused (newuser63): such an element is skipped, unread (PlyHeader.unread).
                if elements[-1].name == "vertex":
                    raise InputError(path, "element vertex", f"list property {' '.join(words[2:])!r} is not "
                                     "supported in splat files (a splat's row holds numbers only)")
                if len(words) != 5 or words[2] not in PLY_TYPES or words[3] not in PLY_TYPES:
                    raise InputError(path, f"header line {lineno}", f"bad property line {line!r} (expected "
                                     "'property list COUNT_TYPE ITEM_TYPE NAME')")
                if elements[-1].name not in with_lists:
                    with_lists.append(elements[-1].name)
                continue
            if len(words) != 3 or words[1] not in PLY_TYPES:
                raise InputError(path, f"header line {lineno}",
                                 f"bad property line {line!r} (expected 'property TYPE NAME' with TYPE one of "
                                 "char, uchar, short, ushort, int, uint, float, double)")
            names = [p[0] for p in elements[-1].properties]
            if words[2] in names:
                raise InputError(path, f"element {elements[-1].name}", f"property {words[2]!r} declared twice")
            elements[-1].properties.append((words[2], PLY_TYPES[words[1]]))
        else:
            raise InputError(path, f"header line {lineno}", f"unknown header keyword {key!r}")
    if fmt is None:
        raise InputError(path, "header", "no 'format' line")
    unread: list[str] = []
    if with_lists:
        first = next(i for i, e in enumerate(elements) if e.name == with_lists[0])
        unread = [e.name for e in elements[first:]]
        if "vertex" in unread:
            raise InputError(path, f"element {with_lists[0]}", "an element with a list property before element "
                             "vertex is not supported (its rows vary in size: the splats after it cannot be "
                             "found); put it after the splats")
        unread_rows = sum(e.count for e in elements[first:])
        elements = elements[:first]
        return PlyHeader(fmt, elements, nl + 1, comments, unread, unread_rows)
    return PlyHeader(fmt, elements, nl + 1, comments)


def read_elements(path: str | os.PathLike, header: PlyHeader | None = None) -> tuple[PlyHeader, dict[str, np.ndarray]]:
    """Read every element of a PLY file into a structured array, checking sizes against the file length."""
    path = os.fspath(path)
    header = header or read_header(path)
    file_size = os.path.getsize(path)
    out: dict[str, np.ndarray] = {}
    if header.format == "ascii":
        data_bytes = file_size - header.size
        # Every value takes at least one character and a separator: counts are capped by the file size before
        # anything is read, and the token list (about 60 bytes a token) must fit the memory budget.
        declared = sum(el.count * len(el.properties) for el in header.elements)
        if declared > (data_bytes + 1) // 2:
            raise InputError(path, "header", f"the elements declare {declared} ASCII values, but {data_bytes} bytes "
                             f"of data hold at most {(data_bytes + 1) // 2} (truncated, or a wrong count)")
        check_memory(path, None, declared, ASCII_BYTES_PER_VALUE)
        with open(path, "rb") as f:
            f.seek(header.size)
            data = f.read()
        tokens = data.split()
        # Letters or other characters anywhere: check each token against the number grammar.
        strict = bool(data.translate(None, _ASCII_NUMBER_CHARS + b" \t\r\n\v\f"))
        del data
        pos = 0
        for el in header.elements:
            width = len(el.properties)
            need = el.count * width
            if len(tokens) - pos < need:
                raise InputError(path, f"element {el.name}",
                                 f"truncated: header declares {el.count} rows of {width} values, "
                                 f"only {max(0, len(tokens) - pos) // max(width, 1)} complete rows follow")
            values = _ascii_values(path, el, tokens[pos:pos + need], strict)
            arr = np.empty(el.count, el.dtype("<"))
            for i, (name, code) in enumerate(el.properties):
                column = values[:, i]
                if code[0] in "iu":
                    info = np.iinfo(code)
                    bad = ~((column == np.round(column)) & (column >= info.min) & (column <= info.max))
                    if bad.any():
                        row = int(np.argmax(bad))
                        raise InputError(path, f"element {el.name}, row {row}, property {name}",
                                         f"{column[row]!r} is not an integer in {info.min}..{info.max}")
                arr[name] = column
            out[el.name] = arr
            pos += need
        if pos != len(tokens) and not header.unread_rows:
            raise InputError(path, "header", f"{len(tokens) - pos} values after the last element: "
                             "the element counts in the header do not match the data")
        return header, out
    check_element_sizes(path, header)
    order = "<" if header.format == "binary_little_endian" else ">"
    offset = header.size
    for el in header.elements:
        dt = el.dtype(order)
        out[el.name] = np.fromfile(path, dtype=dt, count=el.count, offset=offset)
        offset += el.count * dt.itemsize
    return header, out


def check_element_sizes(path: str, header: PlyHeader) -> None:
    """A binary PLY's element counts against the file length, before anything is allocated (a hostile header
    cannot ask for a huge array). ASCII files are checked by read_elements."""
    if header.format == "ascii":
        return
    file_size = os.path.getsize(path)
    offset = header.size
    for el in header.elements:
        itemsize = el.dtype("<").itemsize
        need = el.count * itemsize
        if offset + need > file_size:
            have = max(0, file_size - offset)
            raise InputError(path, f"element {el.name}",
                             f"truncated: header declares {el.count} rows of {itemsize} bytes "
                             f"({need} bytes) but only {have} bytes follow "
                             f"({have // max(itemsize, 1)} complete rows)")
        offset += need
    if offset != file_size and not header.unread_rows:
        raise InputError(path, "header", f"{file_size - offset} bytes after the last element: the element "
                         "counts in the header do not match the data")


# Memory per ASCII value while parsing: the token (a bytes object and its list slot) and its float64.
ASCII_BYTES_PER_VALUE = 72
# What a C printf writes for a number (and nan / inf, which the 3DGS checks then report as non-finite). Python's
# float() also takes "1_000", " 1 " and other spellings a careful reader refuses.
_ASCII_NUMBER = re.compile(rb"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?|[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
_ASCII_NUMBER_CHARS = b"0123456789+-.eE"


def _ascii_values(path: str, el: PlyElement, tokens: list[bytes], strict: bool) -> np.ndarray:
    """(count, width) float64 values of an element's ASCII tokens, each checked to be a plain number."""
    width = len(el.properties)
    try:
        if strict:
            raise ValueError
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        for k, token in enumerate(tokens):
            if not _ASCII_NUMBER.fullmatch(token):
                row, column = divmod(k, max(width, 1))
                raise InputError(path, f"element {el.name}, row {row}, property {el.properties[column][0]}",
                                 f"{token[:40].decode('ascii', 'backslashreplace')!r} is not a number") from None
        values = np.array(tokens, dtype=np.float64)
    return values.reshape(el.count, width)


def _column_reader(arr: np.ndarray):
    """Function name-list -> (N, len) float32 matrix of those columns of a structured array.

    When every property is float32 little-endian the records are a plain float matrix and each output is
    one fancy-index gather from it (no intermediate copy of the whole table: keeps peak memory low).
    """
    fields = arr.dtype.fields
    all_names = list(arr.dtype.names)
    if all(f[0] == np.dtype("<f4") for f in fields.values()):
        mat = arr.view("<f4").reshape(len(arr), len(all_names))
        return lambda names: mat[:, [all_names.index(n) for n in names]]

    def gather(names: list[str]) -> np.ndarray:
        out = np.empty((len(arr), len(names)), np.float32)
        for i, n in enumerate(names):
            out[:, i] = arr[n]
        return out

    return gather


@dataclass
class VertexLayout:
    """Where the splats of a binary 3DGS PLY lie: fixed-size records, so any range of rows is one byte range."""

    path: str
    rows: int
    offset: int  # byte offset of row 0
    dtype: np.dtype  # one record
    rest: int  # f_rest_* properties (0, 9, 24, 45)
    names: list[str] = field(default_factory=list)

    @property
    def sh_degree(self) -> int:
        return (0, 9, 24, 45).index(self.rest)


@dataclass
class RowStats:
    """What reading some rows found wrong (summed over the parts of a file read piece by piece)."""

    rows: int = 0
    bad_rows: int = 0
    per_field: dict[str, int] = field(default_factory=dict)
    zero_q: int = 0
    infinite: int = 0
    infinite_positive: int = 0

    def __add__(self, other: RowStats) -> RowStats:
        fields = dict(self.per_field)
        for k, v in other.per_field.items():
            fields[k] = fields.get(k, 0) + v
        return RowStats(self.rows + other.rows, self.bad_rows + other.bad_rows, fields, self.zero_q + other.zero_q,
                        self.infinite + other.infinite, self.infinite_positive + other.infinite_positive)


def _vertex_header(path: str, header: PlyHeader) -> tuple[PlyElement, int]:
    """The checks of a 3DGS PLY's header: its vertex element and its f_rest_* count."""
    vertex = header.element("vertex")
    if vertex is None:
        raise InputError(path, "header", "no 'vertex' element (a 3DGS PLY stores splats as vertices)")
    names = [p[0] for p in vertex.properties]
    if "packed_position" in names or header.element("chunk") is not None:
        raise InputError(path, "header", "this is a PlayCanvas compressed PLY, not a standard 3DGS PLY")
    missing = [n for n in REQUIRED if n not in names]
    if missing:
        raise InputError(path, "element vertex", f"missing required properties {', '.join(missing)} "
                         "(a 3DGS PLY needs x y z f_dc_0..2 opacity scale_0..2 rot_0..3)")
    rest = sorted((n for n in names if n.startswith("f_rest_")), key=lambda n: int(n[7:]) if n[7:].isdigit() else -1)
    n_rest = len(rest)
    if n_rest not in (0, 9, 24, 45):
        raise InputError(path, "element vertex", f"{n_rest} f_rest_* properties: expected 0, 9, 24 or 45 "
                         "(SH degree 0, 1, 2 or 3)")
    if rest != [f"f_rest_{i}" for i in range(n_rest)]:
        raise InputError(path, "element vertex", f"f_rest_* properties must be numbered 0..{n_rest - 1}")
    return vertex, n_rest


def vertex_layout(path: str | os.PathLike, header: PlyHeader | None = None) -> VertexLayout | None:
    """The row layout of a binary 3DGS PLY (after the same checks as read_gaussians_ply, the file's length
    included), or None for an ASCII PLY (rows of varying length: read it whole). `header`: the file's, when the
    caller parsed it already (io.open_input)."""
    path = os.fspath(path)
    header = header or read_header(path)
    vertex, n_rest = _vertex_header(path, header)
    if header.format == "ascii":
        return None
    order = "<" if header.format == "binary_little_endian" else ">"
    file_size = os.path.getsize(path)
    offset, vertex_offset = header.size, 0
    for el in header.elements:
        dt = el.dtype(order)
        need = el.count * dt.itemsize
        if offset + need > file_size:
            have = max(0, file_size - offset)
            raise InputError(path, f"element {el.name}",
                             f"truncated: header declares {el.count} rows of {dt.itemsize} bytes "
                             f"({need} bytes) but only {have} bytes follow "
                             f"({have // max(dt.itemsize, 1)} complete rows)")
        if el is vertex:
            vertex_offset = offset
        offset += need
    if offset != file_size and not header.unread_rows:
        raise InputError(path, "header", f"{file_size - offset} bytes after the last element: the element "
                         "counts in the header do not match the data")
    return VertexLayout(path, vertex.count, vertex_offset, vertex.dtype(order), n_rest,
                        [p[0] for p in vertex.properties])


def _gaussians_from_records(records: np.ndarray, n_rest: int) -> tuple[Gaussians, RowStats]:
    """Gaussians from 3DGS vertex records: +-inf opacities clamped, rows with non-finite values or zero-length
    quaternions found (and dropped: the caller decides from the stats whether that is an error)."""
    columns = _column_reader(records)
    del records  # the column reader holds the raw records until `columns` goes
    groups = {
        "positions": ["x", "y", "z"], "sh_dc": ["f_dc_0", "f_dc_1", "f_dc_2"], "opacity_logits": ["opacity"],
        "log_scales": ["scale_0", "scale_1", "scale_2"], "rotations": ["rot_0", "rot_1", "rot_2", "rot_3"],
        # Coefficient-major, channels last, so the gathered matrix reshapes to (N, K, 3) without a copy.
        "sh_rest": [f"f_rest_{c * (n_rest // 3) + j}" for j in range(n_rest // 3) for c in range(3)],
    }
    values = {k: columns(v) for k, v in groups.items()}
    del columns  # drops the raw records
    n = len(values["positions"])
    stats = RowStats(rows=n)
    # An infinite opacity logit is alpha exactly 1 (+inf) or 0 (-inf): splat-transform writes +inf for fully
    # opaque splats. It is a value, not corruption: clamp it to the finite logit every 8-bit-alpha reader uses
    # for alpha 1 or 0. NaN stays invalid (below).
    opacity = values["opacity_logits"]
    infinite = np.isinf(opacity)
    if infinite.any():
        limit = float(opacity_logits_from_unit(np.ones(1))[0])
        stats.infinite = int(infinite.sum())
        stats.infinite_positive = int((opacity > 0)[infinite].sum())
        opacity[infinite] = np.where(opacity[infinite] > 0, limit, -limit)
    bad_rows = np.zeros(n, bool)
    for key, cols in groups.items():
        finite = np.isfinite(values[key])
        if not finite.all():
            for i, name in enumerate(cols):
                bad = int((~finite[:, i]).sum())
                if bad:
                    stats.per_field[name] = bad
            bad_rows |= ~finite.all(axis=1)
    q = values["rotations"]
    zero_q = ~bad_rows & ~(np.abs(q) > 0).any(axis=1)
    stats.bad_rows, stats.zero_q = int(bad_rows.sum()), int(zero_q.sum())
    keep = ~(bad_rows | zero_q)
    if not keep.all():
        values = {k: v[keep] for k, v in values.items()}
    m = len(values["positions"])
    g = Gaussians(
        positions=values["positions"],
        rotations=normalize_quaternions(values["rotations"]),
        log_scales=values["log_scales"],
        opacity_logits=values["opacity_logits"][:, 0],
        sh_dc=values["sh_dc"],
        sh_rest=values["sh_rest"].reshape(m, n_rest // 3, 3),
    )
    return g, stats


def check_rows(path: str, stats: RowStats, drop_invalid: bool) -> None:
    """Warn about clamped opacities and dropped rows, or raise InputError for invalid rows without drop_invalid:
    one message for the whole file, however many pieces it was read in."""
    n = stats.rows
    if stats.infinite:
        limit = float(opacity_logits_from_unit(np.ones(1))[0])
        warnings.warn(InfiniteOpacityWarning(
            f"{path}: {some_of(stats.infinite, n, 'splats', ('has', 'have'))} an infinite opacity logit "
            f"({stats.infinite_positive} +inf = alpha 1, {stats.infinite - stats.infinite_positive} -inf = alpha 0); "
            f"read as +-{limit:.2f}",
            stats.infinite), stacklevel=3)
    if stats.bad_rows:
        detail = ", ".join(f"{k}: {v}" for k, v in stats.per_field.items())
        msg = f"{some_of(stats.bad_rows, n, 'splats', ('has', 'have'))} non-finite values (NaN or inf) ({detail})"
        if not drop_invalid:
            raise InputError(path, "element vertex", f"{msg}; {DROP_INVALID_HINT}")
        warnings.warn(f"{path}: {msg}; dropped", stacklevel=3)
    if stats.zero_q:
        msg = f"{some_of(stats.zero_q, n, 'splats', ('has', 'have'))} a zero-length quaternion (rot_0..rot_3 all 0)"
        if not drop_invalid:
            raise InputError(path, "element vertex", f"{msg}; {DROP_INVALID_HINT}")
        warnings.warn(f"{path}: {msg}; dropped", stacklevel=3)


def read_ply_rows(layout: VertexLayout, start: int, stop: int) -> tuple[Gaussians, RowStats]:
    """Rows start..stop of a binary 3DGS PLY: one byte range of the file. Invalid rows are dropped and counted;
    check_rows on the summed stats reports them as read_gaussians_ply would."""
    count = max(0, min(stop, layout.rows) - start)
    return _gaussians_from_records(np.fromfile(layout.path, dtype=layout.dtype, count=count,
                                               offset=layout.offset + start * layout.dtype.itemsize), layout.rest)


def read_gaussians_ply(path: str | os.PathLike, drop_invalid: bool = False, header: PlyHeader | None = None
                       ) -> Gaussians:
    """Read a standard 3DGS PLY (any PLY format, float or double, any property order). `header`: the file's,
    when the caller parsed it already (io.open_input)."""
    path = os.fspath(path)
    header = header or read_header(path)
    vertex, n_rest = _vertex_header(path, header)
    check_element_sizes(path, header)
    check_memory(path, "element vertex", vertex.count,
                 vertex.dtype("<").itemsize + 3 * model_bytes_per_splat(SH_REST_DEGREES.get(n_rest, 3)))
    _, elements = read_elements(path, header)
    g, stats = _gaussians_from_records(elements.pop("vertex"), n_rest)
    check_rows(path, stats, drop_invalid)
    return g


def gaussians_ply_dtype(sh_degree: int, normals: bool = True) -> np.dtype:
    k = SH_REST_COEFFS[sh_degree]
    names = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals else []) + ["f_dc_0", "f_dc_1", "f_dc_2"]
    names += [f"f_rest_{i}" for i in range(3 * k)]
    names += ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    return np.dtype([(n, "<f4") for n in names])


def gaussians_to_records(g: Gaussians, normals: bool = True) -> np.ndarray:
    dt = gaussians_ply_dtype(g.sh_degree, normals)
    n = len(g)
    mat = np.zeros((n, len(dt.names)), np.float32)
    c = 6 if normals else 3
    mat[:, 0:3] = g.positions
    mat[:, c:c + 3] = g.sh_dc
    k = g.sh_rest.shape[1]
    mat[:, c + 3:c + 3 + 3 * k] = g.sh_rest.transpose(0, 2, 1).reshape(n, 3 * k)
    o = c + 3 + 3 * k
    mat[:, o] = g.opacity_logits
    mat[:, o + 1:o + 4] = g.log_scales
    mat[:, o + 4:o + 8] = g.rotations
    return mat.view(dt).reshape(n)


def write_gaussians_ply(g: Gaussians, path: str | os.PathLike, normals: bool = True) -> None:
    """Write a standard binary little-endian 3DGS PLY (atomically: temporary name, then rename)."""
    records = gaussians_to_records(g, normals)
    lines = ["ply", "format binary_little_endian 1.0", "comment written by splatstream",
             f"element vertex {len(g)}"]
    lines += [f"property float {n}" for n in records.dtype.names]
    lines.append("end_header")
    with atomic_file(path) as f:
        f.write(("\n".join(lines) + "\n").encode("ascii"))
        records.tofile(f)
