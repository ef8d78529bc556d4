"""One tree level's grouping (lod_groups.group_ids_of) by two checkouts' code, side by side in one process.

    PYTHONPATH=. python bench/lod_group_level_ab.py SCENE --level 0 --rounds 6 --base /tmp/base --new .

Records the inputs of the auto merge's grouping of tree level LEVEL (0: the first merged level) while building
SCENE's auto tree once (cached as a pickle under --cache), then loads `splatstream/lod_groups.py` of both checkouts
as two modules and runs each one's group_ids_of on those inputs in turn, the order swapped every round. Prints the
thread CPU of every run with a digest of the group ids (they must be equal), the median and minimum per checkout,
and the paired new / base ratios. Thread CPU on one thread: what a change to the grouping saves, without the
rest of an encode's noise.
"""
from __future__ import annotations

import argparse
import hashlib
import importlib.util
import os
import pickle
import statistics
import sys
import time


def load_module(path: str, name: str):
    spec = importlib.util.spec_from_file_location(f"splatstream.{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def record_level(scene: str, level: int, cache: str) -> None:
    from splatstream import lod
    from splatstream.io import read_gaussians

    recorded = []
    original = lod.group_ids_of

    def record(inputs, target, rule, *args, **kwargs):
        recorded.append(({k: (v.copy() if v is not None else None) for k, v in inputs.items()}, target, rule))
        return original(inputs, target, rule, *args, **kwargs)

    lod.group_ids_of = record
    lod.build_tiles(read_gaussians(scene), merge="auto")
    with open(cache, "wb") as out:
        pickle.dump(recorded[level], out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--level", type=int, default=0)
    ap.add_argument("--rounds", type=int, default=6)
    ap.add_argument("--base", required=True, help="checkout directory of the base code")
    ap.add_argument("--new", default=".", help="checkout directory of the new code")
    ap.add_argument("--cache", default="/tmp", help="directory of the recorded level's pickle")
    args = ap.parse_args()
    cache = os.path.join(args.cache, f"level_{os.path.basename(args.scene)}_{args.level}.pkl")
    if not os.path.exists(cache):
        record_level(args.scene, args.level, cache)
    with open(cache, "rb") as inp:
        inputs, target, rule = pickle.load(inp)
    modules = {name: load_module(os.path.join(path, "splatstream", "lod_groups.py"), f"lod_groups_{name}")
               for name, path in (("base", args.base), ("new", args.new))}
    seconds: dict[str, list[float]] = {name: [] for name in modules}
    for r in range(args.rounds):
        for name in (list(modules) if r % 2 == 0 else list(modules)[::-1]):
            t0 = time.thread_time()
            ids = modules[name].group_ids_of(dict(inputs), target, rule)
            seconds[name].append(time.thread_time() - t0)
            print(name, f"{seconds[name][-1]:.4f}", hashlib.sha256(ids.tobytes()).hexdigest()[:16], flush=True)
    for name, values in seconds.items():
        print(name, f"median {statistics.median(values):.4f} min {min(values):.4f}")
    print("paired new / base", [round(n / b, 3) for n, b in zip(seconds["new"], seconds["base"], strict=True)],
          "load", os.getloadavg()[0])


if __name__ == "__main__":
    main()
