# gerr17: where the screen-space error binds (no budget: 100 %, smaller windows = farther cameras), with pictures
cd /work/wt_gerr17
for s in statue-angel statue-angel-kneeling statue-angel-with-candlestick statue-massa statue-narcissus statue-st-peter statue-trumpet guitar winter_fountain; do
  echo "$(date -u +%T) $s load $(cut -d' ' -f1-3 /proc/loadavg)"
  PYTHONPATH=. nice -n 19 /work/main/.venv/bin/python bench/probe_error_steps.py /tmp/psnr16_ours/$s \
    bench/results/lod_vs_peers_manifest31/$s.json --budgets 1.0 --sizes 48,96,192 --variants f32,lin255,log16 \
    --ref /tmp/psnr16_cache/$s/full.ply --out bench/results/gerr17/sse_$s.json
done
echo "$(date -u +%T) done"
