"""edges31: per level of the default tree, its splats, target and how many groups of 1, 2, 3, 4 ... members.

    cd REPO && PYTHONPATH=.:bench python bench/results/edges31/scripts/group_sizes.py SCENE
"""
import sys

import numpy as np
from encode_phases import InlineExecutor  # bench/ on PYTHONPATH

import splatstream.lod as lod
import splatstream.lod_groups as lg
from splatstream.io import read_gaussians

orig_group = lg.group_ids_of


def group(inputs, target, rule=lg.DEFAULT_RULE, *a, **k):
    n = len(inputs["positions"])
    ids = orig_group(inputs, target, rule, *a, **k)
    print(n, target, np.bincount(np.bincount(ids))[1:].tolist())
    return ids


lod.group_ids_of = group
lod.ThreadPoolExecutor = InlineExecutor
lod.build_tiles(read_gaussians(sys.argv[1]), merge="auto", reorder_input=True)
