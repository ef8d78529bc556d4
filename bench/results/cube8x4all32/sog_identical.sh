#!/bin/bash
# cube8x4all32: SOG-made inputs bit-identical, main (fecd8b2, no measure for these presets) against the branch
IN=/tmp/evalrefresh32_in; O=/tmp/cube8x4all32_sog
dig() { (cd "$1" && find . -type f | LC_ALL=C sort | while read f; do echo "$f $(sha256sum < "$f" | cut -c1-64)"; done) | sha256sum | cut -c1-16; }
for s in $IN/statue-*.ply /tmp/step32_w/flowers.ply /tmp/step32_w/playbot.ply /tmp/heldout57_eval/playcanvas-logo.ply; do
  n=$(basename $s .ply)
  for p in medium-low-12bit medium-low-palette low-plus; do
    for side in main wt; do
      root=/work/main; [ $side = wt ] && root=/work/wt_cube8x4all32
      rm -rf $O/out_$side
      (cd $root && nice -n 19 env PYTHONPATH=$root /work/main/.venv/bin/python -m cli.main encode "$s" $O/out_$side --preset $p --no-lod > $O/${n}_${p}_$side.log 2>&1)
    done
    echo "$n $p main $(dig $O/out_main) branch $(dig $O/out_wt) $(grep -o "$p rotations: [^)]*)" $O/${n}_${p}_wt.log)"
  done
done
echo "all done $(date -u +%T)"
