"""Decode speed of every preset on the bundled real scenes, one thread, with where the time goes (issue 32: "Decode
speed stays at 10 M splats/s or more on one core for every preset"). Self-contained: run from the repo root on a
quiet machine, no shared data needed.

    python bench/decode_quiet.py [--scenes a,b] [--presets p,q] [--runs 5] [--jobs N] [--json PATH]

A scene given as name=path (a file of any input format, relative to the repo root or absolute) is read from there,
e.g. a million-splat SH3 PLY made by tests/tools/make_scene.py (issue 32, dec32: a LOD tree of large tiles).

Each bundled scene of tests/data/real (guitar.compressed.ply, fruit_drops_sh3.ply, lod_tile_sh3_zero_rest.ply,
winter_fountain.splat, flowers_lod/3_0: flowers' coarsest SOG unit) is encoded in memory with each preset and the
encoder's defaults (LOD tree); the encodes run in --jobs processes (default: every core, they are not what is
timed), while this process compiles the numba fields1 kernel (client_gl.stream.decode_jit; numba's cache makes
later runs start at once). Then, in this process on one thread, CPU time of the thread (time.thread_time), rounds
of passes with the variants interleaved so that any load falls on them alike; a pass covers every payload of every
tile, and each decoding variant runs with each --kernels (numpy: transport's numpy path; numba: the compiled
fields1 and unshuffle kernels, a payload or a group in one call, the whole kernel, and the morton1 kernel, as
decode_jit.install() installs them; numbap: a group's plane in one
call each; numba1: a section a call):

* `group`: `format.decode.decode_payloads` of each payload group (base, sh1, ...) as a whole, from bytes: size and
  SHA-256 check, zstd, unfiltering into the texel bytes the GPU takes, the ranges (the batch path, issue 32);
* `verified`: the same from the fetcher's VerifiedPayloads (the streaming client's path: the fetcher and the disk
  cache check size and SHA-256 once, where the bytes enter, and decoding does not hash them again);
* `one` (with --one): `format.decode.decode_payload` one payload at a time, from bytes;
* `sha256`: hashlib's SHA-256 of every payload file alone; `zstd`: decompressing every payload into the decoder's
  kept buffer alone (its own call, `container._decompress_into`).

M splats/s counts each tile's splats once per group (a tile of SH3 with a codebook-free preset is 4 payloads),
median and best of --runs passes. The split of a `group` pass: sha256, zstd, unfilter (= verified - zstd:
unfiltering, range checks, copies and the Python around them) and check (= group - verified: the SHA-256 and its
Python). Per payload, one at a time (`one` with the last kernel, each payload alone, least of 2 calls), fitted as
fixed + per splat (least squares), beside SHA-256's and zstd's fits: the fixed cost less theirs is a payload's
Python and numpy-call overhead. Texels are checked equal across variants and kernels. `faults_a_pass`: the
median minor page faults of this thread in a pass of each decoding variant (a pass that faults its output's pages in
again each time reads very-high 1.3-2x slower: whether it does depends on the process's malloc state; vhdecode32's
kept texel slabs and frames buffer leave it none; BENCHMARKS.md, "Decode speed", vhdecode32). Prints one JSON object
(and writes it to $OUT/decode_quiet.json when OUT is set, or to --json).
"""
from __future__ import annotations

import argparse
import concurrent.futures
import hashlib
import json
import multiprocessing
import os
import platform
import statistics
import sys
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # as the CLI sets it; the encodes run one a process
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402

try:
    import resource  # Unix: the page faults a pass
except ImportError:  # pragma: no cover - not on Linux
    resource = None

