"""How long a streaming client's decode job holds the interpreter lock, against its wall (issue 38's fly-through
p99: the frame thread waits for the decode threads' lock; issue 32's decode speed).

    python bench/probe_decode_gil.py [--splats 120000] [--preset medium] [--kernels numpy,numba] [--runs 3]

The scene is the city fly-through's kind (bench/device/run_city.sh: copies of samples/donut.ply on a ground grid by
bench/tile_scene.py's recipe, SH0, the encoder's defaults: leaf tiles of up to 16,384 splats), encoded in memory;
the payloads timed are its base payloads of at least --min-splats splats (the city's are about 10,000 each), each
handed to the engine's `decode_job` (client_gl.stream.engine: decode_payload, then the planes as the pool takes them)
as the fetcher hands them over (VerifiedPayloads), one payload a job as the city's are.

The lock, by the clock (the figures that hold on a loaded machine): each payload's decode CPU (time.thread_time,
least of --runs) alone, then the CPU spent inside the calls that release the lock (zstd's decompression and the
compiled kernels, each wrapped) and how many there are: `held` = CPU - that CPU is the Python and numpy the decode
thread runs holding the lock, and `lock_releases` the times per payload it gives the lock up and must take it back
(the frame thread, waiting, gets it at each; the decode waits for it back after each). For the numpy path only zstd
is counted as released (numpy releases the lock inside its larger loops too, for a few microseconds at a time).

With --probe, by a probe too: a thread spins on a tiny Python loop counting iterations (its rate alone measured
first); while a decode runs in the main thread, held = wall - iterations / rate alone. That needs two free cores:
on a loaded machine the probe waits for a core, not for the lock, and the figure means nothing. Texels are checked
equal across --kernels (numpy: transport's numpy path; numbap: the compiled kernels a plane at a time, the path
before the whole kernel; numba: decode_jit.install(), a payload in one call). Prints one JSON object.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import threading
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from client_gl.stream.engine import decode_job  # noqa: E402
from splatstream.encode import EncodeOptions  # noqa: E402
from splatstream.encode.local import encode_in_memory  # noqa: E402
from splatstream.format import container, transport  # noqa: E402
from splatstream.format.container import verify_payload  # noqa: E402
from splatstream.io import read_gaussians  # noqa: E402
from splatstream.store import read_manifest  # noqa: E402

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")


class Probe:
    """A thread counting iterations of a tiny Python loop for as long as it runs."""

    def __init__(self):
        self.count = 0
        self.stop = False
        self.thread = threading.Thread(target=self._spin, daemon=True)

    def _spin(self) -> None:
        n = 0
        while not self.stop:
            n += 1
            if not n & 63:
                self.count = n

    def start(self) -> None:
        self.thread.start()

    def close(self) -> None:
        self.stop = True
        self.thread.join()


def scene_payloads(splats: int, preset: str, min_splats: int) -> list[tuple]:
    """The base payloads (VerifiedPayload, entry, splats) of a city-like scene of `splats` splats."""
    with tempfile.TemporaryDirectory() as tmp:
        ply = os.path.join(tmp, "s.ply")
        subprocess.run([sys.executable, os.path.join(ROOT, "bench", "tile_scene.py"),
                        os.path.join(ROOT, "samples", "donut.ply"), "--splats", str(splats), "--out", ply],
                       check=True, stdout=subprocess.DEVNULL)
        g = read_gaussians(ply)
    store = encode_in_memory(g, EncodeOptions(preset=preset))
    m = read_manifest(store)
    out = []
    for t in m.tiles:
        entry = t.groups["base"]
        if t.splats >= min_splats:
            out.append((verify_payload(store.read_payload(entry), entry, "probe"), entry, t.splats))
    return out


def job(p: tuple):
    data, entry, splats = p
    return decode_job(data, entry, "base", "probe", False, splats, 0, False, None)


class NogilClock:
    """CPU time of this thread inside the calls that release the interpreter lock (zstd's decompression, the compiled
    kernels), and how many: each one is a point where the decode thread gives the lock up and must take it back."""

    def __init__(self):
        self.cpu = 0.0
        self.calls = 0
        self.saved: list = []

    def wrap(self, fn):
        def timed(*a):
            c = time.thread_time()
            try:
                return fn(*a)
            finally:
                self.cpu += time.thread_time() - c
                self.calls += 1
        return timed

    def __enter__(self):
        self.saved = [container._decompress_into, transport._fields_kernel, transport._unshuffle_kernel,
                      transport._batch_kernels, transport._whole_kernel]
        container._decompress_into = self.wrap(container._decompress_into)
        for name in ("_fields_kernel", "_unshuffle_kernel", "_whole_kernel"):
            if getattr(transport, name) is not None:
                setattr(transport, name, self.wrap(getattr(transport, name)))
        transport._batch_kernels = tuple(k if k is None else self.wrap(k) for k in transport._batch_kernels)
        return self

    def __exit__(self, *exc):
        (container._decompress_into, transport._fields_kernel, transport._unshuffle_kernel,
         transport._batch_kernels, transport._whole_kernel) = self.saved


def use(variant: str) -> None:
    """Hand transport the kernels of `variant` (numpy, numbap, numba)."""
    if variant == "numpy":
        transport.use_fields_kernel(None)
        transport.use_unshuffle_kernel(None)
        transport.use_batch_kernels(None, None)
        transport.use_whole_kernel(None)
        return
    from client_gl.stream import decode_jit
    transport.use_fields_kernel(decode_jit.fields1_kernel)
    transport.use_unshuffle_kernel(decode_jit.unshuffle_kernel)
    transport.use_batch_kernels(decode_jit.fields1_many_kernel, decode_jit.unshuffle_many_kernel)
    transport.use_whole_kernel(decode_jit.whole_kernel if variant == "numba" else None)


def measure(payloads: list[tuple], variants: list[str], runs: int, probe_too: bool) -> dict:
    """Per variant and payload (the least of `runs` rounds, the variants interleaved in each round so that the
    machine's load falls on them alike): CPU alone; CPU inside the lock-free calls and their count (NogilClock);
    held = CPU alone - that. With probe_too, wall, CPU and held beside the spinning probe (the module's doc)."""
    cpu = {v: [1e9] * len(payloads) for v in variants}
    nogil = {v: [1e9] * len(payloads) for v in variants}
    calls = {v: [0] * len(payloads) for v in variants}
    for v in variants:  # warm: kernels, caches, the kept buffer
        use(v)
        for p in payloads:
            job(p)
    for _ in range(runs):
        for v in variants:
            use(v)
            for i, p in enumerate(payloads):
                c = time.thread_time()
                job(p)
                cpu[v][i] = min(cpu[v][i], time.thread_time() - c)
                with NogilClock() as clock:
                    job(p)
                nogil[v][i] = min(nogil[v][i], clock.cpu)
                calls[v][i] = clock.calls
    ms = lambda v: round(1e3 * statistics.median(v), 4)  # noqa: E731
    splats = [p[2] for p in payloads]
    out = {}
    for v in variants:
        held = [max(c - n, 0.0) for c, n in zip(cpu[v], nogil[v], strict=True)]
        out[v] = {"payloads": len(payloads), "splats_median": int(statistics.median(splats)),
                  "cpu_ms": ms(cpu[v]), "nogil_cpu_ms": ms(nogil[v]), "held_ms": ms(held),
                  "held_of_cpu": round(sum(held) / sum(cpu[v]), 3), "lock_releases": int(statistics.median(calls[v])),
                  "cpu_total_ms": round(1e3 * sum(cpu[v]), 2), "held_total_ms": round(1e3 * sum(held), 2),
                  "M_splats_per_s": round(sum(splats) / sum(cpu[v]) / 1e6, 2)}
        if len(set(splats)) > 1:  # a payload's CPU and held lock fitted as fixed + per splat (least squares)
            for name, ys in (("cpu", cpu[v]), ("held", held)):
                slope, fixed = np.polyfit(np.array(splats, float), np.array(ys), 1)
                out[v][f"{name}_fixed_us"] = round(1e6 * fixed, 1)
                out[v][f"{name}_per_splat_ns"] = round(1e9 * slope, 2)
        if probe_too:
            use(v)
            out[v].update(beside_probe(payloads, runs))
    return out


def beside_probe(payloads: list[tuple], runs: int) -> dict:
    probe = Probe()
    probe.start()
    time.sleep(0.05)
    n0, t0 = probe.count, time.perf_counter()
    time.sleep(0.5)  # the main thread sleeps (no lock): the probe's rate alone
    rate = (probe.count - n0) / (time.perf_counter() - t0)
    wall, cpu, held = [], [], []
    for p in payloads:
        rows = []
        for _ in range(runs):
            time.sleep(0.002)
            n0, c, w = probe.count, time.thread_time(), time.perf_counter()
            job(p)
            dw, dc, dn = time.perf_counter() - w, time.thread_time() - c, probe.count - n0
            rows.append((dw - dn / rate, dw, dc))
        h, dw, dc = min(rows)
        held.append(max(h, 0.0))
        wall.append(dw)
        cpu.append(dc)
    probe.close()
    ms = lambda v: round(1e3 * statistics.median(v), 4)  # noqa: E731
    return {"probe_wall_ms": ms(wall), "probe_cpu_ms": ms(cpu), "probe_held_ms": ms(held),
            "probe_rate_M_per_s": round(rate / 1e6, 2)}


def texels(payloads: list[tuple]) -> list[bytes]:
    out = []
    for p in payloads:
        planes, _ = job(p)
        for name in sorted(planes):
            out += [bytes(memoryview(a).cast("B")) for a in planes[name].layers]
            if planes[name].ranges is not None:
                out.append(planes[name].ranges.tobytes())
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--splats", type=int, default=120000)
    ap.add_argument("--preset", default="medium")
    ap.add_argument("--min-splats", type=int, default=4096)
    ap.add_argument("--kernels", default="numpy,numbap,numba")
    ap.add_argument("--probe", action="store_true", help="also beside the spinning probe (needs two free cores)")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--json")
    args = ap.parse_args()
    payloads = scene_payloads(args.splats, args.preset, args.min_splats)
    result = {"command": " ".join(sys.argv), "machine": platform.processor() or platform.machine(),
              "cpus": os.cpu_count(), "load": os.getloadavg(),
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "switch_interval_s": sys.getswitchinterval(), "preset": args.preset, "kernels": {}}
    reference = None
    variants = args.kernels.split(",")
    if {"numba", "numbap"} & set(variants):
        from client_gl.stream import decode_jit
        decode_jit.warm_up()
    for variant in variants:
        use(variant)
        got = texels(payloads)
        if reference is None:
            reference = got
        elif got != reference:
            raise SystemExit(f"{variant}: texels differ from {variants[0]}'s")
    result["kernels"] = measure(payloads, variants, args.runs, args.probe)
    for variant in variants:
        print(variant, json.dumps(result["kernels"][variant]), file=sys.stderr)
    result["load_after"] = os.getloadavg()
    text = json.dumps(result, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
