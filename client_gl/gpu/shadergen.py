"""GLSL sources for a pool's texel formats, generated from the one source of truth in Python.

The texel decoders follow splatstream.format.texformats / codec (format_spec/format.md 4.2-4.5), the SH constants
and basis come from splatstream.sh, the slot layout, range-record word offsets and texture units from
client_gl.gpu.residency_layout. Static code lives in client_gl/gpu/shaders/*; `#include "name"` lines are expanded
here.
"""
from __future__ import annotations

import math
from pathlib import Path

from splatstream import sh
from splatstream.format.codec import rotation_mode
from splatstream.format.texformats import get_format

from .residency_layout import RANGE_WORDS, SH_BAND_LAYERS, PoolLayout

# Radix sort geometry: 4-bit digits, 256 threads x ITEMS keys per work group, scans of 256 x SCAN_ITEMS values.
RADIX_BITS = 4
SORT_ITEMS = 8
SCAN_ITEMS = 8
SORT_TILE = 256 * SORT_ITEMS
SCAN_TILE = 256 * SCAN_ITEMS
DEBUG_STRIDE = 80  # floats per splat written by decode_debug.comp
F2B_BATCHES = 8  # front-to-back draws: batches separated by saturation passes

_INTEGER_FORMATS = {"norm11", "norm9x3", "norm565"}


def read_shader(name: str) -> str:
    return (Path(__file__).parent / "shaders" / name).read_text()


def _expand_includes(src: str) -> str:
    out = []
    for line in src.splitlines():
        s = line.strip()
        if s.startswith("#include"):
            out.append(_expand_includes(read_shader(s.split('"')[1])))
        else:
            out.append(line)
    return "\n".join(out)


def _f(x: float) -> str:
    return repr(float(x))


def _t_fetch(plane: str, fmt_name: str, array: bool) -> str:
    """GLSL `vec4 t_<plane>(ivec2 p[, int layer])`: normalised texel values exactly as texformats decodes them."""
    fmt = get_format(fmt_name)
    args = "ivec2 p, int layer" if array else "ivec2 p"
    coord = "ivec3(p, layer)" if array else "p"
    fetch = f"texelFetch(u_{plane}, {coord}, 0)"
    layout = fmt.texels  # cube565 is norm565's texels (format.md 4.5)
    if layout == "norm11":
        body = (f"uint w = {fetch}.r;\n    return vec4(float(w & 2047u) / 2047.0, float((w >> 11) & 1023u) / 1023.0, "
                "float(w >> 21) / 2047.0, 0.0);")
    elif layout == "norm9x3":  # bits 27-31 are zero (format.md 4.2); the masks ignore them anyway
        body = (f"uint w = {fetch}.r;\n    return vec4(float(w & 511u) / 511.0, float((w >> 9) & 511u) / 511.0, "
                "float((w >> 18) & 511u) / 511.0, 0.0);")
    elif layout == "norm565":
        body = (f"uint w = {fetch}.r;\n    return vec4(float(w & 31u) / 31.0, float((w >> 5) & 63u) / 63.0, "
                "float(w >> 11) / 31.0, 0.0);")
    else:  # float, unorm and BC formats: the texture unit returns the normalised values
        body = f"return {fetch};"
    return f"vec4 t_{plane}({args}) {{\n    {body}\n}}\n"


def _sampler(plane: str, fmt_name: str, array: bool) -> str:
    prefix = "u" if get_format(fmt_name).texels in _INTEGER_FORMATS else ""
    kind = "sampler2DArray" if array else "sampler2D"
    return f"uniform {prefix}{kind} u_{plane};\n"


