"""glTF 2.0 binary (.glb) with KHR_gaussian_splatting, plain or SPZ-compressed
(KHR_gaussian_splatting_compression_spz_2).

`glb_bytes(g)` is a pure function Gaussians -> GLB bytes, one point primitive holding every splat; exporters
(3D Tiles, one GLB per tile) call it per tile and may pass a node `matrix` and extra top-level JSON.

Axes: glTF is y-up with +z forward and +x left (LUF); our model is the 3DGS PLY's RDF. We turn the scene 180
degrees about z (x and y negate), which is also what splat-transform's .glb writer does with a PLY, so a scene
stands upright in glTF viewers.

Plain form (attributes as the extension defines them, all float except COLOR_0):
POSITION (with min/max), COLOR_0 (u8 normalized RGBA fallback: linear RGB of the clamped SH band-0 colour,
alpha = opacity), KHR_gaussian_splatting:ROTATION (x, y, z, w), :SCALE (linear = exp(log scale)),
:OPACITY (sigmoid(logit)), :SH_DEGREE_0_COEF_0 (f_dc), :SH_DEGREE_l_COEF_n (l = 1..3, n = 0..2l, RGB).

SPZ form: the SPZ file (of the same scene in glTF axes, packed "from LUF", i.e. stored in SPZ's RUB like any
SPZ) is buffer view 0 and the extension object points to it; the attributes the extension maps from SPZ
(POSITION with min/max, COLOR_0, SCALE, ROTATION, SH_DEGREE_l_COEF_n for l >= 1) keep accessors with `count`,
`type` and `componentType` but no buffer view. OPACITY and SH_DEGREE_0_COEF_0 are not listed: the extension maps
SPZ's alphas and colours to COLOR_0, and CesiumJS's loader fills only the attributes of that mapping.

`spz_axes="luf"` stores the glTF (LUF) values in the SPZ unconverted instead: CesiumJS decodes SPZ content with
`coordinateSystem: "UNSPECIFIED"` (no conversion) and uses the values as glTF coordinates, which the extension
text (pack from LUF, i.e. into RUB) contradicts; which of the two CesiumJS draws in place is for the 3D Tiles
browser test to decide.
"""
from __future__ import annotations

import json
import os
import struct

import numpy as np

from ..atomic import atomic_file
from ..axes import RDF_TO_LUF, RDF_TO_RUB, turn
from ..errors import UsageError
from ..gaussians import Gaussians, sigmoid
from ..gltf_splats import EXTENSION, PREFIX, SPZ_EXTENSION, sh_attribute_names
from ..readers.spz import decode_spz
from .spz import spz_bytes

GLB_MAGIC = b"glTF"
GLB_VERSION = 2
CHUNK_JSON = 0x4E4F534A
CHUNK_BIN = 0x004E4942
FLOAT = 5126
UNSIGNED_BYTE = 5121
ARRAY_BUFFER = 34962
SPLAT_PROPERTIES = {"kernel": "ellipse", "colorSpace": "srgb_rec709_display", "projection": "perspective",
                    "sortingMethod": "cameraDistance"}
# SPZ inside glTF: the extension references SPZ 2.0.0, whose files are version 3 (gzip); CesiumJS's loader
# reads those. Version 4 (zstd) is on request.
DEFAULT_SPZ_VERSION = 3
COMPRESSIONS = ("none", "spz")
SPZ_AXES = ("rub", "luf")


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _color0(g: Gaussians) -> np.ndarray:
    """COLOR_0 fallback: the extension asks for linear values (glTF colours are linear) of the display colour."""
    rgb = _srgb_to_linear(np.clip(g.base_colors.astype(np.float64), 0.0, 1.0))
    rgba = np.concatenate([rgb, sigmoid(g.opacity_logits)[:, None]], axis=1)
    return np.clip(np.rint(rgba * 255.0), 0, 255).astype(np.uint8)


def _pad4(data: bytes, fill: bytes = b"\x00") -> bytes:
    return data + fill * (-len(data) % 4)


