#!/bin/bash
# cube32: medium-low's rows (the measured rotation choice) with each stored report's cameras (8 x 512; playbot and the logo also 4 x 384)
cd /tmp/cube32_snap
IN=/tmp/evalrefresh32_in; R=/work/shared/data/real; O=/tmp/cube32_eval
run() {  # name input views size
  echo "== $1 $(date -u +%T) load $(cut -d' ' -f1 /proc/loadavg)"
  /usr/bin/time -f "$1 %U user %S sys %e wall" nice -n 19 env PYTHONPATH=. /work/main/.venv/bin/python -m cli.main eval "$2" --presets medium-low --views $3 --size $4 --renderer gl --json $O/$1.json --quiet > $O/$1.log 2>&1
  tail -3 $O/$1.log
}
run fruit $R/fruit_drops_sh3.ply 8 512x512
run guitar $R/guitar.compressed.ply 8 512x512
run statue-massa $IN/statue-massa.ply 8 512x512
run lodtile $R/lod_tile_sh3_zero_rest.ply 8 512x512
run donut $R/donut_sh0_no_normals.ply 8 512x512
run winter_fountain $R/winter_fountain.splat 8 512x512
run biker $R/biker.compressed.ply 8 512x512
for s in angel angel-with-candlestick angel-kneeling trumpet narcissus st-peter; do run statue-$s $IN/statue-$s.ply 8 512x512; done
run playcanvas-logo /tmp/heldout57_eval/playcanvas-logo.ply 8 512x512
run playcanvas-logo_4x384 /tmp/heldout57_eval/playcanvas-logo.ply 4 384x384
run playbot /tmp/step32_w/playbot.ply 8 512x512
run flowers /tmp/step32_w/flowers.ply 8 512x512
run playbot_4x384 /tmp/step32_w/playbot.ply 4 384x384
echo "all done $(date -u +%T)"
