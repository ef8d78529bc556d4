#!/bin/bash
# usage: phases.sh SCENE LABEL ROUNDS VARIANTS...
scene=$1; label=$2; rounds=$3; shift 3
for r in $(seq $rounds); do for v in "$@"; do
  out=$(cd /work/wt_edges31 && PYTHONPATH=/tmp/edges31_v_$v nice -n 19 /work/main/.venv/bin/python bench/lod_tree_phases.py $scene 2>&1 | tr '\n' ' ')
  echo "$label $v r$r $out" >> /tmp/edges31_res/phases.txt
done; done
