"""The fields1 decoder (format_spec/format.md 5.2) compiled with numba (the `view` extra, or `fast` alone):
the bytes of transport.unfilter_fields' numpy path, bit for bit, in one pass over a section's slots.

The numpy path decodes a layer in a dozen to two dozen whole-array steps (zigzag, running sums, masks, cross
predictions, packing, the gather into texture order), each a numpy call and a pass over a work array; on the LOD
tree's tiles of a few hundred splats that was most of a payload's decode (issue 32; BENCHMARKS.md, "Decode speed").
Here each slot's fields are read from their byte planes, summed, predicted, masked and packed into its texel in
slot order, and a layer's texels then stored at their places in texture order two at a time (a pair of slots is a
pair of texels side by side: _store_pairs).

The arithmetic is the spec's read literally, in int64: a field of up to 8 bits is its byte, a wider one its zigzag
code's residual; a delta field's running sum (int64 sums of residuals under 2^32 cannot overflow in a section of
at most 2^25 slots, and the cut below takes them modulo 2^bits); every value cut to its bits (the numpy path cuts only
where the cut reaches the texel: the same bytes); a predicted field plus floor((slope x reference + 64 x intercept
+ 32) / 64), cut again. transport.py checks a content's header, geometry and size before it hands one to the kernel.

`unshuffle_kernel` undoes format.md 5.1's byte shuffle of a unit (rotations, scales and ranges stored shuffled)
in one call where numpy takes four to eight.

`whole_kernel` decodes a whole payload's, or a whole group's, fields1 sections of every format and shuffled units
(texels and ranges) in one call: a decode thread then gives the interpreter lock up twice a payload (zstd, this
kernel) and runs its Python in one stretch before and one after (issue 38's fly-through p99: the frame thread waits
for that lock; issue 32: that Python is most of a small payload's decode).

`morton_kernel` decodes a `morton1` position section (format.md 5.4: keyed positions, the preset
medium-low-palette) in one pass where numpy takes about fifteen calls (keyed.use_morton_kernel).

`ranges_kernel` checks a plane's range values (finite, each minimum at most its maximum, inside the plane's domain:
format.md 4.3, 4.8) in one pass where Python's floats took 5-6 us a call (container.use_ranges_kernel).

`install()` compiles the kernels (or loads them from numba's cache: cache=True) with the argument types of a real
call and hands them to format.transport (`use_fields_kernel`, `use_unshuffle_kernel`, `use_batch_kernels`,
`use_whole_kernel`, keyed's `use_morton_kernel`, container's `use_ranges_kernel`); `uninstall()` goes back to
numpy. The core never imports numba (ARCHITECTURE.md): this module is the streaming client's, and benchmarks import
it to compare both.
"""
from __future__ import annotations

import math
import os

import numpy as np
from numba import njit

from splatstream.format import container, keyed, transport

_JIT = dict(cache=True, nogil=True, boundscheck=False)
WHOLE_ENV = "SPLATSTREAM_DECODE_WHOLE"  # "0": install() leaves the whole kernel out


