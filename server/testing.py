"""Synthetic scene directories for the server's tests and benchmark: a valid manifest, random payloads named by
their SHA-256. Not real splat data (use splatstream.encoder for that)."""
from __future__ import annotations

import os
import random
from collections.abc import Sequence

from splatstream.atomic import atomic_directory
from splatstream.manifest import DATA_DIR, FORMAT_NAME, FORMAT_VERSION, MANIFEST_NAME, pack_manifest, payload_name
from splatstream.manifest import sha256_hex as _sha


def fake_manifest(name: str, groups: Sequence[tuple[str, int]], splats: int = 1000) -> dict:
    """A manifest with one tile whose groups are (sha256 hex, bytes)."""
    return {
        "format": FORMAT_NAME,
        "version": list(FORMAT_VERSION),
        "name": name,
        "splats": splats,
        "sh_degree": 0,
        "preset": "medium",
        "bounds": {"min": [-1.0, -1.0, -1.0], "max": [1.0, 1.0, 1.0]},
        "tiles": [{
            "id": 0, "level": 0, "children": [], "splats": splats,
            "groups": {f"g{i}": {"file": payload_name(sha), "bytes": n, "sha256": sha}
                       for i, (sha, n) in enumerate(groups)},
        }],
    }


def write_fake_scene(directory: str | os.PathLike, sizes: Sequence[int], seed: int = 0, name: str | None = None,
                     atomic: bool = True) -> list[str]:
    """Create (or atomically replace) a scene directory with payloads of the given sizes; their sha256 hexes."""
    rng = random.Random(seed)
    directory = os.fspath(directory)

    def fill(target: str) -> list[str]:
        os.makedirs(os.path.join(target, DATA_DIR), exist_ok=True)
        groups = []
        for n in sizes:
            data = rng.randbytes(n)
            sha = _sha(data)
            with open(os.path.join(target, payload_name(sha)), "wb") as f:
                f.write(data)
            groups.append((sha, n))
        m = fake_manifest(name or os.path.basename(directory), groups)
        with open(os.path.join(target, MANIFEST_NAME), "wb") as f:
            f.write(pack_manifest(m))
        return [sha for sha, _ in groups]

    if not atomic:
        return fill(directory)
    with atomic_directory(directory) as tmp:
        return fill(tmp)