def _rotation_decoder(fmt_name: str) -> str:
    mode = rotation_mode(fmt_name)
    if mode == "full":
        body = "vec4 q = t * 2.0 - 1.0;"
    elif mode == "xyz":
        span = get_format(fmt_name).rotation_range  # cube565: x, y, z over the cube gauge's range (format.md 4.5)
        scaled = "" if span == 1.0 else f" * {_f(span)}"
        body = f"vec3 v = (t.xyz * 2.0 - 1.0){scaled};\n    vec4 q = vec4(sqrt(max(0.0, 1.0 - dot(v, v))), v);"
    else:
        levels = get_format(fmt_name).levels[3]
        body = (f"int largest = clamp(int(round(t.w * {_f(levels)})), 0, 3);\n"
                f"    vec3 small = (t.xyz * 2.0 - 1.0) / {_f(math.sqrt(2.0))};\n"
                "    float big = sqrt(max(0.0, 1.0 - dot(small, small)));\n"
                "    vec4 q;\n    int k = 0;\n"
                "    for (int c = 0; c < 4; ++c) {\n"
                "        if (c == largest) q[c] = big; else { q[c] = small[k]; ++k; }\n"
                "    }")
    return ("// Unit quaternion (w, x, y, z) in (.x, .y, .z, .w), w >= 0 (codec.decode_rotations).\n"
            f"vec4 decode_rotation(ivec2 p) {{\n    vec4 t = t_rotation(p);\n    {body}\n"
            "    float len = length(q);\n    q = len > 0.0 ? q / len : q;\n    return q.x < 0.0 ? -q : q;\n}\n")


def _sh_code(sh_degree: int, codebook: bool = False) -> str:
    lines = [f"const float SH_C0 = {_f(sh.SH_C0)};", f"const float SH_C1 = {_f(sh.SH_C1)};",
             "const float SH_C2[5] = float[5](" + ", ".join(_f(c) for c in sh.SH_C2) + ");",
             "const float SH_C3[7] = float[7](" + ", ".join(_f(c) for c in sh.SH_C3) + ");", ""]
    lines.append("// Sum over bands 0..min(degree, the splat's resident bands) of basis(dir) * coefficient (no +0.5,")
    lines.append("// no clamp): splatstream.sh. A band not resident is not evaluated, exactly as at a lower SH degree.")
    lines.append("vec3 eval_sh(uint id, ivec2 p, vec3 dir, int degree, vec3 dc) {")
    if sh_degree >= 1:
        lines.append("    degree = min(degree, resident_sh_degree(id >> 8));")
    lines.append("    float x = dir.x, y = dir.y, z = dir.z;")
    const, poly = sh.SH_BASIS[0]
    lines.append(f"    vec3 c = ({const}) * ({poly}) * dc;")
    if codebook and sh_degree >= 1:  # one index fetch for all bands: the splat's codebook entry
        lines.append("    uint cb_e = degree >= 1 ? sh_entry(p) : 0u;")
        lines.append("    uint cb_c = cb_e >> 8;")
        lines.append("    ivec2 cb_q = codebook_texel(cb_e);")
    k = 1
    for band in range(1, sh_degree + 1):
        lines.append(f"    if (degree >= {band}) {{")
        for layer in range(SH_BAND_LAYERS[band]):
            const, poly = sh.SH_BASIS[k]
            coeff = (f"decode_cb_sh{band}(cb_c, cb_q, {layer})" if codebook
                     else f"decode_sh{band}(id, p, {layer})")
            lines.append(f"        c += ({const}) * ({poly}) * {coeff};")
            k += 1
        lines.append("    }")
    lines.append("    return c;")
    lines.append("}")
    return "\n".join(lines) + "\n"