@njit(**_JIT)
def _f32x4_layer(raw, base, n, deltas, work, slot_to_texel, o):
    """One layer of an f32x4 fields1 content (`o`: its texels' words, texture order), the general loops' bytes: each
    field's zigzag residuals from its four byte planes into a row of `work` taken as uint32, then one loop over the
    slots that adds the four running sums (four chains that do not wait on each other; a field that is not delta
    starts each slot from 0: its mask) and writes each texel's four words.

    Why its own path: very-high, every plane f32x4, was the slowest preset on a slow core (issue 32: 9.8-10.0 M
    splats/s on r23's host). In uint32 a residual loop takes twice the values a vector instruction of int64 takes
    (a 32-bit field's sum modulo 2^32 is uint32's own wrap: no mask), and the running sums taken while the texels are
    written save the separate pass over each row (about 0.8x of the general loops' time on very-high's sections:
    BENCHMARKS.md, "Decode speed", vhdecode32)."""
    for f in range(4):
        b0 = raw[base + 4 * f * n:base + (4 * f + 1) * n]
        b1 = raw[base + (4 * f + 1) * n:base + (4 * f + 2) * n]
        b2 = raw[base + (4 * f + 2) * n:base + (4 * f + 3) * n]
        b3 = raw[base + (4 * f + 3) * n:base + (4 * f + 4) * n]
        row = work[f].view(np.uint32)
        for i in range(n):
            c = (np.uint32(b0[i]) | (np.uint32(b1[i]) << np.uint32(8)) | (np.uint32(b2[i]) << np.uint32(16))
                 | (np.uint32(b3[i]) << np.uint32(24)))
            row[i] = (c >> np.uint32(1)) ^ (np.uint32(0) - (c & np.uint32(1)))
    keep0 = np.uint32(0xFFFFFFFF) if deltas[0] else np.uint32(0)
    keep1 = np.uint32(0xFFFFFFFF) if deltas[1] else np.uint32(0)
    keep2 = np.uint32(0xFFFFFFFF) if deltas[2] else np.uint32(0)
    keep3 = np.uint32(0xFFFFFFFF) if deltas[3] else np.uint32(0)
    r0, r1 = work[0].view(np.uint32)[:n], work[1].view(np.uint32)[:n]
    r2, r3 = work[2].view(np.uint32)[:n], work[3].view(np.uint32)[:n]
    s0 = s1 = s2 = s3 = np.uint32(0)
    for i in range(n):
        s0 = (s0 & keep0) + r0[i]
        s1 = (s1 & keep1) + r1[i]
        s2 = (s2 & keep2) + r2[i]
        s3 = (s3 & keep3) + r3[i]
        # an unsigned index: numba checks a signed one for a negative value (wraparound) on every write
        t = np.uint64(slot_to_texel[i]) * np.uint64(4)
        o[t] = s0
        o[t + np.uint64(1)] = s1
        o[t + np.uint64(2)] = s2
        o[t + np.uint64(3)] = s3


@njit(**_JIT)
def _store_pairs(packed, o, order, texel_bytes):
    """A layer's texels, packed in slot order in `packed` (bytes), stored at their places in `o` (the layer's texels
    as bytes, texture order; `order`: slot_to_texel), two at a time: slots 2k and 2k + 1 are the texels t and t + 1
    of one row, t even (transport.slot_to_texel: Morton order inside a 16 x 16 block, x its lowest bit), so a pair is
    one 4 or 8-byte store (two for 8-byte texels) where a texel at a time took one to four stores each. Every block
    of 256 slots lies alike about its first texel (blocks at multiples of 16 texels in both directions): a pair's
    place is its block's first texel plus its place in the first block, read from the first block's 256 entries
    (in cache) rather than from `order`'s 8 bytes a slot."""
    first = order[:256]
    at0 = first[0]
    blocks = order.shape[0] // 256
    if texel_bytes == 2:
        src = packed.view(np.uint32)
        dst = o.view(np.uint32)
        for b in range(blocks):
            base = order[b * 256] - at0
            s = src[b * 128:(b + 1) * 128]
            for k in range(128):
                dst[np.uint64(base + first[2 * k]) >> np.uint64(1)] = s[k]
        return
    src64 = packed.view(np.uint64)
    dst64 = o.view(np.uint64)
    if texel_bytes == 4:
        for b in range(blocks):
            base = order[b * 256] - at0
            s = src64[b * 128:(b + 1) * 128]
            for k in range(128):
                dst64[np.uint64(base + first[2 * k]) >> np.uint64(1)] = s[k]
    elif texel_bytes == 8:  # norm16x4, f16x4: two words of 8 bytes a pair
        for b in range(blocks):
            base = order[b * 256] - at0
            s = src64[b * 256:(b + 1) * 256]
            for k in range(128):
                at = np.uint64(base + first[2 * k])
                dst64[at] = s[2 * k]
                dst64[at + np.uint64(1)] = s[2 * k + 1]
    else:  # wider texels (none of FIELD_LAYOUTS' packed paths): texel_bytes // 8 words of 8 bytes a texel
        per = texel_bytes // 8
        for b in range(blocks):
            base = order[b * 256] - at0
            for k in range(128):
                at = np.uint64((base + first[2 * k]) * per)
                for w in range(2 * per):
                    dst64[at + np.uint64(w)] = src64[(b * 256 + 2 * k) * per + w]


