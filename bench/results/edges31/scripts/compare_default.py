"""edges31: lod_vs_peers out dirs against the default's stored rows and best peers (BENCHMARKS.md, the table of
"The CPU refinement at 0.4x its CPU"): change, margin before and after, points falling below the peer or under 1 dB.

    python compare_default.py OUT_DIR...
"""
import json
import os
import re
import statistics
import sys

rows = {}
scene = None
txt = open(os.path.join(os.path.dirname(__file__), "../../../../BENCHMARKS.md")).read()
sec = txt[txt.index("### The CPU refinement at 0.4x its CPU"):]
sec = sec[:sec.index("**The 48 points")]
for line in sec.splitlines():
    m = re.match(r"\| (\S.*?)? \| (\d+)% \(([\d,]+)\) \| ([\d.]+) \| [\d.]+ \| [\d.]+ \| [-+\d.]+ \| ([\d.]+) \(", line)
    if not m:
        continue
    if m.group(1):
        scene = m.group(1).split(" (")[0]
    rows[(scene, int(m.group(3).replace(",", "")))] = (int(m.group(2)), float(m.group(4)), float(m.group(5)))
out = []
for d in sys.argv[1:]:
    for f in sorted(os.listdir(d)):
        if not f.endswith(".json"):
            continue
        j = json.load(open(os.path.join(d, f)))
        for o in j["ours"]:
            key = (j["scene"], o["budget"])
            if key in rows:
                pct, default, peer = rows[key]
                out.append((j["scene"], pct, default, o["psnr_mean"], round(o["psnr_mean"] - default, 3), peer,
                            round(default - peer, 2), round(o["psnr_mean"] - peer, 2)))
for r in out:
    flag = " FLIP-BELOW-PEER" if r[6] > 0 and r[7] < 0 else ""
    flag += " FALLS-UNDER-1dB" if r[6] >= 1 and r[7] < 1 else ""
    print(f"{r[0]:32s} {r[1]:3d}% default {r[2]:.2f} now {r[3]:.3f} change {r[4]:+.3f} peer {r[5]:.2f} "
          f"margin {r[6]:+.2f} -> {r[7]:+.2f}{flag}")
if out:
    ch = [r[4] for r in out]
    print(f"points {len(out)} median change {statistics.median(ch):+.3f} min {min(ch):+.3f} max {max(ch):+.3f}; "
          f">=1 dB above peer: default {sum(r[6] >= 1 for r in out)} now {sum(r[7] >= 1 for r in out)}; "
          f"above peer: default {sum(r[6] > 0 for r in out)} now {sum(r[7] > 0 for r in out)}")
