"""edges31: per level of the default tree, the rows each round costs and the matching's size (biker, pools inline).

    cd REPO && PYTHONPATH=.:bench python bench/results/edges31/scripts/rounds.py SCENE
"""
import sys
import time

from encode_phases import InlineExecutor  # bench/ on PYTHONPATH

import splatstream.lod as lod
import splatstream.lod_groups as lg
from splatstream.io import read_gaussians

log = []
orig_cost, orig_pairs, orig_group = lg.edge_costs_at, lg._greedy_pairs, lg.group_ids_of


def cost(out, rows, *a, **k):
    t = time.process_time()
    orig_cost(out, rows, *a, **k)
    log.append(("cost", len(rows), len(out), time.process_time() - t))


def pairs(count, i, j, c, quota, *a):
    t = time.process_time()
    r = orig_pairs(count, i, j, c, quota, *a)
    log.append(("match", count, quota, len(r[0]), len(i), time.process_time() - t))
    return r


def group(inputs, target, rule=lg.DEFAULT_RULE, *a, **k):
    log.append(("LEVEL", len(inputs["positions"]), target, rule.neighbours))
    return orig_group(inputs, target, rule, *a, **k)


lg.edge_costs_at, lg._greedy_pairs, lg.group_ids_of, lod.group_ids_of = cost, pairs, group, group
lod.ThreadPoolExecutor = InlineExecutor
lod.build_tiles(read_gaussians(sys.argv[1]), merge="auto", reorder_input=True)
for e in log:
    print(*e)
