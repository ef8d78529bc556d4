"""What the decode side hands to the GPU pool for one tile. Pure: numpy only, no GL (the streaming client's decode
workers build these off the render thread; client_gl.scene builds them from a store).

    planes = decode_payload(data, tile.groups["base"], "base", source)   # splatstream.format.decode
    tile = TileData(splats, planes, host_mirror(planes, splats))         # -> pool.join(tile_id, tile)
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from splatstream.errors import UsageError
from splatstream.format.codec import EncodedPlane, decode_plane


@dataclass(frozen=True)
class HostMirror:
    """Per-splat values the CPU-sort path culls and sorts with: decoded centres, opacity (after the sigmoid, clipped
    to [0, 1]) and the largest log scale. Indexed by splat: a tile's splats, or a pool's global splat ids."""

    positions: np.ndarray  # (N, 3) float32
    opacity: np.ndarray  # (N,) float32
    max_log_scale: np.ndarray  # (N,) float32

    def __len__(self) -> int:
        return len(self.opacity)


def host_mirror(planes: Mapping[str, EncodedPlane], splats: int) -> HostMirror:
    """The host mirror of a tile from its base planes (position, color, scale), decoded as the shaders decode them."""
    missing = {"position", "color", "scale"} - set(planes)
    if missing:
        raise UsageError(f"a host mirror needs the base planes; missing {', '.join(sorted(missing))}")
    return HostMirror(decode_plane(planes["position"], splats)[:, 0],
                      np.clip(decode_plane(planes["color"], splats)[:, 0, 3], 0.0, 1.0),
                      decode_plane(planes["scale"], splats)[:, 0].max(axis=1))


@dataclass
class TileData:
    """One tile's planes as the file stores them (texels still encoded), by plane name.

    `planes` holds the base planes (position, rotation, scale, color) and optionally SH bands joined with the base
    (sh1, sh2, .. in order; with an SH codebook the index plane sh_index, which stands for every codebook band).
    `mirror`: the host mirror, required by pools that keep one (the CPU-sort path)."""

    splats: int
    planes: dict[str, EncodedPlane]
    mirror: HostMirror | None = None

    def __post_init__(self) -> None:
        if self.splats < 0:
            raise UsageError(f"a tile of {self.splats} splats")
        if self.mirror is not None and len(self.mirror) != self.splats:
            raise UsageError(f"host mirror of {len(self.mirror)} splats for a tile of {self.splats}")
