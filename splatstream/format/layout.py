"""Splat order and texture layout (format_spec/format.md, "Order" and "Texture layout").

Splats are sorted by 3D Morton code over the bounds of their centres and cut into chunks of 256. Each
chunk is one 16x16 block of every attribute texture; inside the block splat j sits at the 2D Morton
decode of j (x from the even bits, y from the odd bits), so 4x4 BC blocks hold spatial neighbours.
"""
from __future__ import annotations

import functools

import numpy as np

CHUNK_SIZE = 256
ALIGN = 16  # payload sections start at multiples of this many bytes (format.md 5)
BLOCK = 16  # a chunk is a BLOCK x BLOCK texel square
MAX_BLOCKS_PER_ROW = 128  # texture width at most 2048 texels
MAX_BLOCK_ROWS = 1024  # texture height at most 16384 texels, the GL 4.3 guaranteed minimum of GL_MAX_TEXTURE_SIZE
MORTON_BITS = 21


def _part1by2(v: np.ndarray) -> np.ndarray:
    """Insert two zero bits after each of the low 21 bits (Fabian Giesen's bit trick, 64-bit)."""
    x = v.astype(np.uint64) & np.uint64(0x1FFFFF)
    x = (x ^ (x << np.uint64(32))) & np.uint64(0x1F00000000FFFF)
    x = (x ^ (x << np.uint64(16))) & np.uint64(0x1F0000FF0000FF)
    x = (x ^ (x << np.uint64(8))) & np.uint64(0x100F00F00F00F00F)
    x = (x ^ (x << np.uint64(4))) & np.uint64(0x10C30C30C30C30C3)
    x = (x ^ (x << np.uint64(2))) & np.uint64(0x1249249249249249)
    return x


def morton_codes(positions: np.ndarray, lo: np.ndarray | None = None, hi: np.ndarray | None = None) -> np.ndarray:
    """63-bit 3D Morton codes of positions quantised to 21 bits per axis over [lo, hi]."""
    p = positions.astype(np.float64)
    lo = p.min(axis=0) if lo is None else np.asarray(lo, np.float64)
    hi = p.max(axis=0) if hi is None else np.asarray(hi, np.float64)
    extent = np.where(hi > lo, hi - lo, 1.0)
    scale = (2**MORTON_BITS - 1) / extent
    q = np.clip((p - lo) * scale, 0, 2**MORTON_BITS - 1).astype(np.uint32)
    return (_part1by2(q[:, 2]) << np.uint64(2)) | (_part1by2(q[:, 1]) << np.uint64(1)) | _part1by2(q[:, 0])


def morton_order(positions: np.ndarray) -> np.ndarray:
    """Permutation that sorts splats by 3D Morton code (stable, so equal codes keep input order)."""
    if len(positions) == 0:
        return np.zeros(0, np.int64)
    return np.argsort(morton_codes(positions), kind="stable")


