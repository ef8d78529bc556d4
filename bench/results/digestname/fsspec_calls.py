"""Encode scenes to memory:// through the CLI in this process, counting the object store's writes, copies and
deletes, and every object name ever created; dump the final objects to a directory for diff -r.
usage: PYTHONPATH=TREE python digestname_fsspec.py OUTDIR JSON"""
import json
import os
import sys
from collections import Counter

from fsspec.implementations.memory import MemoryFileSystem

from cli.main import main

calls: Counter = Counter()
created: set[str] = set()


def counted(name, fn, record=False):
    def wrapper(self, path, *a, **k):
        calls[name] += 1
        if record:
            created.add(str(path))
        return fn(self, path, *a, **k)
    return wrapper


for name in ("pipe_file", "cp_file", "rm_file", "_rm", "rm", "mv", "copy", "open"):
    if hasattr(MemoryFileSystem, name):
        setattr(MemoryFileSystem, name, counted(name, getattr(MemoryFileSystem, name), name == "pipe_file"))

R = "/work/shared/data/real"
out, report = sys.argv[1], {}
for scene, path in (("guitar", f"{R}/guitar.compressed.ply"), ("donut", f"{R}/donut_sh0_no_normals.ply"),
                    ("massa", f"{R}/statues/massa.sog")):
    for mode in ("short", "whole"):
        calls.clear()
        created.clear()
        url = f"memory://digestname/{scene}_{mode}"
        rc = main(["encode", path, url, "-q"] + (["--no-short-digests"] if mode == "whole" else []))
        fs = MemoryFileSystem()
        root = f"/digestname/{scene}_{mode}"
        final = sorted(fs.find(root))
        for p in final:
            dest = os.path.join(out, f"{scene}_{mode}", os.path.relpath(p, root))
            os.makedirs(os.path.dirname(dest), exist_ok=True)
            with open(dest, "wb") as f:
                f.write(fs.cat_file(p))
        names = [os.path.basename(p) for p in created]
        report[f"{scene}_{mode}"] = {
            "rc": rc, "calls": dict(calls), "objects_created": len(created), "objects_final": len(final),
            "created_64hex_payloads": sum(1 for n in names if len(n) == 68 and n.endswith(".bin")),
            "created_32hex_payloads": sum(1 for n in names if len(n) == 36 and n.endswith(".bin")),
        }
        print(scene, mode, report[f"{scene}_{mode}"], flush=True)
with open(sys.argv[2], "w") as f:
    json.dump(report, f, indent=1, sort_keys=True)
