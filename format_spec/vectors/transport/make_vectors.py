"""Regenerate the `fields1` test vectors (format_spec/format.md 5.2 and 8).

    python format_spec/vectors/transport/make_vectors.py

For each texel format, a 32x16 section of 2 layers with smooth, channel-correlated values; layer 0 is coded with
modes chosen by hand so every mode occurs (plain, DELTA, REF, REF + DELTA), layer 1 with the encoder's own choice.
Writes <format>.fields1.bin (the stored content), <format>.texels.bin (the GPU bytes it decodes to) and
vectors.json (geometry and modes).
"""
from __future__ import annotations

import json
import os

import numpy as np

from splatstream.format.transport import (
    FIELD_LAYOUTS,
    choose_modes,
    field_bits,
    fields_content,
    slot_to_texel,
    split_layer,
)

HERE = os.path.dirname(os.path.abspath(__file__))
WIDTH, HEIGHT, LAYERS = 32, 16, 2
# appended formats come last, so the earlier ones keep their rng draws and bytes
FORMATS = ("norm11", "norm10_2", "norm565", "norm8x4", "f16x4", "index16", "norm16x4", "norm9x3")


def texels(fmt: str, rng: np.random.Generator) -> np.ndarray:
    """2 layers of texels whose fields follow a shared random walk along the slot order."""
    dtype, _, layout = FIELD_LAYOUTS[fmt]
    bits = field_bits(fmt)
    n = WIDTH * HEIGHT
    out = []
    for _ in range(LAYERS):
        walk = np.cumsum(rng.integers(-3, 4, n))
        fields = [((walk * (1 << b) // 64 + rng.integers(0, 3, n) * (i + 1)) % (1 << b)).astype(np.uint64)
                  for i, b in enumerate(bits)]
        words = len(bits) // len(layout)
        word = np.zeros((n, words), np.uint64)
        k = 0
        for w in range(words):
            for shift, _ in layout:
                word[:, w] |= fields[k] << np.uint64(shift)
                k += 1
        layer = np.empty((n, words), np.dtype(dtype))
        layer[slot_to_texel(WIDTH, HEIGHT)] = word.astype(np.dtype(dtype))
        out.append(layer.reshape(-1).view(np.uint8))
    return np.concatenate(out)


def hand_modes(fmt: str) -> list[tuple[bool, int | None]]:
    nf = len(field_bits(fmt))
    if nf == 1:
        return [(True, None)]
    if fmt in ("norm8x4", "f16x4", "norm16x4"):
        return [(False, 1), (True, None), (True, 1), (False, None)]
    modes = [(False, 1), (True, None), (True, 1)]
    return modes + [(False, None)] * (nf - 3)


def main() -> None:
    rng = np.random.default_rng(15)
    index = {}
    for fmt in FORMATS:
        data = texels(fmt, rng)
        unit = data.size // LAYERS
        auto = choose_modes(split_layer(data[unit:], fmt, WIDTH, HEIGHT), field_bits(fmt))
        modes = [hand_modes(fmt), auto]
        content, _ = fields_content(data, fmt, WIDTH, HEIGHT, LAYERS, modes)
        with open(os.path.join(HERE, f"{fmt}.fields1.bin"), "wb") as f:
            f.write(content)
        with open(os.path.join(HERE, f"{fmt}.texels.bin"), "wb") as f:
            f.write(data.tobytes())
        index[fmt] = {"width": WIDTH, "height": HEIGHT, "layers": LAYERS, "stored_bytes": len(content),
                      "texel_bytes": int(data.size),
                      "modes": [[{"delta": d, "ref": r} for d, r in layer] for layer in modes]}
    with open(os.path.join(HERE, "vectors.json"), "w") as f:
        json.dump(index, f, indent=1)
        f.write("\n")


if __name__ == "__main__":
    main()