def glb_bytes(g: Gaussians, compression: str = "none", spz_version: int = DEFAULT_SPZ_VERSION,
              matrix: list[float] | None = None, generator: str = "splatstream",
              extras: dict | None = None, spz_axes: str = "rub") -> bytes:
    """A GLB holding `g` (RDF axes) as one KHR_gaussian_splatting point primitive.

    compression: "none" (plain float accessors) or "spz" (KHR_gaussian_splatting_compression_spz_2 with an SPZ
    file of `spz_version`). matrix: optional column-major 4x4 node matrix (glTF convention). extras: merged into
    the asset's `extras`. spz_axes: "rub" (the extension's text) or "luf" (glTF values stored unconverted).
    """
    if compression not in COMPRESSIONS:
        raise UsageError(f"glTF compression {compression!r} is not supported (expected one of {COMPRESSIONS})")
    if spz_axes not in SPZ_AXES:
        raise UsageError(f"SPZ axes {spz_axes!r} (expected one of {SPZ_AXES})")
    if matrix is not None and (len(matrix) != 16 or not np.isfinite(np.asarray(matrix, np.float64)).all()):
        raise UsageError("a glTF node matrix needs 16 finite numbers (column-major)")
    n = len(g)
    if n == 0:
        raise UsageError("a glTF splat primitive needs at least one splat (accessor count must be >= 1)")
    # Plain accessors hold the scene in glTF axes; the SPZ form packs from `g` directly (below).
    luf = turn(g, RDF_TO_LUF) if compression == "none" else None
    position_min = luf.positions.min(axis=0).astype(np.float64).tolist() if luf is not None else None
    position_max = luf.positions.max(axis=0).astype(np.float64).tolist() if luf is not None else None
    names = ["POSITION", "COLOR_0", f"{PREFIX}ROTATION", f"{PREFIX}SCALE", f"{PREFIX}OPACITY",
             f"{PREFIX}SH_DEGREE_0_COEF_0", *sh_attribute_names(g.sh_degree)]
    if compression == "spz":
        names = [n for n in names if n not in (f"{PREFIX}OPACITY", f"{PREFIX}SH_DEGREE_0_COEF_0")]
    kinds = {"POSITION": ("VEC3", FLOAT), "COLOR_0": ("VEC4", UNSIGNED_BYTE), f"{PREFIX}ROTATION": ("VEC4", FLOAT),
             f"{PREFIX}OPACITY": ("SCALAR", FLOAT)}
    accessors: list[dict] = []
    attributes: dict[str, int] = {}
    for name in names:
        gl_type, component = kinds.get(name, ("VEC3", FLOAT))
        accessor: dict = {"componentType": component, "count": n, "type": gl_type}
        if component == UNSIGNED_BYTE:
            accessor["normalized"] = True
        if name == "POSITION":
            accessor["min"], accessor["max"] = position_min, position_max
        attributes[name] = len(accessors)
        accessors.append(accessor)
    splat_extension: dict = dict(SPLAT_PROPERTIES)
    extensions_used = [EXTENSION]
    extensions_required: list[str] = []
    buffer_views: list[dict] = []
    if compression == "spz":
        # Packed from glTF's LUF into SPZ's RUB: the same bytes as an SPZ file of the RDF scene.
        blob = spz_bytes(g, spz_version, axes=RDF_TO_RUB if spz_axes == "rub" else RDF_TO_LUF)
        # The bounds a viewer gets are those of the decoded (quantised) positions.
        decoded = turn(decode_spz("<spz content>", blob), RDF_TO_LUF if spz_axes == "rub" else RDF_TO_RUB).positions
        accessors[0]["min"] = decoded.min(axis=0).astype(np.float64).tolist()
        accessors[0]["max"] = decoded.max(axis=0).astype(np.float64).tolist()
        buffer_views.append({"buffer": 0, "byteOffset": 0, "byteLength": len(blob)})
        splat_extension["extensions"] = {SPZ_EXTENSION: {"bufferView": 0}}
        extensions_used.append(SPZ_EXTENSION)
        extensions_required = [EXTENSION, SPZ_EXTENSION]  # no uncompressed fallback data
        binary = _pad4(blob)
    else:
        assert luf is not None
        rest = [luf.sh_rest[:, k] for k in range(luf.sh_rest.shape[1])]
        arrays = [luf.positions, _color0(luf), luf.rotations[:, [1, 2, 3, 0]], np.exp(luf.log_scales),
                  sigmoid(luf.opacity_logits), luf.sh_dc, *rest]
        chunks = []
        offset = 0
        for index, array in enumerate(arrays):
            data = np.ascontiguousarray(array).astype("<f4" if array.dtype != np.uint8 else "u1").tobytes()
            buffer_views.append({"buffer": 0, "byteOffset": offset, "byteLength": len(data), "target": ARRAY_BUFFER})
            accessors[index]["bufferView"] = index
            chunks.append(_pad4(data))
            offset += len(chunks[-1])
        binary = b"".join(chunks)
    node: dict = {"mesh": 0}
    if matrix is not None:
        node["matrix"] = [float(v) for v in matrix]
    asset: dict = {"version": "2.0", "generator": generator}
    if extras:
        asset["extras"] = extras
    gltf: dict = {
        "asset": asset,
        "extensionsUsed": extensions_used,
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [node],
        "meshes": [{"primitives": [{"attributes": attributes, "mode": 0,
                                    "extensions": {EXTENSION: splat_extension}}]}],
        "accessors": accessors,
        "bufferViews": buffer_views,
        "buffers": [{"byteLength": len(binary)}],
    }
    if extensions_required:
        gltf["extensionsRequired"] = extensions_required
    json_chunk = _pad4(json.dumps(gltf, separators=(",", ":")).encode("utf-8"), b" ")
    total = 12 + 8 + len(json_chunk) + 8 + len(binary)
    return b"".join([struct.pack("<4sII", GLB_MAGIC, GLB_VERSION, total),
                     struct.pack("<II", len(json_chunk), CHUNK_JSON), json_chunk,
                     struct.pack("<II", len(binary), CHUNK_BIN), binary])


def write_glb(g: Gaussians, path: str | os.PathLike, compression: str = "none",
              spz_version: int = DEFAULT_SPZ_VERSION) -> None:
    """Write a .glb atomically (temporary name, then rename)."""
    try:
        data = glb_bytes(g, compression, spz_version)
    except UsageError as exc:  # name the file being written
        raise UsageError(f"{os.fspath(path)}: {exc}") from None
    with atomic_file(path) as f:
        f.write(data)