def decode_header(layout: PoolLayout) -> str:
    """Samplers, texel decoders and attribute decoders of a pool with this layout (formats, SH bands, codebook).

    With an SH codebook decode_sh<b> looks the splat's entry up in the sh_index atlas and decodes that entry of the
    codebook band. Per slot, the slot-state texture gives the draw flag and the SH bands resident
    (slot_drawn, resident_sh_degree).
    """
    w = RANGE_WORDS
    formats = layout.formats
    sh_degree = layout.sh_degree
    codebook_format = layout.codebook_format
    codebook = codebook_format is not None and sh_degree >= 1
    parts = [f"// ---- generated by client_gl/gpu/shadergen.py ----\n#define SH_DEGREE {sh_degree}\n"
             f"#define DEBUG_STRIDE {DEBUG_STRIDE}u\n"]
    if codebook:
        parts.append("#define SH_CODEBOOK 1\n")
    for plane in ("position", "rotation", "scale", "color"):
        parts.append(_sampler(plane, formats[plane], False))
    if codebook:
        parts.append("uniform usampler2D u_sh_index;  // codebook entry per splat (index16)\n")
        for band in range(1, sh_degree + 1):
            parts.append(_sampler(f"cb_sh{band}", codebook_format, True))
        parts.append("uniform usampler2D u_cb_ranges;  // one 64-word record per codebook chunk (row = chunk)\n")
    else:
        for band in range(1, sh_degree + 1):
            parts.append(_sampler(f"sh{band}", formats["sh"], True))
    parts.append("uniform usampler2D u_ranges;\nuniform uint u_cols;  // chunk blocks per atlas row\n")
    parts.append("uniform usampler2D u_slot_state;  // per slot, RG8UI at (slot % cols, slot / cols): drawn, bands\n")
    if codebook:
        parts.append("uniform int u_cb_bands;  // SH codebook bands uploaded\n")
    parts.append("\n")
    parts.append("""// Texel of index id = block * 256 + j in a chunk-block layout with `cols` blocks a row:
// the block's 16x16 texels, j at the 2D Morton decode.
ivec2 block_texel(uint id, uint cols) {
    uint slot = id >> 8;
    uint j = id & 255u;
    uint mx = (j & 1u) | ((j >> 1) & 2u) | ((j >> 2) & 4u) | ((j >> 3) & 8u);
    uint my = ((j >> 1) & 1u) | ((j >> 2) & 2u) | ((j >> 3) & 4u) | ((j >> 4) & 8u);
    return ivec2(int((slot % cols) * 16u + mx), int((slot / cols) * 16u + my));
}

// Texel of global splat index id = slot * 256 + j in the atlases.
ivec2 splat_texel(uint id) { return block_texel(id, u_cols); }

uint range_word(uint slot, uint w) {
    return texelFetch(u_ranges, ivec2(int((slot % u_cols) * 16u + (w >> 2)), int(slot / u_cols)), 0)[w & 3u];
}
float range_f32(uint slot, uint w) { return uintBitsToFloat(range_word(slot, w)); }
#if __VERSION__ >= 420
float half_bits_to_float(uint h) { return unpackHalf2x16(h).x; }
#else
float half_bits_to_float(uint h) {  // finite halves only (ranges are validated finite)
    uint e = (h >> 10) & 31u;
    float m = float(h & 1023u);
    float v = e == 0u ? m * exp2(-24.0) : (1.0 + m / 1024.0) * exp2(float(e) - 15.0);
    return (h & 0x8000u) != 0u ? -v : v;
}
#endif
float range_f16(uint slot, uint w0, uint k) {
    return half_bits_to_float((range_word(slot, w0 + (k >> 1)) >> ((k & 1u) * 16u)) & 0xFFFFu);
}
""")
    parts.append(f"uint range_count(uint slot) {{ return range_word(slot, {w['count']}u); }}\n")
    parts.append("""uvec2 slot_state(uint slot) {
    return texelFetch(u_slot_state, ivec2(int(slot % u_cols), int(slot / u_cols)), 0).rg;
}
// The draw mask: false for slots of tiles outside the frame's draw set (and for free slots).
bool slot_drawn(uint slot) { return slot_state(slot).r != 0u; }
""")
    if codebook:
        parts.append("// SH bands the slot's tile has resident, and the codebook has uploaded.\n"
                     "int resident_sh_degree(uint slot) { return min(int(slot_state(slot).g), u_cb_bands); }\n\n")
    else:
        parts.append("// SH bands the slot's tile has resident.\n"
                     "int resident_sh_degree(uint slot) { return int(slot_state(slot).g); }\n\n")
    if codebook:
        parts.append("""// SH codebook: splat -> entry e (sh_index atlas); entry e of a band is texel
// block_texel(e, cols) of the band's texture (as stored: chunk e >> 8, Morton j = e & 255), dequantised with the
// ranges of codebook chunk e >> 8.
uint sh_entry(ivec2 p) { return texelFetch(u_sh_index, p, 0).r; }
ivec2 codebook_texel(uint e) { return block_texel(e, uint(textureSize(u_cb_sh1, 0).x) >> 4); }
uint cb_range_word(uint c, uint w) { return texelFetch(u_cb_ranges, ivec2(int(w >> 2), int(c)), 0)[w & 3u]; }
float cb_range_f16(uint c, uint w0, uint k) {
    return half_bits_to_float((cb_range_word(c, w0 + (k >> 1)) >> ((k & 1u) * 16u)) & 0xFFFFu);
}

""")
    for plane in ("position", "rotation", "scale", "color"):
        parts.append(_t_fetch(plane, formats[plane], False))
    for band in range(1, sh_degree + 1):
        if codebook:
            parts.append(_t_fetch(f"cb_sh{band}", codebook_format, True))
        else:
            parts.append(_t_fetch(f"sh{band}", formats["sh"], True))
    parts.append(f"""
vec3 decode_position(uint id, ivec2 p) {{
    uint s = id >> 8;
    uint w = {w['position']}u;
    vec3 lo = vec3(range_f32(s, w), range_f32(s, w + 1u), range_f32(s, w + 2u));
    vec3 hi = vec3(range_f32(s, w + 3u), range_f32(s, w + 4u), range_f32(s, w + 5u));
    return lo + t_position(p).xyz * (hi - lo);
}}

vec3 decode_log_scale(uint id, ivec2 p) {{
    uint s = id >> 8;
    vec3 lo = vec3(range_f16(s, {w['scale']}u, 0u), range_f16(s, {w['scale']}u, 1u), range_f16(s, {w['scale']}u, 2u));
    vec3 hi = vec3(range_f16(s, {w['scale']}u, 3u), range_f16(s, {w['scale']}u, 4u), range_f16(s, {w['scale']}u, 5u));
    return lo + t_scale(p).xyz * (hi - lo);
}}

// SH0 (rgb) and opacity after the sigmoid (a).
vec4 decode_color(uint id, ivec2 p) {{
    uint s = id >> 8;
    vec4 lo = vec4(range_f16(s, {w['color']}u, 0u), range_f16(s, {w['color']}u, 1u), range_f16(s, {w['color']}u, 2u),
                   range_f16(s, {w['color']}u, 3u));
    vec4 hi = vec4(range_f16(s, {w['color']}u, 4u), range_f16(s, {w['color']}u, 5u), range_f16(s, {w['color']}u, 6u),
                   range_f16(s, {w['color']}u, 7u));
    return lo + t_color(p) * (hi - lo);
}}
""")
    parts.append(_rotation_decoder(formats["rotation"]))
    for band in range(1, sh_degree + 1):
        layers = SH_BAND_LAYERS[band]
        w0 = w[f"sh{band}"]
        if codebook:
            parts.append(f"""
// Coefficient `layer` of SH band {band} (rgb) of codebook entry texel q in codebook chunk c; ranges as the tiles'.
vec3 decode_cb_sh{band}(uint c, ivec2 q, int layer) {{
    uint k = uint(layer) * 3u;
    vec3 lo = vec3(cb_range_f16(c, {w0}u, k), cb_range_f16(c, {w0}u, k + 1u), cb_range_f16(c, {w0}u, k + 2u));
    vec3 hi = vec3(cb_range_f16(c, {w0}u, {layers * 3}u + k), cb_range_f16(c, {w0}u, {layers * 3 + 1}u + k),
                   cb_range_f16(c, {w0}u, {layers * 3 + 2}u + k));
    return lo + t_cb_sh{band}(q, layer).xyz * (hi - lo);
}}

// Coefficient `layer` of SH band {band} (rgb) of splat id: its codebook entry's.
vec3 decode_sh{band}(uint id, ivec2 p, int layer) {{
    uint e = sh_entry(p);
    return decode_cb_sh{band}(e >> 8, codebook_texel(e), layer);
}}
""")
            continue
        parts.append(f"""
// Coefficient `layer` of SH band {band} (rgb); ranges are [min/max][layer][component] halves.
vec3 decode_sh{band}(uint id, ivec2 p, int layer) {{
    uint s = id >> 8;
    uint k = uint(layer) * 3u;
    vec3 lo = vec3(range_f16(s, {w0}u, k), range_f16(s, {w0}u, k + 1u), range_f16(s, {w0}u, k + 2u));
    vec3 hi = vec3(range_f16(s, {w0}u, {layers * 3}u + k), range_f16(s, {w0}u, {layers * 3 + 1}u + k),
                   range_f16(s, {w0}u, {layers * 3 + 2}u + k));
    return lo + t_sh{band}(p, layer).xyz * (hi - lo);
}}
""")
    parts.append(_sh_code(sh_degree, codebook))
    parts.append("// ---- end of generated code ----\n")
    return "".join(parts)


