"""Why today's page rule wants a page at a small budget (branch bandpage): per view, the heads whose page it wanted,
and whether each head's box crossed the frustum (children may all lie outside) or lay inside it.

    PYTHONPATH=. python bench/results/bandpage/probe_page_heads.py PAGED_SCENE LOD_VS_PEERS.json --budgets 0.02 OUT.json
"""
import json
import sys

import numpy as np

sys.path.insert(0, "bench")
sys.path.insert(0, ".")
import small_budget_bytes  # noqa: E402

import client_gl.stream.engine as eng  # noqa: E402
from client_gl.stream.selection import boxes_inside_frustum, frustum_planes  # noqa: E402

LOG = []
orig = eng.pages_the_budget_can_use


def wrapped(a, view, cost, root, sel, heads, opts, *args, **kw):
    wanted, waiting = orig(a, view, cost, root, sel, heads, opts, *args, **kw)
    h = np.asarray(heads, np.intp)
    if len(h):
        planes = frustum_planes(view.wide_frustum[1], 1.0, view.wide_frustum[2])
        inside = boxes_inside_frustum(a.box_corners[h], planes)
        for i in np.flatnonzero(wanted | waiting).tolist():
            LOG.append((int(a.ids[h[i]]), bool(inside[i]), bool(wanted[i])))
    return wanted, waiting


eng.pages_the_budget_can_use = wrapped
orig_measure = small_budget_bytes.measure_view
out = []


def measure(*args, **kw):
    LOG.clear()
    r = orig_measure(*args, **kw)
    heads = {}
    for hid, ins, _wanted in LOG:
        heads.setdefault(hid, set()).add("inside" if ins else "crossing")
    out.append({"n_pages": r["n_pages"], "heads": {str(k): sorted(v) for k, v in heads.items()}})
    return r


small_budget_bytes.measure_view = measure
small_budget_bytes.main(sys.argv[1:-1])
json.dump(out, open(sys.argv[-1], "w"), indent=1)
for o in out:
    kinds = [",".join(v) for v in o["heads"].values()]
    print(o["n_pages"], "pages;", len(kinds), "heads wanted:", {k: kinds.count(k) for k in set(kinds)})