@njit(**_JIT)
def fields1_kernel(raw, planes_at, params_at, n, layers, words, fields, modes, slot_to_texel, work, out):
    """Decode a fields1 content's layers into `out` (its texel words, native order, texture order); `work` is
    (fields, n) int64 scratch; `fields` and `modes` are transport._kernel_args' tables (few arguments: each one
    costs the call a few hundred nanoseconds). A field at a time over the slots (loops without branches inside,
    which the compiler keeps tight: a slot at a time over tables of fields ran no faster than numpy), then the
    predictions a block at a time, then each texel's words packed and written to its texel."""
    nbytes, plane_index, masks, shifts = fields[0], fields[1], fields[2], fields[4]
    deltas, refs, param_index = modes[0], modes[1], modes[2]
    nf = nbytes.shape[0]
    blocks = n // 256
    plane_bytes = plane_index[nf - 1] + nbytes[nf - 1]
    pos = planes_at
    words32 = words == 4 and nf == 4 and plane_bytes == 16  # f32x4: four 32-bit fields, a word each
    for k in range(layers * nf):
        words32 = words32 and refs[k] < 0  # (the header check refuses a predicted field wider than 16 bits)
    if words32:
        for layer in range(layers):
            _f32x4_layer(raw, pos, n, deltas[layer * 4:layer * 4 + 4], work, slot_to_texel,
                         out[layer * n * 4:(layer + 1) * n * 4])
            pos += n * 16
        return
    packed = np.empty_like(out[:n * words])  # a layer's texels in slot order (the packing below)
    for layer in range(layers):
        mode = layer * nf
        for f in range(nf):
            base = pos + plane_index[f] * n
            nb = nbytes[f]
            m = masks[f]
            row = work[f]
            delta = deltas[mode + f] != 0
            s = np.int64(0)
            # each byte plane as its own slice, read by the loop's index alone: with raw[base + i] the compiled loop
            # checked every read for a negative index (numba's wraparound), which took 1.5-2x the time of the whole
            # kernel on small payloads (BENCHMARKS.md, "Decode speed"; issue 32)
            if nb == 1:  # fields of up to 8 bits: the byte itself, no zigzag
                b0 = raw[base:base + n]
                if delta:
                    for i in range(n):
                        s += np.int64(b0[i])
                        row[i] = s & m
                else:
                    for i in range(n):
                        row[i] = np.int64(b0[i]) & m
            elif nb == 2:
                b0 = raw[base:base + n]
                b1 = raw[base + n:base + 2 * n]
                if delta:
                    for i in range(n):
                        c = np.int64(b0[i]) | (np.int64(b1[i]) << 8)
                        row[i] = (c >> 1) ^ -(c & 1)
                    for i in range(n):
                        s += row[i]
                        row[i] = s & m
                else:
                    for i in range(n):
                        c = np.int64(b0[i]) | (np.int64(b1[i]) << 8)
                        row[i] = ((c >> 1) ^ -(c & 1)) & m
            elif nb == 4:  # 32-bit fields (f32x4): |residual| < 2^31, so int64 sums of 2^25 slots cannot overflow
                b0 = raw[base:base + n]
                b1 = raw[base + n:base + 2 * n]
                b2 = raw[base + 2 * n:base + 3 * n]
                b3 = raw[base + 3 * n:base + 4 * n]
                if delta:
                    for i in range(n):
                        c = (np.int64(b0[i]) | (np.int64(b1[i]) << 8) | (np.int64(b2[i]) << 16)
                             | (np.int64(b3[i]) << 24))
                        row[i] = (c >> 1) ^ -(c & 1)
                    for i in range(n):
                        s += row[i]
                        row[i] = s & m
                else:
                    for i in range(n):
                        c = (np.int64(b0[i]) | (np.int64(b1[i]) << 8) | (np.int64(b2[i]) << 16)
                             | (np.int64(b3[i]) << 24))
                        row[i] = ((c >> 1) ^ -(c & 1)) & m
            else:
                for i in range(n):
                    c = np.int64(0)
                    for k in range(nb):
                        c |= np.int64(raw[base + k * n + i]) << (8 * k)
                    r = (c >> 1) ^ -(c & 1)
                    if delta:
                        s = (s + r) & 0xFFFFFFFF
                        r = s
                    row[i] = r & m
        for f in range(nf):
            ref = refs[mode + f]
            if ref >= 0:
                p = params_at + param_index[mode + f] * 3 * blocks
                m = masks[f]
                row = work[f]
                anchor = work[ref]
                for b in range(blocks):
                    slope = np.int64(raw[p + b])
                    if slope >= 128:
                        slope -= 256
                    intercept = np.int64(raw[p + blocks + 2 * b]) | (np.int64(raw[p + blocks + 2 * b + 1]) << 8)
                    if intercept >= 32768:
                        intercept -= 65536
                    bias = 64 * intercept + 32
                    for i in range(b * 256, (b + 1) * 256):
                        row[i] = (row[i] + ((slope * anchor[i] + bias) >> 6)) & m
        first = layer * n
        # the texels' packing spelt out for each layout of FIELD_LAYOUTS (about a fifth of the kernel's time on
        # 16-bit and four-field formats against the general loops below them; issue 32): packed in slot order into
        # `packed` (loops the compiler vectorises), then stored two texels at a time (_store_pairs: a pair of slots
        # is a pair of texels side by side). A texel at a time, the stores to scattered places were about half of
        # the kernel's time on the SH bands' norm565 (issue 32, dec32).
        if words == 1 and nf == 3:  # fields packed in one word (norm11, norm9x3, norm565)
            s1, s2 = shifts[1], shifts[2]
            r0, r1, r2 = work[0, :n], work[1, :n], work[2, :n]
            p = packed[:n]
            for i in range(n):
                p[i] = r0[i] | (r1[i] << s1) | (r2[i] << s2)
            _store_pairs(p.view(np.uint8), out[first:first + n].view(np.uint8), slot_to_texel, out.itemsize)
        elif words == 1 and nf == 4:  # norm10_2
            s1, s2, s3 = shifts[1], shifts[2], shifts[3]
            r0, r1, r2, r3 = work[0, :n], work[1, :n], work[2, :n], work[3, :n]
            p = packed[:n]
            for i in range(n):
                p[i] = r0[i] | (r1[i] << s1) | (r2[i] << s2) | (r3[i] << s3)
            _store_pairs(p.view(np.uint8), out[first:first + n].view(np.uint8), slot_to_texel, out.itemsize)
        elif words == 1 and nf == 1:  # index16
            r0 = work[0, :n]
            p = packed[:n]
            for i in range(n):
                p[i] = r0[i]
            _store_pairs(p.view(np.uint8), out[first:first + n].view(np.uint8), slot_to_texel, out.itemsize)
        elif words == 1:
            for i in range(n):
                v = np.int64(0)
                for f in range(nf):
                    v |= work[f, i] << shifts[f]
                out[first + slot_to_texel[i]] = v
        elif words == 4 and nf == 4:  # one field a word (norm8x4, norm16x4, f16x4): a texel's four at once
            r0, r1, r2, r3 = work[0, :n], work[1, :n], work[2, :n], work[3, :n]
            p = packed[:4 * n]
            for i in range(n):
                p[4 * i] = r0[i]
                p[4 * i + 1] = r1[i]
                p[4 * i + 2] = r2[i]
                p[4 * i + 3] = r3[i]
            _store_pairs(p.view(np.uint8), out[first * 4:(first + n) * 4].view(np.uint8), slot_to_texel,
                         4 * out.itemsize)
        else:  # one field a word
            for f in range(nf):
                row = work[f]
                for i in range(n):
                    out[(first + slot_to_texel[i]) * words + f] = row[i]
        pos += n * plane_bytes


