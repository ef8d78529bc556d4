# gerr17: the probe on the nine held-out scenes (main's 1.16 default encodes from psnr16, /tmp/psnr16_ours)
cd /work/wt_gerr17
for s in statue-angel statue-angel-kneeling statue-angel-with-candlestick statue-massa statue-narcissus statue-st-peter statue-trumpet guitar winter_fountain; do
  echo "$(date -u +%T) $s load $(cut -d' ' -f1-3 /proc/loadavg)"
  PYTHONPATH=. nice -n 19 /work/main/.venv/bin/python bench/probe_error_steps.py /tmp/psnr16_ours/$s \
    bench/results/lod_vs_peers_manifest31/$s.json --budgets 0.02,0.06,0.25,0.5,1.0 --variants f32,lin255,log16,log1 \
    --out bench/results/gerr17/probe_$s.json $EXTRA
done
echo "$(date -u +%T) done"