def morton2d_decode_16(j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(x, y) inside a 16x16 block of in-chunk index j (0..255): x = even bits, y = odd bits."""
    j = np.asarray(j, np.uint32)
    x = (j & 1) | ((j >> 1) & 2) | ((j >> 2) & 4) | ((j >> 3) & 8)
    y = ((j >> 1) & 1) | ((j >> 2) & 2) | ((j >> 3) & 4) | ((j >> 4) & 8)
    return x, y


def texture_size(chunks: int) -> tuple[int, int]:
    """(width, height) in texels of a texture holding `chunks` 16x16 blocks.

    The row length (at most 128 blocks) is the one that leaves the fewest unused blocks, the widest on ties:
    GPU memory is allocated for the whole rectangle, so padding would count against bytes per splat.
    """
    chunks = max(1, chunks)
    if chunks > MAX_BLOCKS_PER_ROW * MAX_BLOCK_ROWS:
        raise ValueError(f"{chunks} chunks do not fit one texture ({MAX_BLOCKS_PER_ROW * MAX_BLOCK_ROWS} at most)")
    # At least 64 blocks per row (or all of them) keeps textures from becoming needlessly tall and thin.
    narrowest = max(-(-chunks // MAX_BLOCK_ROWS), min(chunks, 64))
    widest = min(chunks, MAX_BLOCKS_PER_ROW)
    cols = min(range(narrowest, widest + 1), key=lambda k: (-(-chunks // k) * k, -k))
    return cols * BLOCK, -(-chunks // cols) * BLOCK


def texel_coords(n: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Texel (x, y) of splats 0..n-1 in a texture of the given width."""
    i = np.arange(n, dtype=np.uint32)
    chunk = i // CHUNK_SIZE
    cols = width // BLOCK
    bx, by = morton2d_decode_16(i % CHUNK_SIZE)
    return (chunk % cols) * BLOCK + bx, (chunk // cols) * BLOCK + by


def to_texture(values: np.ndarray, width: int, height: int, fill: float = 0.0) -> np.ndarray:
    """Scatter per-splat rows (N, C) into an (H, W, C) image in chunk-block layout.

    Padding texels of the last chunk repeat the chunk's last splat rather than `fill` where possible,
    so BC blocks are not pulled toward an arbitrary value.
    """
    n, c = values.shape
    img = np.full((height, width, c), fill, dtype=values.dtype)
    x, y = texel_coords(n, width)
    img[y, x] = values
    pad_end = -(-n // CHUNK_SIZE) * CHUNK_SIZE
    if n and pad_end > n:
        px, py = texel_coords(pad_end, width)
        img[py[n:], px[n:]] = values[n - 1]
    return img


def from_texture(img: np.ndarray, n: int) -> np.ndarray:
    """Gather per-splat rows (N, C) back from an (H, W, C) image."""
    x, y = texel_coords(n, img.shape[1])
    return img[y, x]


# Position of in-chunk index j for each texel of a 16x16 block, row-major: _BLOCK_TO_INDEX[y * 16 + x] = j.
_bx, _by = morton2d_decode_16(np.arange(CHUNK_SIZE))
_BLOCK_TO_INDEX = np.empty(CHUNK_SIZE, np.int64)
_BLOCK_TO_INDEX[_by * BLOCK + _bx] = np.arange(CHUNK_SIZE)


def chunks_to_image(chunked: np.ndarray, width: int, height: int) -> np.ndarray:
    """(chunks, 256, C) per-chunk rows -> (H, W, C) image of 16x16 blocks; unused blocks are zero."""
    chunks, _, c = chunked.shape
    cols, rows = width // BLOCK, height // BLOCK
    grid = np.zeros((rows * cols, CHUNK_SIZE, c), chunked.dtype)
    grid[:chunks] = chunked[:, _BLOCK_TO_INDEX]
    return grid.reshape(rows, cols, BLOCK, BLOCK, c).transpose(0, 2, 1, 3, 4).reshape(height, width, c)


def image_to_chunks(img: np.ndarray, chunks: int) -> np.ndarray:
    """(H, W, C) image -> (chunks, 256, C) rows in in-chunk (Morton) order."""
    height, width, c = img.shape
    cols, rows = width // BLOCK, height // BLOCK
    grid = img.reshape(rows, BLOCK, cols, BLOCK, c).transpose(0, 2, 1, 3, 4).reshape(rows * cols, CHUNK_SIZE, c)
    out = np.empty((chunks, CHUNK_SIZE, c), img.dtype)
    out[:, _BLOCK_TO_INDEX] = grid[:chunks]
    return out


@functools.lru_cache(maxsize=16)
def chunk_texel_index(chunks: int, width: int) -> np.ndarray:
    """Flat texel index (y * width + x) of every splat slot 0..chunks*256-1, in splat order (read-only, cached:
    every plane and layer of a tile uses the same one)."""
    x, y = texel_coords(chunks * CHUNK_SIZE, width)
    index = y.astype(np.int64) * width + x
    index.setflags(write=False)
    return index


def order_within_chunks(order: np.ndarray, key: np.ndarray) -> np.ndarray:
    """Re-sort each chunk of 256 consecutive entries of `order` by `key` (indexed like the splats).

    Chunk membership is unchanged (chunks stay spatially compact); only the order inside a chunk changes, so
    the 16 consecutive splats of each 4x4 BC block are similar in `key`.
    """
    chunk = np.arange(len(order)) // CHUNK_SIZE
    return order[np.lexsort((key[order], chunk))]