@njit(**_JIT)
def unshuffle_into(unit, count, element, out):
    """format.md 5.1's inverse byte shuffle of `count` elements of `element` bytes: byte k of element i is
    unit[k * count + i]. Written in order, read from `element` streams (about twice as fast as the other way); the
    common element sizes spelt out, which the compiler vectorises: 0.08 ns a byte where the loop over a run-time
    element size took 1.4-2.8 (a city payload's 76 KB of units, 2-core VM at load 6)."""
    if element == 4:
        for i in range(count):
            out[4 * i] = unit[i]
            out[4 * i + 1] = unit[count + i]
            out[4 * i + 2] = unit[2 * count + i]
            out[4 * i + 3] = unit[3 * count + i]
    elif element == 2:
        for i in range(count):
            out[2 * i] = unit[i]
            out[2 * i + 1] = unit[count + i]
    else:
        for i in range(count):
            for k in range(element):
                out[i * element + k] = unit[k * count + i]


@njit(**_JIT)
def unshuffle_kernel(unit, element, out):
    """format.md 5.1's inverse byte shuffle of one unit (unshuffle_into)."""
    unshuffle_into(unit, unit.shape[0] // element, element, out)


@njit(**_JIT)
def fields1_many_kernel(raw, table, words, fields, modes, orders, work, out):
    """fields1_kernel over many sections of one format and layer count lying in `raw` (a group's decompressed
    payloads), one row of `table` a section: (where its byte planes start, where its parameters start, slots, where
    its slot_to_texel starts in `orders`, where its texels start in `out`, how many words they are, its row of
    `modes`). One call for a plane of a whole group: the dispatch of a call (a few microseconds with these many
    arguments) and the Python around it were most of a small payload's decode (issue 32)."""
    for s in range(table.shape[0]):
        n = table[s, 2]
        first = table[s, 4]
        fields1_kernel(raw, table[s, 0], table[s, 1], n, table[s, 5] // (n * words),
                       words, fields, modes[table[s, 6]], orders[table[s, 3]:table[s, 3] + n], work,
                       out[first:first + table[s, 5]])


@njit(**_JIT)
def unshuffle_many_kernel(raw, table, element, out):
    """unshuffle_kernel over many units lying in `raw`, one row of `table` a unit (where it starts, its element
    count), their bytes one unit after the other in `out`."""
    first = 0
    for u in range(table.shape[0]):
        at, count = table[u, 0], table[u, 1]
        unshuffle_into(raw[at:at + count * element], count, element, out[first:first + count * element])
        first += count * element


@njit(**_JIT)
def floats_outside(words, one, negative_zero):
    """Whether any of `words` (float texels' bits as unsigned integers) leaves [0, 1] (format.md 4.2): bits above
    those of 1.0 other than -0.0's (NaN, inf and negatives lie above, as container._check_float_texels reads them).
    An OR over the words, no early exit: the loop vectorises (the words were just written, still in cache)."""
    bad = False
    for i in range(words.shape[0]):
        v = words[i]
        bad |= (v > one) & (v != negative_zero)
    return bad


@njit(**_JIT)
def ranges_outside(values, k, low, high):
    """Whether `values` (float32: chunks of `k` minimums then `k` maximums) fail ranges_kernel's checks: a value not
    finite, a minimum above its maximum, or one outside [low, high] (compared as float64, as ranges_kernel does).
    Also True where the values are not whole chunks or there are none (the caller's own check decides those)."""
    if k <= 0 or values.shape[0] == 0 or values.shape[0] % (2 * k):
        return True
    for c in range(0, values.shape[0], 2 * k):
        for j in range(k):
            lo = np.float64(values[c + j])
            hi = np.float64(values[c + k + j])
            if not (math.isfinite(lo) and math.isfinite(hi) and low <= lo and lo <= hi and hi <= high):
                return True
    return False


_TWO_TO_MINUS_24 = 2.0 ** -24  # a half's subnormal step
_TWO_TO_MINUS_25 = 2.0 ** -25  # (1024 + mantissa) x 2^exponent x this: a normal half's value


@njit(**_JIT)
def half_value(h):
    """An IEEE 754 half's bits `h` (uint16) as its exact float64 value (numba has no float16 arithmetic): +-inf for
    the infinities, NaN for NaNs. The power of two by a shift, not `**` (a pow call a value: that made medium's
    float16 range checks cost more in the kernel than they saved in Python)."""
    sign = -1.0 if h & 0x8000 else 1.0
    exponent = np.int64((h >> 10) & 0x1F)
    mantissa = np.float64(h & 0x3FF)
    if exponent == 0x1F:
        return sign * math.inf if mantissa == 0 else math.nan
    if exponent == 0:
        return sign * mantissa * _TWO_TO_MINUS_24
    return sign * (1024.0 + mantissa) * np.float64(np.int64(1) << exponent) * _TWO_TO_MINUS_25


@njit(**_JIT)
def halves_outside(values, k, low, high):
    """ranges_outside of float16 ranges (their bits as uint16), each value compared as its exact float64, as
    container._ranges_ok compares them (float16 widened to float32, exact, then to float64)."""
    if k <= 0 or values.shape[0] == 0 or values.shape[0] % (2 * k):
        return True
    for c in range(0, values.shape[0], 2 * k):
        for j in range(k):
            lo = half_value(values[c + j])
            hi = half_value(values[c + k + j])
            if not (math.isfinite(lo) and math.isfinite(hi) and low <= lo and lo <= hi and hi <= high):
                return True
    return False


@njit(**_JIT)
def whole_kernel(raw, rows, fields, modes, orders, work, out8, out16, out32, outf32, units, spans, bounds):
    """A whole payload's, or a whole group's, fields1 sections of every format and shuffled units in one call
    (transport.use_whole_kernel): per row of `rows` fields1_kernel into the out view of its word size (out8, out16,
    out32: views of one buffer), with its columns of `fields` and `modes`; then per row of `units` unshuffle_kernel's
    bytes into out8. One call that releases the interpreter lock for all of it, where a plane at a time took one or
    two calls a plane, each taking the lock back after it (issue 38's fly-through; issue 32's small payloads).

    Then each row's and unit's check (transport.CHECK_*: float texels in [0, 1]) and each span's (a plane's ranges
    finite, ordered and inside bounds[code], float32 or float16 by bounds[code, 2]) on the values just written,
    while they are in cache; returns the CHECK_FAILED_* bits of the checks that failed (0: all passed), and the
    caller checks as it would without the kernel only then (issue 32: those checks were a numpy call a plane a run
    after the call)."""
    status = 0
    for s in range(rows.shape[0]):
        n, first, length = rows[s, 2], rows[s, 4], rows[s, 5]
        f0, nf, m0, nm, words = rows[s, 6], rows[s, 7], rows[s, 8], rows[s, 9], rows[s, 10]
        layers = length // (n * words)
        order = orders[rows[s, 3]:rows[s, 3] + n]
        if rows[s, 11] == 1:
            fields1_kernel(raw, rows[s, 0], rows[s, 1], n, layers, words, fields[:, f0:f0 + nf],
                           modes[:, m0:m0 + nm], order, work, out8[first:first + length])
        elif rows[s, 11] == 2:
            fields1_kernel(raw, rows[s, 0], rows[s, 1], n, layers, words, fields[:, f0:f0 + nf],
                           modes[:, m0:m0 + nm], order, work, out16[first:first + length])
        else:
            fields1_kernel(raw, rows[s, 0], rows[s, 1], n, layers, words, fields[:, f0:f0 + nf],
                           modes[:, m0:m0 + nm], order, work, out32[first:first + length])
        check = rows[s, 12]
        if check == 1:  # CHECK_F32
            if rows[s, 11] != 4 or floats_outside(out32[first:first + length], np.uint32(0x3F800000),
                                                  np.uint32(0x80000000)):
                status |= 1
        elif check == 2:  # CHECK_F16
            if rows[s, 11] != 2 or floats_outside(out16[first:first + length], np.uint16(0x3C00),
                                                  np.uint16(0x8000)):
                status |= 1
    for u in range(units.shape[0]):
        count, element, at = units[u, 1], units[u, 2], units[u, 3]
        size = count * element
        unshuffle_into(raw[units[u, 0]:units[u, 0] + size], count, element, out8[at:at + size])
        check = units[u, 4]
        if check == 1:  # CHECK_F32: whole aligned words only (else the caller's check)
            if at % 4 or size % 4 or floats_outside(out32[at // 4:(at + size) // 4], np.uint32(0x3F800000),
                                                    np.uint32(0x80000000)):
                status |= 1
        elif check == 2:  # CHECK_F16
            if at % 2 or size % 2 or floats_outside(out16[at // 2:(at + size) // 2], np.uint16(0x3C00),
                                                    np.uint16(0x8000)):
                status |= 1
    for p in range(spans.shape[0]):  # a plane's ranges in a row: inside bounds[check], float32 or float16 (its [2])
        at, size, half, check = spans[p, 0], spans[p, 1], spans[p, 2], spans[p, 3]
        if bounds[check, 2] == 4:
            if at % 4 or size % 4 or ranges_outside(outf32[at // 4:(at + size) // 4], half, bounds[check, 0],
                                                    bounds[check, 1]):
                status |= 2
        elif at % 2 or size % 2 or halves_outside(out16[at // 2:(at + size) // 2], half, bounds[check, 0],
                                                  bounds[check, 1]):
            status |= 2
    return status


def _spread_table() -> np.ndarray:
    """morton_kernel's byte table: _SPREAD[r, v] is byte value v of a morton key whose bit 0 lies at key bit p with
    p % 3 == r, split into x, y and z (bit j of v is key bit p + j: component (r + j) % 3, its bit (r + j) // 3) as
    a texel's three 16-bit lanes. Key byte b (b = 0..5) starts at key bit 8b = 3q + r: its lanes are
    _SPREAD[r, byte] << q (q at most 13 and (r + 7) // 3 at most 3: nothing crosses into the next lane). Six lookups
    in a 6 KB table a slot where keyed.compact_bits' shifts and masks took three times five steps (issue 32)."""
    table = np.zeros((3, 256), np.uint64)
    for r in range(3):
        for v in range(256):
            t = 0
            for j in range(8):
                if v >> j & 1:
                    t |= 1 << (16 * ((r + j) % 3) + (r + j) // 3)
            table[r, v] = t
    return table


_SPREAD = _spread_table()


@njit(**_JIT)
def morton_kernel(stored, slots, slot_to_texel, out):
    """keyed.unfilter_morton's bytes (format.md 5.4) in one pass (keyed.use_morton_kernel): each slot's key
    difference from its six byte planes, the running sum modulo 2^64 (only its low 48 bits are read), the key split
    back into x, y and z, the fourth component from its two planes, the texel written at its place in texture
    order. All arithmetic in uint64 (numba would take a mix with signed integers to floats)."""
    key = np.uint64(0)
    # each byte plane as its own slice, read by the loop's index alone: stored[b * slots + s] made every compiled
    # read check for a negative index (numba's wraparound), as fields1_kernel's reads did (issue 32)
    b0, b1, b2 = stored[0:slots], stored[slots:2 * slots], stored[2 * slots:3 * slots]
    b3, b4, b5 = stored[3 * slots:4 * slots], stored[4 * slots:5 * slots], stored[5 * slots:6 * slots]
    w0, w1 = stored[6 * slots:7 * slots], stored[7 * slots:8 * slots]
    for s in range(slots):
        key += (np.uint64(b0[s]) | (np.uint64(b1[s]) << np.uint64(8)) | (np.uint64(b2[s]) << np.uint64(16))
                | (np.uint64(b3[s]) << np.uint64(24)) | (np.uint64(b4[s]) << np.uint64(32))
                | (np.uint64(b5[s]) << np.uint64(40)))
        w = np.uint64(w0[s]) | (np.uint64(w1[s]) << np.uint64(8))
        t = _SPREAD[0, key & np.uint64(0xFF)]
        t |= _SPREAD[2, (key >> np.uint64(8)) & np.uint64(0xFF)] << np.uint64(2)
        t |= _SPREAD[1, (key >> np.uint64(16)) & np.uint64(0xFF)] << np.uint64(5)
        t |= _SPREAD[0, (key >> np.uint64(24)) & np.uint64(0xFF)] << np.uint64(8)
        t |= _SPREAD[2, (key >> np.uint64(32)) & np.uint64(0xFF)] << np.uint64(10)
        t |= _SPREAD[1, (key >> np.uint64(40)) & np.uint64(0xFF)] << np.uint64(13)
        out[slot_to_texel[s]] = t | (w << np.uint64(48))


@njit(**_JIT)
def ranges_kernel(pairs, low, high):
    """container._ranges_ok's answer in one pass (container.use_ranges_kernel): every minimum and maximum of
    `pairs` ((chunks, 2, k) float32) finite, each minimum at most its maximum, all inside [low, high]. A NaN fails
    every comparison; the float32 values compared as float64, as Python's floats compare them."""
    for c in range(pairs.shape[0]):
        lows = pairs[c, 0]
        highs = pairs[c, 1]
        for k in range(lows.shape[0]):
            lo = np.float64(lows[k])
            hi = np.float64(highs[k])
            if not (math.isfinite(lo) and math.isfinite(hi) and low <= lo and lo <= hi and hi <= high):
                return False
    return True


def warm_up(whole: bool = True) -> None:
    """Compile (or load from the cache) the kernel for the argument types of real calls: a content as a writable
    buffer's view (a payload's kept buffer) and as read-only bytes, into texels of 1, 2 and 4-byte words. Each kernel
    is handed to format.transport / keyed for its calls and the one before put back, while the decode threads of
    the process may be decoding with the numpy path: every call site there reads its kernel once (a thread that
    read a kernel and then called the module's, put back to None meanwhile, failed with "'NoneType' object is not
    callable" and its view never converged: pagebudget31). `whole`: the whole kernel too."""
    previous = transport.use_fields_kernel(fields1_kernel)
    try:
        for fmt in ("norm8x4", "norm565", "norm11"):
            bits = transport.field_bits(fmt)
            content = bytes([transport.FIELDS_VERSION]) + bytes([transport.MODE_DELTA] * len(bits)) \
                + bytes(256 * sum((b + 7) // 8 for b in bits))
            transport.unfilter_fields(content, fmt, 16, 16, 1)
            transport.unfilter_fields(np.frombuffer(content, np.uint8).copy(), fmt, 16, 16, 1)
    finally:
        transport.use_fields_kernel(previous)
    previous = transport.use_batch_kernels(fields1_many_kernel, unshuffle_many_kernel)
    try:
        for fmt in ("norm8x4", "norm565", "norm11"):
            bits = transport.field_bits(fmt)
            content = bytes([transport.FIELDS_VERSION]) + bytes([transport.MODE_DELTA] * len(bits)) \
                + bytes(256 * sum((b + 7) // 8 for b in bits))
            raw = np.frombuffer(content * 2, np.uint8).copy()
            transport.unfilter_fields_at(raw, fmt, 1, [(0, len(content), 16, 16), (len(content), len(content), 16, 16)])
        transport.unshuffle_at(np.zeros(32, np.uint8), [(0, 16), (16, 16)], 4)
    finally:
        transport.use_batch_kernels(*previous)
    if whole:
        _warm_up_whole()
    previous = keyed.use_morton_kernel(morton_kernel)
    try:  # a content in a payload's kept buffer (a writable view) and as read-only bytes
        content = np.zeros(8 * 256, np.uint8)
        keyed.unfilter_morton(content, 16, 16)
        keyed.unfilter_morton(content.tobytes(), 16, 16)
    finally:
        keyed.use_morton_kernel(previous)
    pairs = np.zeros((1, 2, 3), np.float32)  # ranges in a kept buffer or a fresh array, and read-only ones
    read_only_pairs = pairs.copy()
    read_only_pairs.setflags(write=False)
    for p in (pairs, read_only_pairs):
        ranges_kernel(p, -1.0, 1.0)
    unit = np.zeros(16, np.uint8)
    read_only = unit.copy()
    read_only.setflags(write=False)
    for u in (unit, read_only):
        unshuffle_kernel(u, 4, np.empty(16, np.uint8))


def _warm_up_whole() -> None:
    """warm_up's whole kernel."""
    previous = transport.use_whole_kernel(whole_kernel)
    try:  # sections of every word size and a unit in one call: the one argument type of every call
        parts, sections, at = [], [], 0
        for fmt in ("norm8x4", "norm565", "norm11"):
            bits = transport.field_bits(fmt)
            content = bytes([transport.FIELDS_VERSION]) + bytes([transport.MODE_DELTA] * len(bits)) \
                + bytes(256 * sum((b + 7) // 8 for b in bits))
            at += -at % 16
            parts.append(bytes(at - sum(len(p) for p in parts)) + content)
            sections.append((fmt, 1, at, len(content), 16, 16))
            at += len(content)
        raw = np.frombuffer(b"".join(parts) + bytes(32), np.uint8).copy()
        transport.unfilter_whole(raw, sections, [(at, 16, 4), (at + 16, 16, 2)])
    finally:
        transport.use_whole_kernel(previous)


def install() -> None:
    """format.transport decodes fields1 with the compiled kernel from now on (in every thread of this process).
    Warmed up first, so that the decode threads keep the numpy path until every kernel is loaded (handed in first,
    the first frame's decode waited for the loads: 1M first frame 0.086 -> 0.157 s on the GPU machine, r23)."""
    whole = os.environ.get(WHOLE_ENV, "1") != "0"
    warm_up(whole)
    transport.use_fields_kernel(fields1_kernel)
    transport.use_unshuffle_kernel(unshuffle_kernel)
    transport.use_batch_kernels(fields1_many_kernel, unshuffle_many_kernel)
    keyed.use_morton_kernel(morton_kernel)
    container.use_ranges_kernel(ranges_kernel)
    # SPLATSTREAM_DECODE_WHOLE=0: a plane at a time as before the whole kernel (for A/B runs of the fly-through:
    # the whole kernel gives the lock up twice a payload instead of about five times, for 10-20 us more of Python
    # holding it; BENCHMARKS.md, "Decode speed")
    transport.use_whole_kernel(whole_kernel if whole else None)


def uninstall() -> None:
    """Back to the numpy path."""
    transport.use_fields_kernel(None)
    transport.use_unshuffle_kernel(None)
    transport.use_batch_kernels(None, None)
    transport.use_whole_kernel(None)
    keyed.use_morton_kernel(None)
    container.use_ranges_kernel(None)
