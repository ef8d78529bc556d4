import contextlib
import hashlib
import os
import pathlib
import signal
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
# The project's shared test data (larger real scenes, tools): SPLATSTREAM_SHARED, else ../shared beside the clone.
SHARED = pathlib.Path(os.environ.get("SPLATSTREAM_SHARED", ROOT.parent / "shared"))
REAL = SHARED / "data" / "real"
# Small real scenes bundled with the tests (provenance and licences: tests/data/real/README.md); the donut is the
# bundled sample scene itself.
BUNDLED = ROOT / "tests" / "data" / "real"
BUNDLED_ALIASES = {"donut_sh0_no_normals.ply": ROOT / "samples" / "donut.ply"}
REAL_PLYS = ["fruit_drops_sh3.ply", "lod_tile_sh3_zero_rest.ply", "donut_sh0_no_normals.ply"]


def real_path(name: str) -> pathlib.Path | None:
    """A real scene by its name in the shared data (data/real/NAME): the bundled copy when there is one, else the
    shared one; None when neither is here."""
    for path in (BUNDLED / name, BUNDLED_ALIASES.get(name), REAL / name):
        if path is not None and path.exists():
            return path
    return None


# Real scenes that are not bundled: biker.compressed.ply's licence (CC BY-NC-ND 4.0) forbids redistributing it
# here; the whole flowers_lod (22 MB; its coarsest unit is bundled) is too large. Test cases on them are collected
# only where the shared data holds them (`with_shared`), and the session header says which were left out, so a
# fresh clone runs every test it collects, with no data skip.
NOT_BUNDLED = ("biker.compressed.ply", "flowers_lod/lod-meta.json")


def with_shared(cases: list) -> list:
    """The parametrize cases whose scene (the case itself, or its first element) is here: bundled cases always,
    cases on NOT_BUNDLED scenes only where the shared data holds them."""
    def scene(case) -> str:
        return case if isinstance(case, str) else case[0]
    return [c for c in cases if scene(c) not in NOT_BUNDLED or real_path(scene(c)) is not None]


def pytest_report_header(config) -> str:
    missing = [n for n in NOT_BUNDLED if real_path(n) is None]
    if not missing:
        return f"shared test data: {SHARED} (every real scene here)"
    return (f"shared test data not found at {SHARED}: cases on {', '.join(missing)} (not bundled) are not "
            "collected; set SPLATSTREAM_SHARED to the directory holding data/real/ to run them")


def lod_probe_scene(n: int, seed: int, random_sh: bool):
    """A random SH1 Gaussians of n splats for the LOD probes' tests (bench/probe_lod_refine.py, probe_lod_distill.py):
    positions and colours N(0, 1), log-scales N(-3.5, 0.4), opacity logits N(0, 1.5), SH rest N(0, 1) or zero."""
    import numpy as np

    from splatstream.gaussians import Gaussians

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return Gaussians(rng.normal(size=(n, 3)).astype(np.float32), q.astype(np.float32),
                     rng.normal(-3.5, 0.4, size=(n, 3)).astype(np.float32),
                     rng.normal(0, 1.5, size=n).astype(np.float32), rng.normal(size=(n, 3)).astype(np.float32),
                     rng.normal(size=(n, 3, 3)).astype(np.float32) if random_sh else np.zeros((n, 3, 3), np.float32))


