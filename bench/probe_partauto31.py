"""Encode one scene as one variant of BENCHMARKS.md's "The auto merge in partitioned encodes" (issue 31, branch
partauto31) and print one JSON line: wall and CPU seconds and the peak RSS of this process (the in-process engine:
every partition runs here, so it is the one worker's peak).

    PYTHONPATH=. python bench/probe_partauto31.py IN.ply OUT/SCENE auto 30 40000   # partitioned, domains <= 40,000
    PYTHONPATH=. python bench/probe_partauto31.py IN.ply OUT/SCENE grid 2.5 -      # partitioned grid, 2.5 MiB/worker
    PYTHONPATH=. python bench/probe_partauto31.py IN.ply OUT/SCENE auto 4096 -     # in memory

Arguments: input (a binary PLY: only those are read by rows, so partitioned in one process), output directory,
--lod-merge, --memory-per-worker in MiB, EncodeOptions.lod_merge_domain_splats (- for the default, 2^20).
"""
import json
import logging
import resource
import sys
import time

from splatstream.encode.driver import encode_file


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    src, out, merge, memory, domain = sys.argv[1:6]
    kw: dict = {"lod_merge": merge}
    if domain != "-":
        kw["lod_merge_domain_splats"] = int(domain)
    t0 = time.time()
    encode_file(src, out, memory_per_worker=int(float(memory) * 2**20), **kw)
    ru = resource.getrusage(resource.RUSAGE_SELF)
    print(json.dumps({"out": out, "merge": merge, "memory_mb": memory, "domain": domain,
                      "wall_s": round(time.time() - t0, 1), "cpu_s": round(ru.ru_utime + ru.ru_stime, 1),
                      "peak_rss_mb": round(ru.ru_maxrss / 1024)}))


if __name__ == "__main__":
    main()