def sort_defines(radix_bits: int = RADIX_BITS) -> str:
    return (f"#define RADIX_BITS {radix_bits}u\n#define RADIX {1 << radix_bits}u\n"
            f"#define ITEMS {SORT_ITEMS}u\n#define TILE {SORT_TILE}u\n"
            f"#define SCAN_ITEMS {SCAN_ITEMS}\n#define SCAN_TILE {SCAN_TILE}u\n#define BATCHES {F2B_BATCHES}u\n")


def compute_source(name: str, header: str = "", version: int = 430, radix_bits: int = RADIX_BITS) -> str:
    """A compute shader: version line, sort defines, optional decode header + common code, then the file."""
    body = _expand_includes(read_shader(name))
    common = header + _expand_includes(read_shader("common.glsl")) if header else ""
    return f"#version {version}\n{sort_defines(radix_bits)}{common}\n{body}\n"


def saturate_sources() -> tuple[str, str]:
    return f"#version 430\n{read_shader('saturate.vert')}\n", f"#version 430\n{read_shader('saturate.frag')}\n"


def projected_render_sources(mode: str = "instanced", front_to_back: bool = False) -> tuple[str, str]:
    """(vertex, fragment) sources of the GPU path's draw, which reads the cull pass's projected records.

    instanced: 4-vertex strips, attributes passed as flat varyings; triangles: non-instanced, 6 vertices a splat;
    fetch: instanced strips passing only the record index (the fragment shader reads the record);
    points: point sprites with the record fetch (measurement only: GL drops points centred off screen).
    """
    if mode in ("instanced", "triangles"):
        define = "#define DRAW_TRIANGLES\n" if mode == "triangles" else ""
        vert = f"#version 430\n{define}{_expand_includes(read_shader('splat_pre.vert'))}\n"
        return vert, f"#version 430\n{read_shader('splat.frag')}\n"
    # Instanced quads index order[] by instance; points draw one instance of n vertices (stride 1, instance 0).
    define = "#define DRAW_POINTS\n#define POINTS_STRIDE 1u\n" if mode == "points" else "#define POINTS_STRIDE 0u\n"
    if front_to_back and mode != "points":
        define += "#define ORDER_ATTRIBUTE\n"  # batches start at a base instance; gl_InstanceID ignores it
    vert = f"#version 430\n{define}{_expand_includes(read_shader('splat_fetch.vert'))}\n"
    early = "#define EARLY_TESTS\n" if front_to_back else ""
    return vert, f"#version 430\n{early}{read_shader('splat_fetch.frag')}\n"


def render_sources(header: str, version: int = 430) -> tuple[str, str]:
    """(vertex, fragment) sources of the splat draw. GL 4.1 is enough for these two (the CPU-sort path)."""
    vert = (f"#version {version}\n{header}{_expand_includes(read_shader('common.glsl'))}\n"
            f"{read_shader('splat.vert')}\n")
    frag = f"#version {version}\n{read_shader('splat.frag')}\n"
    return vert, frag
