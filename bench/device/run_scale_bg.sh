#!/bin/bash
# A bench_scale run longer than one device call (a 60M-splat scene on 1 worker takes about 17 minutes), carried
# over several calls on the same warm machine: `start` launches it in the background (its own session, so the
# call's end does not stop it), `wait` waits up to SECONDS for its JSON and copies its JSON and log to $OUT.
# Run after bench/device/run_scale.sh on the same machine (the wheels installed, the scene kept under /tmp/bs).
# Usage: bash bench/device/run_scale_bg.sh start SPLATS WORKERS NAME
#        bash bench/device/run_scale_bg.sh wait NAME SECONDS
set -u
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT" /tmp/bg
case ${1:?start or wait} in
  start)
    splats=${2:?splats} workers=${3:?workers} name=${4:?name}
    setsid nohup python3 bench/bench_scale.py --splats "$splats" --workers "$workers" --generator synthetic \
      --memory-per-worker 3GB --scenes /tmp/bs --keep --json "/tmp/bg/$name.json" > "/tmp/bg/$name.log" 2>&1 \
      < /dev/null &
    echo "started $name (pid $!)"
    ;;
  wait)
    name=${2:?name} seconds=${3:?seconds}
    end=$((SECONDS + seconds))
    while [ ! -e "/tmp/bg/$name.json" ] && [ $SECONDS -lt $end ]; do sleep 5; done
    cp "/tmp/bg/$name.log" "$OUT/" 2>/dev/null
    if [ -e "/tmp/bg/$name.json" ]; then cp "/tmp/bg/$name.json" "$OUT/"; tail -3 "/tmp/bg/$name.log"
    else echo "$name still running after ${seconds}s:"; tail -c 600 "/tmp/bg/$name.log"; pgrep -af bench_scale | head -3
    fi
    ;;
esac
