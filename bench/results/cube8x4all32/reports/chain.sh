#!/bin/bash
# cube8x4all32: the other half-turn presets, wired (measured choice) and with rotation=norm8x4 (half turns), one report per scene
cd /tmp/cube8x4all32_snap
R=/work/shared/data/real; O=/tmp/cube8x4all32_eval
P="medium-low-9bit,medium-low-12bit,medium-low-palette,low-plus-9bit,low-plus,low-plus-9bit-sh6,low-plus-9bit-sh5,low-plus-10bit-cb8"
V=""
for p in ${P//,/ }; do V="$V ht-$p:$p,rotation=norm8x4"; done
run() {  # name input
  echo "== $1 $(date -u +%T) load $(cut -d' ' -f1 /proc/loadavg)"
  /usr/bin/time -f "$1 %U user %S sys %e wall" nice -n 19 env PYTHONPATH=. /work/main/.venv/bin/python -m cli.main eval "$2" --presets $P --variants $V --views 8 --size 512x512 --renderer gl --json $O/$1.json --quiet > $O/$1.log 2>&1
  tail -2 $O/$1.log
}
run fruit $R/fruit_drops_sh3.ply
run guitar $R/guitar.compressed.ply
run lodtile $R/lod_tile_sh3_zero_rest.ply
run donut $R/donut_sh0_no_normals.ply
run winter_fountain $R/winter_fountain.splat
run biker $R/biker.compressed.ply
echo "all done $(date -u +%T)"
