cd /tmp/rootcut31_merged
PY=/work/main/.venv/bin/python
mkdir -p /tmp/rootcut31_enc16 /tmp/rootcut31_m16runs
for s in statue-angel statue-angel-kneeling statue-angel-with-candlestick statue-massa statue-narcissus statue-st-peter statue-trumpet guitar winter_fountain; do
  src=/tmp/fill31_full/$s.ply; [ -f $src ] || src=/tmp/rootcut31_full/$s.ply
  echo "$(date -u +%T) $s"
  [ -f /tmp/rootcut31_enc16/$s/manifest.msgpack ] || PYTHONPATH=. nice -n 19 $PY -m cli.main encode $src /tmp/rootcut31_enc16/$s -q
  PYTHONPATH=. nice -n 19 $PY bench/small_budget_bytes.py /tmp/rootcut31_enc16/$s \
    /work/wt_rootcut31/bench/results/lod_vs_peers_manifest31/$s.json --budgets 0.02,0.06,0.25,0.5 --compare "--fill-root-kb 0|--fill-root-kb 512" \
    --out /tmp/rootcut31_m16runs/bytes16_${s}.json 2>&1 | grep -o "^.*x (payloads" 
done
echo "$(date -u +%T) done"
