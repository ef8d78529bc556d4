#!/bin/bash
# usage: mkvar NAME 'GroupRule(...)' ['GroupRule(...)' for the first merged level]
set -e
d=/tmp/edges31_v_$1
first=${3:-$2}
rm -rf $d; mkdir -p $d
cp -r /work/wt_edges31/splatstream /work/wt_edges31/cli $d/
find $d -name __pycache__ -prune -exec rm -rf {} +
sed -i "s/^AUTO_RULE = GroupRule(.*)\$/AUTO_RULE = $2/; s/^AUTO_FIRST_RULE = GroupRule(.*)\$/AUTO_FIRST_RULE = $first/" $d/splatstream/lod.py
grep -n "^AUTO_RULE\|^AUTO_FIRST_RULE" $d/splatstream/lod.py