from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.errors import UsageError  # noqa: E402
from splatstream.format import container, keyed, transport  # noqa: E402
from splatstream.format.container import verify_payload  # noqa: E402
from splatstream.format.decode import decode_payload, decode_payloads  # noqa: E402
from splatstream.format.presets import PRESETS  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
SCENES = {
    "guitar": "tests/data/real/guitar.compressed.ply",
    "fruit_drops_sh3": "tests/data/real/fruit_drops_sh3.ply",
    "lod_tile_sh3_zero_rest": "tests/data/real/lod_tile_sh3_zero_rest.ply",
    "winter_fountain": "tests/data/real/winter_fountain.splat",
    "flowers_3_0": "tests/data/real/flowers_lod/3_0/meta.json",
    "statue_massa": "tests/data/real/statues/massa.sog",  # a SOG input: medium-low-palette keeps its palettes
}
DECODES = ("group", "verified", "one")


def scene_gaussians(names: str):
    """(name, Gaussians) of each comma-separated scene: a name of SCENES or `name=path` (added to SCENES)."""
    for scene in names.split(","):
        if "=" in scene:  # another scene: name=path
            scene, path = scene.split("=", 1)
            SCENES[scene] = path
        yield scene, read_gaussians(os.path.join(ROOT, SCENES[scene]))


def encode(scene: str, preset: str, path: str | None = None):
    """(scene, preset, MemoryStore or the reason it was skipped, encode CPU s) in a worker process; `path`: the
    scene's file where it is not one of SCENES (--scenes name=path: a worker process has only SCENES' own)."""
    t = time.process_time()
    path = path or SCENES[scene]
    try:  # a scene this machine cannot read (the SOG unit's WebP planes need Pillow) is skipped, and said so
        g = read_gaussians(os.path.join(ROOT, path))
    except Exception as e:  # any reason, reported in the JSON's "skipped"
        return scene, preset, f"reading {path}: {type(e).__name__}: {e}", 0.0
    try:
        store = encode_in_memory(g, EncodeOptions(preset=preset))
    except UsageError as e:  # very-low's BC7 colour without the `bc` extra
        return scene, preset, str(e), 0.0
    return scene, preset, store, time.process_time() - t


