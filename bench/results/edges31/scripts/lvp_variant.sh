#!/bin/bash
# usage: lvp.sh VARIANT SCENES [extra args]; cwd = the variant's copy, so `python -m cli` runs its code
v=$1; scenes=$2; shift 2
cd /tmp/edges31_v_$v && PYTHONPATH=/tmp/edges31_v_$v nice -n 19 /work/main/.venv/bin/python /work/wt_edges31/bench/lod_vs_peers.py --skip-peers \
  --peers-from /work/wt_edges31/bench/results/lod_vs_peers_viewscale --cache-dir /tmp/edges31_cache --our-scene-dir /tmp/edges31_ours_$v \
  --out-dir /tmp/edges31_lvp_$v --scenes $scenes "$@"