def load_bench(name: str):
    """bench/<name>.py (not a package: loaded from its file) as the module splatstream_bench_<name>, registered in
    sys.modules while it executes (dataclasses look their module up then); bench/ is put on sys.path first, since
    the probes import their neighbours (lod_vs_peers) by name."""
    import importlib.util

    bench = str(ROOT / "bench")
    if bench not in sys.path:
        sys.path.insert(0, bench)
    spec = importlib.util.spec_from_file_location(f"splatstream_bench_{name}", ROOT / "bench" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def real(name: str) -> pathlib.Path:
    """A real scene (see real_path), or skip the test saying what is missing and how to get it."""
    path = real_path(name)
    if path is None:
        pytest.skip(f"real scene {name} is not bundled with the tests and not in {REAL}: it is in the project's "
                    "shared test data (data/real/); set SPLATSTREAM_SHARED to the directory holding data/real/ "
                    "(default: ../shared beside the clone)")
    return path


def tree_digest(path) -> dict[str, str]:
    """Every file below `path` by its relative path: its SHA-256 (a scene directory compared byte for byte)."""
    out = {}
    for root, _, files in os.walk(path):
        for f in files:
            full = os.path.join(root, f)
            out[os.path.relpath(full, path)] = hashlib.sha256(open(full, "rb").read()).hexdigest()
    return out


def run_cli(*args: str, cwd=None) -> subprocess.CompletedProcess:
    """Run the installed CLI the way a user does (a separate process, no stdin)."""
    return subprocess.run([sys.executable, "-m", "cli", *map(str, args)], capture_output=True, text=True,
                          cwd=cwd, stdin=subprocess.DEVNULL, timeout=600)


@pytest.fixture(scope="session")
def gl_context():
    """The process's shared headless GL context (client_gl.offscreen.shared_context, also behind render_image), or
    skip the test where none opens. One context only: GL objects act on the current context."""
    pytest.importorskip("moderngl")
    from client_gl.offscreen import GLUnavailableError, shared_context

    try:
        return shared_context()
    except GLUnavailableError as exc:
        pytest.skip(f"no OpenGL context: {exc}")


@pytest.fixture(scope="session")
def gl_compute_context(gl_context):
    """The shared GL context where it has GL 4.3 compute shaders (else the test is skipped)."""
    if gl_context.version_code < 430:
        pytest.skip("no GL 4.3 compute shaders")
    return gl_context


def group_planes_of(scene_dir, manifest, tile, group: str) -> dict:
    """One payload group of a tile of an encoded scene, verified and unpacked (texels still encoded)."""
    from splatstream.format.decode import decode_payload
    from splatstream.store import DirectoryStore

    store = DirectoryStore(scene_dir)
    entry = tile.groups[group]
    return decode_payload(store.read_payload(entry), entry, group, store.payload_source(entry),
                          manifest.uses_codebook)


def read_manifest_dict(scene_dir) -> dict:
    """The raw manifest map, for tests that damage it on purpose; an unpaged 1.8 tile table (format.md 6.2) as the
    same scene's 1.7 tile maps (tile_maps), so that a test damages one tile's map as before. (The tile table's own
    damage: tests/test_manifest_table.py.) A 1.15 table's payloads, named by 16 bytes of their SHA-256, are linked
    under their whole SHA-256's names too, which the tile maps name."""
    import hashlib
    import os

    import msgpack

    scene_dir = pathlib.Path(scene_dir)
    d = tile_maps(msgpack.unpackb((scene_dir / "manifest.msgpack").read_bytes(), raw=False))
    renamed = False
    for t in d.get("tiles", []) if "paged" not in d else []:
        for e in t["groups"].values():
            if len(e["sha256"]) == 64:
                continue
            full = hashlib.sha256((scene_dir / e["file"]).read_bytes()).hexdigest()
            if not (scene_dir / "data" / f"{full}.bin").exists():
                os.link(scene_dir / e["file"], scene_dir / "data" / f"{full}.bin")
            e.update(sha256=full, file=f"data/{full}.bin")
            renamed = True
    if renamed:
        settle_totals(d)  # the longer names: bytes_on_disk again
    return d


def tile_maps(d: dict) -> dict:
    """A manifest map holding a tile table (1.8, or 1.12's compact one; unpaged) as the map the same scene has as
    version 1.7 (tile maps, bytes_on_disk settled); any other map as it is."""
    from dataclasses import replace

    from splatstream.format.manifest import manifest_from_dict
    from splatstream.format.manifest.versions import VERSION_1_7, writer_version

    if not {"tile_table", "tile_table_zstd"} & d.keys() or "paged" in d:
        return d
    m = manifest_from_dict(d)  # without the tree's build record (1.9), which a 1.7 manifest does not have
    m = replace(m, version=VERSION_1_7, lod=replace(m.lod, merge=None, viewing_scale_px=None))
    out = m.with_bytes_on_disk(m.payload_bytes()).to_dict()
    # A scene whose texel formats need a newer version (1.13: cube565 rotations) keeps it, with the same tile maps
    # (a manifest from 1.8 on may hold `tiles`, format.md 6.2; [1, 13] packs to as many bytes as [1, 7])
    out["version"] = list(max(VERSION_1_7, writer_version(m.formats)))
    return out


def write_manifest_dict(scene_dir, m: dict, settle: bool = False) -> None:
    """Write a (damaged) manifest map as a file of its version: from 1.2 on with a valid checksum, so the damage
    under test is what the reader finds (tests of the checksum itself damage the bytes). With `settle`, the totals
    a reader recomputes (gpu_bytes, leaf_bytes_on_disk, bytes_on_disk) are made to agree with the entries first,
    for tests that replace a payload and mean only its content to be wrong."""
    from splatstream.format.manifest import pack_manifest_dict

    if settle:
        settle_totals(m)
    (pathlib.Path(scene_dir) / "manifest.msgpack").write_bytes(pack_manifest_dict(m))


def settle_totals(m: dict) -> None:
    from splatstream.format.manifest import pack_manifest_dict

    leaves = [p for t in m["tiles"] if not t["children"] for p in t["groups"].values()]
    leaves += list((m.get("sh_codebook") or {}).get("groups", {}).values())
    m["gpu_bytes"] = sum(p["gpu_bytes"] for p in leaves)
    m["leaf_bytes_on_disk"] = sum(p["bytes"] for p in leaves)
    every = {p["file"]: p["bytes"] for t in m["tiles"] for p in t["groups"].values()}
    every.update({p["file"]: p["bytes"] for p in (m.get("sh_codebook") or {}).get("groups", {}).values()})
    for _ in range(3):  # the number's own msgpack length can change the manifest's length once
        m["bytes_on_disk"] = sum(every.values()) + len(pack_manifest_dict(m))


def sphere_framed_camera(positions, width: int, height: int, up=(0.0, 0.0, 1.0)):
    """The default camera as it was before issue 34 (target the median, the central 95 % box's bounding sphere in
    the narrower field of view): the view some tests' thresholds were measured on."""
    import numpy as np

    from splatstream.camera import DEFAULT_FOV_Y_DEG, REFERENCE_NEAR, Camera, _diagonal, fit_distance, robust_bounds

    med, lo, hi = robust_bounds(positions, 95.0)
    radius = float(np.linalg.norm(np.maximum(hi - med, med - lo))) or 1.0
    dist = fit_distance(radius, DEFAULT_FOV_Y_DEG, width / height)
    eye = med + _diagonal(np.asarray(up, dtype=np.float64)) * dist
    return Camera(tuple(eye), tuple(med), tuple(up), DEFAULT_FOV_Y_DEG, width, height,
                  min(REFERENCE_NEAR, 0.01 * dist), max(1000.0, 10.0 * (dist + radius)))



def close_camera(g, width: int, height: int):
    """A close view of `g`: splats straddle the image border and tile borders, some lie behind the camera (the view
    the compute draw's thresholds were measured on: 0.35 of sphere_framed_camera's distance at 128x96)."""
    import numpy as np

    from splatstream.camera import look_at

    base = sphere_framed_camera(g.positions, 128, 96)
    eye = np.array(base.target) + 0.35 * (np.array(base.eye) - np.array(base.target))
    return look_at(eye, base.target, fov_y_deg=60, width=width, height=height)


def payloads_by_group(store, manifest) -> dict[str, list]:
    """Every tile's payload bytes with its entry, by group, in the manifest's tile order (a group's decode input)."""
    by_group: dict[str, list] = {}
    for t in manifest.tiles:
        for group, entry in t.groups.items():
            by_group.setdefault(group, []).append((store.read_payload(entry), entry))
    return by_group


def zstd_block_count(data: bytes) -> int:
    """The number of blocks in a zstd frame (RFC 8878 3.1.1: the frame header, then blocks of a 3-byte header)."""
    descriptor = data[4]
    single, has_checksum = descriptor >> 5 & 1, descriptor >> 2 & 1
    at = 5 + (0 if single else 1) + (0, 1, 2, 4)[descriptor & 3] + ((1, 2, 4, 8)[descriptor >> 6] if single or
                                                                     descriptor >> 6 else 0)
    blocks = 0
    while True:
        header = int.from_bytes(data[at:at + 3], "little")
        last, kind, size = header & 1, header >> 1 & 3, header >> 3
        at += 3 + (1 if kind == 1 else size)
        blocks += 1
        if last:
            return blocks if at + 4 * has_checksum == len(data) else -1

@contextlib.contextmanager
def xvfb_display(screen: str = "1024x768x24"):
    """A virtual X display for window tests: yields its name (":N"), stops the server afterwards."""
    r, w = os.pipe()
    proc = subprocess.Popen(["Xvfb", "-displayfd", str(w), "-screen", "0", screen, "-nolisten", "tcp"],
                            pass_fds=(w,), stderr=subprocess.DEVNULL, stdout=subprocess.DEVNULL)
    os.close(w)
    number = b""
    while not number.endswith(b"\n"):
        chunk = os.read(r, 16)
        if not chunk:
            break
        number += chunk
    os.close(r)
    try:
        yield f":{number.decode().strip()}"
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(10)