class Case:
    """One scene with one preset: its payloads by group, as a decoder receives them."""

    def __init__(self, store):
        m = read_manifest(store)
        self.codebook = m.uses_codebook
        self.palettes = m.scene_palettes  # format.md 4.3.2 (1.7): a palette plane's palettes may be the scene's
        self.groups: dict[str, list] = {}
        self.verified: dict[str, list] = {}
        self.splats_of: dict[str, list[int]] = {}
        for t in m.tiles:
            for group, entry in t.groups.items():
                data = store.read_payload(entry)
                self.groups.setdefault(group, []).append((data, entry))
                self.verified.setdefault(group, []).append((verify_payload(data, entry, "bench"), entry))
                self.splats_of.setdefault(group, []).append(t.splats)
        self.splats = sum(sum(v) for v in self.splats_of.values())
        self.payloads = sum(len(v) for v in self.groups.values())
        self.tiles = len(m.tiles)
        self.bytes = sum(len(d) for v in self.groups.values() for d, _ in v)
        self.raw_bytes = sum(e.raw_bytes for v in self.groups.values() for _, e in v)
        self.faults: dict[str, list[int]] = {}  # minor page faults of each pass, by variant

    def run(self, variant: str) -> float:
        """CPU seconds of this thread for one pass of `variant` over every payload (its page faults noted)."""
        cb = self.codebook
        faults = _faults()
        start = time.thread_time()
        if variant == "group":
            for group, items in self.groups.items():
                decode_payloads(items, group, ["bench"] * len(items), cb, palettes=self.palettes)
        elif variant == "one":
            for group, items in self.groups.items():
                for data, entry in items:
                    decode_payload(data, entry, group, "bench", cb, palettes=self.palettes)
        elif variant == "verified":
            for group, items in self.verified.items():
                decode_payloads(items, group, ["bench"] * len(items), cb, palettes=self.palettes)
        elif variant == "sha256":
            for items in self.groups.values():
                for data, _ in items:
                    hashlib.sha256(data).digest()
        elif variant == "zstd":
            for items in self.groups.values():
                for data, entry in items:
                    buf, _ = container._raw_buffer(entry.raw_bytes)
                    container._decompress_into(data, buf, "bench")
        took = time.thread_time() - start
        self.faults.setdefault(variant, []).append(_faults() - faults)
        return took

    def texels(self) -> list[bytes]:
        """Every texel and range byte, decoded by each variant (which must agree)."""
        out = None
        for group_items in (self.groups, self.verified):
            got = []
            for group, items in group_items.items():
                for planes in decode_payloads(items, group, ["bench"] * len(items), self.codebook,
                                              palettes=self.palettes):
                    got += _bytes(planes)
            if out is not None and got != out:
                raise SystemExit("decode_payloads of VerifiedPayloads differs from that of bytes")
            out = got
        alone = []
        for group, items in self.groups.items():
            for data, entry in items:
                alone += _bytes(decode_payload(data, entry, group, "bench", self.codebook, palettes=self.palettes))
        if alone != out:
            raise SystemExit("decode_payloads differs from decode_payload")
        return out

    def fit(self) -> dict:
        """Each payload alone (least of 2 calls): decode_payload, SHA-256 and zstd as fixed + per splat."""
        rows = {"one": [], "sha256": [], "zstd": []}
        splats = []
        for group, items in self.groups.items():
            for (data, entry), n in zip(items, self.splats_of[group], strict=True):
                splats.append(n)
                best = {k: float("inf") for k in rows}
                for _ in range(2):
                    t = time.thread_time()
                    decode_payload(data, entry, group, "bench", self.codebook, palettes=self.palettes)
                    t1 = time.thread_time()
                    hashlib.sha256(data).digest()
                    t2 = time.thread_time()
                    buf, _ = container._raw_buffer(entry.raw_bytes)
                    container._decompress_into(data, buf, "bench")
                    t3 = time.thread_time()
                    best["one"] = min(best["one"], t1 - t)
                    best["sha256"] = min(best["sha256"], t2 - t1)
                    best["zstd"] = min(best["zstd"], t3 - t2)
                for k in rows:
                    rows[k].append(best[k])
        ns = np.array(splats, float)
        a = np.stack([np.ones_like(ns), ns], 1)
        out = {}
        for k, ts in rows.items():
            (fixed, per), *_ = np.linalg.lstsq(a, np.array(ts), rcond=None)
            out[k] = {"fixed_us": round(fixed * 1e6, 1), "per_splat_ns": round(per * 1e9, 1)}
        out["overhead_us_per_payload"] = round(out["one"]["fixed_us"] - out["sha256"]["fixed_us"]
                                               - out["zstd"]["fixed_us"], 1)
        return out


def _faults() -> int:
    """This thread's minor page faults so far (0 where the platform does not count them)."""
    return resource.getrusage(getattr(resource, "RUSAGE_THREAD", resource.RUSAGE_SELF)).ru_minflt if resource else 0


def _bytes(planes: dict) -> list[bytes]:
    out = []
    for p in planes.values():
        out += [np.asarray(layer).tobytes() for layer in p.layers]
        for extra in (p.ranges, p.palette):
            if extra is not None:
                out.append(np.asarray(extra).tobytes())
    return out


def _numba_kernel():
    """The compiled kernels (fields1, unshuffle, fields1 and unshuffle over a group), or None and the reason."""
    try:
        from client_gl.stream import decode_jit  # numba: the optional extra `fast`
    except ImportError as exc:
        return None, str(exc)
    decode_jit.warm_up()
    return (decode_jit.fields1_kernel, decode_jit.unshuffle_kernel, decode_jit.fields1_many_kernel,
            decode_jit.unshuffle_many_kernel, decode_jit.whole_kernel, decode_jit.morton_kernel,
            decode_jit.ranges_kernel), None


