"""The `verified` decode pass of two source trees, paired (issue 32, vhdec33: the per-payload Python around the
whole kernel): the same encoded cases decoded by a `before` tree (e.g. `git archive main` unpacked in a folder) and
this one, passes alternating between the two, so that the load of a shared machine falls on both alike.

    python bench/decode_tree_ab.py --before DIR [--scenes guitar,winter_fountain] [--presets very-high,medium]
        [--runs 15] [--kernels numba|numpy] [--cache DIR] [--json PATH]

Each scene is encoded once per preset with the encoder's defaults (LOD tree) by this tree, in this process, and
kept pickled under --cache (an encode on 2 shared cores takes a minute; the payloads are what both trees decode).
Two worker processes, one per tree (PYTHONPATH the tree, the same interpreter), each load the cases and decode on
request: a round asks each worker for one `verified` pass of a case (bench/decode_quiet.py's Case.run: every
payload group through format.decode.decode_payloads from the fetcher's VerifiedPayloads, CPU time of the thread),
the order of the trees swapped every round. Before the rounds both workers hash every texel, range and palette byte
of a pass (decode_quiet's Case.texels: bytes, VerifiedPayloads and a payload at a time must agree within a tree),
and the two digests must be equal: the same texels, bit for bit. --kernels numba: the `fast` extra's kernels as
decode_jit.install() installs them (decode_quiet._numba_kernel); numpy: transport's numpy path.

Prints, per case, each tree's median pass (ms), M splats/s and the ratio before / after (above 1: after is faster),
with the median of the per-round ratios; one JSON object on stdout (and in --json). With --stages each pass is also
split as bench/decode_stages.py splits it (each tree's own decode_stages.py). --before with this same tree is an A/A
check of the harness (vhdec33, load 3.4-3.8: 0.94-1.00x).
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import pickle
import statistics
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.join(HERE, "..")


def _encode_cached(cache: str, scene: str, preset: str) -> str:
    """The pickled MemoryStore of `scene` (a name of decode_quiet.SCENES, or name=path) at `preset` (encoded by this
    tree once, then read from `cache`), or the reason it was skipped."""
    scene, _, where = scene.partition("=")
    path = os.path.join(cache, f"{scene}__{preset}.pkl")
    if not os.path.exists(path):
        sys.path.insert(0, HERE)
        sys.path.insert(0, ROOT)
        import decode_quiet  # noqa: PLC0415  (bench/: its encode)
        _, _, store, cpu = decode_quiet.encode(scene, preset, where or None)
        if isinstance(store, str):
            return store
        with open(path + ".part", "wb") as f:
            pickle.dump(store, f)
        os.replace(path + ".part", path)
        print(f"encoded {scene} {preset} in {cpu:.1f} CPU s", file=sys.stderr, flush=True)
    return path


def worker(kernels: str, tree: str) -> None:
    """`tree`'s decoder (its bench/decode_quiet.py, which puts the tree first on sys.path): reads commands from stdin,
    a line each ("load PATH", "digest", "run N", "quit"), answers one JSON line each."""
    sys.path.insert(0, os.path.join(tree, "bench"))
    import decode_quiet  # noqa: PLC0415  (this tree's bench/decode_quiet.py)

    if kernels == "numba":
        got, why = decode_quiet._numba_kernel()
        if got is None:
            raise SystemExit(f"numba kernels: {why}")
        decode_quiet._use(got)
    else:
        decode_quiet._use(None)
    stages = None
    if os.environ.get("DECODE_TREE_AB_STAGES") and kernels == "numba":  # --stages: decode_stages.py's split
        import decode_stages  # noqa: PLC0415  (this tree's)

        from splatstream.format import transport  # noqa: PLC0415

        stages = decode_stages.Stages(transport.whole_kernel())
    case = None
    for line in sys.stdin:
        cmd, _, arg = line.strip().partition(" ")
        if cmd == "load":
            with open(arg, "rb") as f:
                case = decode_quiet.Case(pickle.load(f))
            answer = {"splats": case.splats, "payloads": case.payloads}
        elif cmd == "digest":
            h = hashlib.sha256()
            for b in case.texels():
                h.update(len(b).to_bytes(8, "little"))
                h.update(b)
            case.run("verified")  # a warm pass
            answer = {"sha256": h.hexdigest()}
        elif cmd == "run":
            answer = {"s": [], "stages": []}
            for _ in range(int(arg or 1)):
                if stages is not None:
                    stages.reset()
                answer["s"].append(case.run("verified"))
                if stages is not None:
                    answer["stages"].append(dict(stages.spent))
        else:
            return
        print(json.dumps(answer), flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", required=True, help="the other tree (a folder with splatstream/ and bench/)")
    ap.add_argument("--after", default=ROOT, help="default: this tree")
    ap.add_argument("--scenes", default="guitar,winter_fountain")
    ap.add_argument("--presets", default="very-high,medium,high")
    ap.add_argument("--runs", type=int, default=15, help="rounds (each: one pass of each tree)")
    ap.add_argument("--passes", type=int, default=1, help="passes a tree a round (each timed alone)")
    ap.add_argument("--kernels", default="numba", choices=("numba", "numpy"))
    ap.add_argument("--cache", default="/tmp/decode_tree_ab_cache", help="pickled encodes")
    ap.add_argument("--stages", action="store_true", help="with numba: each pass split as bench/decode_stages.py "
                    "splits it (zstd, plan, call, kernel, views; rest = the pass less those), medians")
    ap.add_argument("--json")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args.worker, args.before)
        return
    os.makedirs(args.cache, exist_ok=True)
    trees = {"before": os.path.abspath(args.before), "after": os.path.abspath(args.after)}
    procs = {}
    for name, tree in trees.items():
        # the tree first; what PYTHONPATH held after it (a site folder of wheels on the GPU machine, say)
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p for p in (tree, os.environ.get("PYTHONPATH")) if p))
        if args.stages:
            env["DECODE_TREE_AB_STAGES"] = "1"
        procs[name] = subprocess.Popen([sys.executable, os.path.abspath(__file__), "--before", tree, "--worker",
                                        args.kernels],
                                       stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env, cwd=tree)

    def ask(name: str, line: str) -> dict:
        p = procs[name]
        p.stdin.write(line + "\n")
        p.stdin.flush()
        got = p.stdout.readline()
        if not got:
            raise SystemExit(f"the {name} tree's worker ended")
        return json.loads(got)

    rows = []
    try:
        for scene in args.scenes.split(","):
            for preset in args.presets.split(","):
                path = _encode_cached(args.cache, scene, preset)
                if not path.endswith(".pkl"):
                    print(f"{scene} {preset}: skipped: {path}", file=sys.stderr)
                    continue
                info = {name: ask(name, f"load {path}") for name in procs}
                digests = {name: ask(name, "digest")["sha256"] for name in procs}
                if digests["before"] != digests["after"]:
                    raise SystemExit(f"{scene} {preset}: the trees decode to other texels: {digests}")
                times = {name: [] for name in procs}
                split = {name: [] for name in procs}
                ratios = []
                for r in range(args.runs):
                    order = ("before", "after") if r % 2 == 0 else ("after", "before")
                    answers = {name: ask(name, f"run {args.passes}") for name in order}
                    got = {name: statistics.median(a["s"]) for name, a in answers.items()}
                    for name in order:
                        times[name].append(got[name])
                        for t, st in zip(answers[name]["s"], answers[name]["stages"], strict=False):  # no stages: none
                            split[name].append(st | {"rest": t - sum(st.values())})
                    ratios.append(got["before"] / got["after"])
                splats = info["after"]["splats"]
                med = {name: statistics.median(v) for name, v in times.items()}
                row = {"scene": scene.partition("=")[0], "preset": preset, "splats": splats,
                       "payloads": info["after"]["payloads"],
                       "texels_sha256": digests["after"],
                       "pass_ms": {name: round(v * 1e3, 3) for name, v in med.items()},
                       "m_splats_s": {name: round(splats / v / 1e6, 2) for name, v in med.items()},
                       "speedup_of_medians": round(med["before"] / med["after"], 3),
                       "speedup_median_of_rounds": round(statistics.median(ratios), 3),
                       "load_average": os.getloadavg()}
                if args.stages:
                    row["stages_ms"] = {name: {k: round(statistics.median(st[k] for st in v) * 1e3, 3)
                                               for k in v[0]} for name, v in split.items()}
                rows.append(row)
                print(f"{row['scene']:>16} {preset:>20}: before {row['pass_ms']['before']:7.3f} ms "
                      f"({row['m_splats_s']['before']:5.2f} M/s) after {row['pass_ms']['after']:7.3f} ms "
                      f"({row['m_splats_s']['after']:5.2f} M/s): {row['speedup_of_medians']:.3f}x "
                      f"(rounds {row['speedup_median_of_rounds']:.3f}x), load {os.getloadavg()[0]:.2f}",
                      file=sys.stderr, flush=True)
                for name, st in row.get("stages_ms", {}).items():
                    print(f"{'':>38}{name:>6}: " + " ".join(f"{k} {v:.3f}" for k, v in st.items()), file=sys.stderr,
                          flush=True)
    finally:
        for p in procs.values():
            try:
                p.stdin.write("quit\n")
                p.stdin.close()
            except OSError:
                pass
            p.wait()
    sys.path.insert(0, HERE)
    import decode_quiet  # noqa: PLC0415
    report = {"bench": "bench/decode_tree_ab.py", "argv": sys.argv[1:],
              "date_utc": time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime()), "cpu": decode_quiet._cpu_name(),
              "python": sys.version.split()[0], "kernels": args.kernels, "runs": args.runs,
              "load_average_end": os.getloadavg(), "cases": rows}
    text = json.dumps(report, indent=1)
    print(text)
    if args.json:
        with open(args.json, "w") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
