"""Paired, interleaved A/B of two versions of the compiled decode kernels (client_gl/stream/decode_jit.py), end to
end on the streaming client's path (issue 32: "Decode speed stays at 10 M splats/s or more on one core").

    git show REV:client_gl/stream/decode_jit.py > /tmp/decode_jit_ref.py  # any file name but decode_jit.py
    python bench/decode_kernel_ab.py --reference /tmp/decode_jit_ref.py [--scenes guitar,winter_fountain]
        [--presets high,medium,...] [--rounds 7] [--cap 4096] [--json PATH]

Each scene (tests/data/real, as bench/decode_quiet.py names them) is encoded in memory with each preset and the
encoder's defaults (LOD tree), not timed. Then, in this process on one thread, CPU time of the thread
(time.thread_time): `format.decode.decode_payloads` of VerifiedPayloads (the fetcher's; no SHA-256 at decode) in
jobs of at most --cap splats of one group, as the engine's decode_batch_splats cuts them, with the reference's
kernels and this tree's installed in turn (the order alternating each round; each round's figure the least of 3
passes), so that the load of a shared machine falls on both alike and only the kernels differ: the Python around
them is this tree's for both. Texels and ranges are checked equal between the two first. Prints us a payload and
M splats/s (each tile's splats once per group), best and median round, and writes them to --json.
"""
from __future__ import annotations

import argparse
import importlib
import json
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import numpy as np  # noqa: E402

from client_gl.stream import decode_jit  # noqa: E402
from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format import container, keyed, transport  # noqa: E402
from splatstream.format.container import verify_payload  # noqa: E402
from splatstream.format.decode import decode_payloads  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
SCENES = {"guitar": "tests/data/real/guitar.compressed.ply", "winter_fountain": "tests/data/real/winter_fountain.splat"}
PRESETS = "high,low-plus-10bit-cb8,low-plus-9bit-sh6,low,medium-low-12bit,medium-low-9bit,medium-low-palette,medium," \
          "very-high"


def _use(kernels) -> None:
    """Decode with this decode_jit module's kernels (as its install() hands them in, without compiling again)."""
    transport.use_fields_kernel(kernels.fields1_kernel)
    transport.use_unshuffle_kernel(kernels.unshuffle_kernel)
    transport.use_batch_kernels(kernels.fields1_many_kernel, kernels.unshuffle_many_kernel)
    transport.use_whole_kernel(kernels.whole_kernel)
    keyed.use_morton_kernel(kernels.morton_kernel)
    container.use_ranges_kernel(getattr(kernels, "ranges_kernel", None))  # a reference may have none


def _jobs(store, cap: int) -> tuple[list, bool, object, int, int]:
    """The scene's payloads as the engine's decode jobs: (group, [(VerifiedPayload, entry)]) of at most `cap` splats."""
    m = read_manifest(store)
    by_group: dict[str, list] = {}
    for t in m.tiles:
        for group, entry in t.groups.items():
            data = store.read_payload(entry)
            by_group.setdefault(group, []).append((verify_payload(data, entry, "bench"), entry, t.splats))
    jobs = []
    for group, items in by_group.items():
        job, splats = [], 0
        for data, entry, n in items:
            if job and splats + n > cap:
                jobs.append((group, job))
                job, splats = [], 0
            job.append((data, entry))
            splats += n
        if job:
            jobs.append((group, job))
    splats = sum(n for items in by_group.values() for _, _, n in items)
    payloads = sum(len(items) for items in by_group.values())
    return jobs, m.uses_codebook, m.scene_palettes, splats, payloads


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--reference", required=True,
                    help="a decode_jit.py of another version (git show REV:path), under another file name")
    ap.add_argument("--scenes", default="guitar,winter_fountain")
    ap.add_argument("--presets", default=PRESETS)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--cap", type=int, default=4096, help="splats a decode job (the engine's decode_batch_splats)")
    ap.add_argument("--json")
    args = ap.parse_args()
    # imported by its file's name from its folder: numba's cache (cache=True) loads a kernel's environment by
    # importing its module by name, which a module made from a spec alone does not have
    folder, name = os.path.split(os.path.abspath(args.reference))
    sys.path.insert(0, folder)
    reference = importlib.import_module(os.path.splitext(name)[0])
    reference.warm_up()
    decode_jit.warm_up()
    variants = (("reference", reference), ("this", decode_jit))
    results = {"load_start": os.getloadavg()[0], "cap": args.cap, "cases": {}}
    for scene in args.scenes.split(","):
        g = read_gaussians(os.path.join(ROOT, SCENES[scene]))
        for preset in args.presets.split(","):
            jobs, codebook, palettes, splats, payloads = _jobs(encode_in_memory(g, EncodeOptions(preset=preset)),
                                                               args.cap)

            def decode(jobs=jobs, codebook=codebook, palettes=palettes) -> list:
                return [decode_payloads(items, group, ["bench"] * len(items), codebook, palettes=palettes)
                        for group, items in jobs]

            texels = []
            for _, kernels in variants:
                _use(kernels)
                texels.append([np.asarray(x).tobytes() for job in decode() for planes in job for p in planes.values()
                               for x in [*p.layers, p.ranges] if x is not None])
            if texels[0] != texels[1]:
                raise SystemExit(f"{scene} {preset}: the two kernels decode different bytes")
            times: dict[str, list[float]] = {name: [] for name, _ in variants}
            for r in range(args.rounds):
                for name, kernels in (variants if r % 2 == 0 else variants[::-1]):
                    _use(kernels)
                    best = float("inf")
                    for _ in range(3):
                        t = time.thread_time()
                        decode()
                        best = min(best, time.thread_time() - t)
                    times[name].append(best)
            row = {name: {"us_per_payload_best": round(min(ts) / payloads * 1e6, 1),
                          "us_per_payload_median": round(statistics.median(ts) / payloads * 1e6, 1),
                          "M_splats_s_best": round(splats / min(ts) / 1e6, 2),
                          "M_splats_s_median": round(splats / statistics.median(ts) / 1e6, 2)}
                   for name, ts in times.items()}
            row["load"] = os.getloadavg()[0]
            results["cases"][f"{scene} {preset}"] = row
            ref, this = row["reference"], row["this"]
            print(f"{scene:16} {preset:20} reference {ref['M_splats_s_best']:6.2f} ({ref['M_splats_s_median']:6.2f}) "
                  f"M splats/s, this {this['M_splats_s_best']:6.2f} ({this['M_splats_s_median']:6.2f}); "
                  f"load {row['load']:.1f}", flush=True)
    _use(decode_jit)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