def _use(kernels) -> None:
    """Decode with these kernels (fields1, unshuffle, their batch forms for a group's plane, the whole kernel for
    a payload or a group, morton1's, the range checks'); None: numpy's path."""
    transport.use_fields_kernel(kernels[0] if kernels else None)
    transport.use_unshuffle_kernel(kernels[1] if kernels else None)
    transport.use_batch_kernels(*(kernels[2:4] if kernels else (None, None)))
    transport.use_whole_kernel(kernels[4] if kernels else None)
    keyed.use_morton_kernel(kernels[5] if kernels else None)
    container.use_ranges_kernel(kernels[6] if kernels and len(kernels) > 6 else None)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--presets", default=",".join(PRESETS))
    ap.add_argument("--kernels", default="numpy,numba", help="fields1 decoders: numpy, numba (if installed: a "
                    "payload or a group in one call, the whole kernel), numbap (a plane of a group a call: the path "
                    "before the whole kernel), numba1 (a section a call: the path before the batch kernels)")
    ap.add_argument("--runs", type=int, default=3, help="rounds of timed passes (each round: every variant once; "
                    "3 keeps the default run under 150 s of one quiet core, 5 or more for steadier medians)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="encoding processes (not timed)")
    ap.add_argument("--no-fit", action="store_true", help="skip the per-payload fit")
    ap.add_argument("--one", action="store_true", help="time `one` (decode_payload a payload at a time) in the rounds "
                    "too (the per-payload fit times it anyway)")
    ap.add_argument("--json", help="also write the JSON here (default $OUT/decode_quiet.json when OUT is set)")
    args = ap.parse_args()
    wall = time.time()
    scenes, presets = args.scenes.split(","), args.presets.split(",")
    paths = dict(s.split("=", 1) if "=" in s else (s, SCENES[s]) for s in scenes)  # name=path: another scene
    scenes = list(paths)
    stores, skipped, encode_s = {}, {}, {}
    work = [(s, p, paths[s]) for s in scenes for p in presets]
    kernels = {"numpy": None}
    compile_s = None
    if args.jobs > 1:
        with concurrent.futures.ProcessPoolExecutor(args.jobs, mp_context=multiprocessing.get_context("spawn")) as ex:
            pending = ex.map(encode, *zip(*work, strict=True))
            if {"numba", "numba1", "numbap"} & set(args.kernels.split(",")):  # compiled while the workers encode
                t = time.time()
                kernel, why = _numba_kernel()
                compile_s = round(time.time() - t, 1)
            done = list(pending)
    else:
        done = [encode(*w) for w in work]
        if {"numba", "numba1", "numbap"} & set(args.kernels.split(",")):
            t = time.time()
            kernel, why = _numba_kernel()
            compile_s = round(time.time() - t, 1)
    names = args.kernels.split(",")
    if {"numba1", "numbap"} & set(names) and "numba" not in names:
        names.append("numba")
    if "numba" in names:
        if kernel is None:
            skipped["numba"] = why
        else:
            if "numba1" in names:
                kernels["numba1"] = kernel[:2] + (None, None, None, None)
            if "numbap" in names:
                kernels["numbap"] = kernel[:4] + (None, None)
            kernels["numba"] = kernel
    if "numpy" not in args.kernels.split(","):
        del kernels["numpy"]
    for scene, preset, store, cpu in done:
        if isinstance(store, str):
            skipped[f"{scene}/{preset}"] = store
        else:
            stores[scene, preset] = store
            encode_s[f"{scene}/{preset}"] = round(cpu, 2)
    print(f"encoded {len(stores)} cases in {time.time() - wall:.1f} s wall ({args.jobs} processes); kernels "
          f"{list(kernels)} (numba compile {compile_s} s)", file=sys.stderr, flush=True)
    results = []
    decodes = DECODES if args.one else DECODES[:2]
    variants = [(v, k) for v in decodes for k in kernels] + [("sha256", None), ("zstd", None)]
    for (scene, preset), store in stores.items():
        case = Case(store)
        reference = None
        for name, kernel in kernels.items():
            _use(kernel)
            got = case.texels()
            if reference is not None and got != reference:
                raise SystemExit(f"{scene} {preset}: the {name} kernel decodes to other texels")
            reference = got
        times: dict[tuple, list[float]] = {v: [] for v in variants}
        faults: dict[tuple, list[int]] = {v: [] for v in variants}
        for _ in range(args.runs):  # the texel check above was the warm-up (allocations, caches, kernels)
            for v in variants:
                _use(kernels.get(v[1]))
                times[v].append(case.run(v[0]))
                faults[v].append(case.faults[v[0]][-1])
        med = {v: statistics.median(ts) for v, ts in times.items()}
        row = {
            "scene": scene, "preset": preset, "tiles": case.tiles, "payloads": case.payloads,
            "groups": list(case.groups), "splats": case.splats, "bytes_per_splat": round(case.bytes / case.splats, 2),
            "raw_mb": round(case.raw_bytes / 1e6, 3), "encode_cpu_s": encode_s[f"{scene}/{preset}"],
            "zstd_mb_s": round(case.raw_bytes / med["zstd", None] / 1e6, 1),
        }
        for name in kernels:
            k = {}
            for v in decodes:
                k[v] = round(case.splats / med[v, name] / 1e6, 2)
                k[f"{v}_best"] = round(case.splats / min(times[v, name]) / 1e6, 2)
            k["split_ms"] = {  # of a `group` pass, medians
                "sha256": round(med["sha256", None] * 1e3, 3), "zstd": round(med["zstd", None] * 1e3, 3),
                "unfilter": round((med["verified", name] - med["zstd", None]) * 1e3, 3),
                "check": round((med["group", name] - med["verified", name]) * 1e3, 3),
                "group": round(med["group", name] * 1e3, 3),
            }
            k["faults_a_pass"] = {v: statistics.median(faults[v, name]) for v in decodes}
            row[name] = k
        if not args.no_fit:
            _use(kernels[list(kernels)[-1]])
            row["per_payload"] = case.fit()
            row["per_payload"]["kernel"] = list(kernels)[-1]
        results.append(row)
        print(f"{scene:>24} {preset:>20}: " + "; ".join(
            f"{name} group {row[name]['group']:6.2f} (best {row[name]['group_best']:6.2f}) verified "
            f"{row[name]['verified']:6.2f}" + (f" one {row[name]['one']:6.2f}" if args.one else "")
            + f" ({row[name]['faults_a_pass']['verified']:.0f} faults a pass)"
            for name in kernels)
            + f" M splats/s; {case.payloads} payloads", file=sys.stderr, flush=True)
    _use(None)
    by_preset = {}
    for preset in presets:
        rows = [r for r in results if r["preset"] == preset]
        if rows:  # every scene's splats over every scene's median pass
            total = sum(r["splats"] for r in rows)
            by_preset[preset] = {name: {
                v: round(total / sum(r["splats"] / r[name][v] for r in rows), 2) for v in decodes} | {
                "slowest_scene_group": min(r[name]["group"] for r in rows),
                "slowest_scene_verified": min(r[name]["verified"] for r in rows)} for name in kernels}
    report = {
        "bench": "bench/decode_quiet.py", "argv": sys.argv[1:], "date_utc": time.strftime("%Y-%m-%d %H:%M:%S",
                                                                                         time.gmtime()),
        "machine": {"node": platform.node(), "cpu": _cpu_name(), "cores": os.cpu_count(),
                    "python": platform.python_version(), "numpy": np.__version__,
                    "zstandard": __import__("zstandard").__version__},
        "load_average_end": os.getloadavg(), "wall_s": round(time.time() - wall, 1), "runs": args.runs,
        "kernels": list(kernels), "numba_compile_s": compile_s,
        "by_preset": by_preset, "skipped": skipped, "cases": results,
    }
    text = json.dumps(report, indent=1)
    print(text)
    path = args.json or (os.path.join(os.environ["OUT"], "decode_quiet.json") if os.environ.get("OUT") else None)
    if path:
        with open(path, "w") as f:
            f.write(text + "\n")


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor()


if __name__ == "__main__":
    main()
