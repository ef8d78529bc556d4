"""Named presets against the peers' points (issue 15's "Done when"), from `splatstream eval` reports.

    python bench/preset_dominance.py REPORT.json ... [--markdown OUT.md] [--table OUT.md] [--plot OUT.png]

Each REPORT.json is one scene's eval (bench/run_eval.sh writes <scene>.json; reports of the same scene are merged,
later files winning on equal labels). For every peer point (rows of kind `compare`: splat-transform's
compressed.ply, SPZ, SOG) it names the smallest preset (rows of kind `preset`) whose mean PSNR is at least the
peer's, and the ratio of their disk bytes; the goal is a ratio of at most 0.90. Where it is not met the shortfall
is stated both ways: the smallest ratio at the peer's PSNR, and the best preset at 0.90 of its bytes or fewer with
its PSNR deficit. The plot has one panel per scene (the eval's rate-distortion plot of the presets and peers).
"""
from __future__ import annotations

import argparse
import json
import os
from collections import defaultdict

GOAL = 0.90


def _name(report: dict) -> str:
    return os.path.basename(report["input"]["path"])


def load(paths: list[str]) -> dict[str, dict]:
    scenes: dict[str, dict] = defaultdict(lambda: {"presets": {}, "peers": {}, "input": None})
    for path in paths:
        report = json.load(open(path))
        s = scenes[_name(report)]
        s["input"] = report["input"]
        for row in report["rows"]:
            if row["kind"] == "compare":
                s["peers"][row["label"]] = row
            elif row["kind"] == "preset":
                s["presets"][row["label"]] = row
    return dict(scenes)


def _psnr(row: dict) -> float:
    return float("inf") if row["psnr_mean"] is None else float(row["psnr_mean"])


def best_within(presets: dict[str, dict], budget: float) -> tuple[str, float, float] | None:
    """The preset with the highest PSNR at `budget` B/splat or fewer: (name, bytes, PSNR)."""
    fits = [(_psnr(r), -r["disk_bytes_per_splat"], n) for n, r in presets.items()
            if r["disk_bytes_per_splat"] <= budget]
    if not fits:
        return None
    p, neg_b, n = max(fits)
    return n, -neg_b, p


def verdicts(s: dict) -> list[dict]:
    out = []
    for label, peer in s["peers"].items():
        peer_b, peer_p = peer["disk_bytes_per_splat"], _psnr(peer)
        ok = sorted((r["disk_bytes_per_splat"], -_psnr(r), n) for n, r in s["presets"].items() if _psnr(r) >= peer_p)
        v = {"peer": label, "peer_bytes": peer_b, "peer_psnr": peer_p, "preset": None, "ratio": None, "met": False,
             "best_within_goal": best_within(s["presets"], GOAL * peer_b)}
        if ok:
            b, neg_p, n = ok[0]
            v.update(preset=n, preset_bytes=b, preset_psnr=-neg_p, ratio=b / peer_b, met=b / peer_b <= GOAL)
        out.append(v)
    return out


def markdown(scenes: dict[str, dict]) -> str:
    lines = ["| scene | peer | peer B/splat | peer PSNR dB | smallest preset at >= its PSNR | ratio | goal <= 0.90 |",
             "|---|---|---|---|---|---|---|"]
    for name, s in scenes.items():
        short = f"{name} ({s['input']['splats']:,}, SH{s['input']['sh_degree']})"
        for v in verdicts(s):
            found = "none" if v["preset"] is None else \
                f"{v['preset']} ({v['preset_bytes']:.2f} B, {v['preset_psnr']:.2f} dB)"
            ratio = "" if v["ratio"] is None else f"{v['ratio']:.2f}"
            if v["met"]:
                verdict = "met"
            else:
                best = v["best_within_goal"]
                verdict = "**not met**: at <= 0.90 of its bytes the best is " + \
                    ("none" if best is None else f"{best[0]} ({best[1]:.2f} B, {best[2]:.2f} dB, "
                     f"{best[2] - v['peer_psnr']:+.2f} dB)")
            lines.append(f"| {short} | {v['peer']} | {v['peer_bytes']:.2f} | {v['peer_psnr']:.2f} | {found} | "
                         f"{ratio} | {verdict} |")
    return "\n".join(lines)


def preset_table(scenes: dict[str, dict]) -> str:
    """Disk B/splat and mean PSNR of every preset and peer, one column per scene."""
    from splatstream.format.presets import PRESETS

    def cell(r: dict | None) -> str:
        if r is None:
            return "not run"
        return f"{r['disk_bytes_per_splat']:.2f} B, " + \
            ("lossless" if r["psnr_mean"] is None else f"{r['psnr_mean']:.1f} dB")

    head = [f"{os.path.splitext(n)[0]} ({s['input']['splats']:,}, SH{s['input']['sh_degree']})"
            for n, s in scenes.items()]
    lines = ["| preset | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for p in PRESETS:
        lines.append(f"| {p} | " + " | ".join(cell(s["presets"].get(p)) for s in scenes.values()) + " |")
    for peer in sorted({k for s in scenes.values() for k in s["peers"]}):
        lines.append(f"| {peer.replace('st-', 'splat-transform ')} | "
                     + " | ".join(cell(s["peers"].get(peer)) for s in scenes.values()) + " |")
    return "\n".join(lines)


def plot(scenes: dict[str, dict], out: str) -> None:
    """One panel per scene (splatstream.evaluate's rate-distortion plot of its presets and peers), in a grid."""
    import tempfile

    from PIL import Image

    from splatstream.evaluate import plot_rate_distortion

    panels = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, s in enumerate(scenes.values()):
            report = {"input": s["input"], "rows": list(s["presets"].values()) + list(s["peers"].values())}
            path = os.path.join(tmp, f"{i}.png")
            plot_rate_distortion(report, path, size=(720, 480))
            with Image.open(path) as im:
                panels.append(im.convert("RGB"))
    cols = min(2, len(panels))
    rows = (len(panels) + cols - 1) // cols
    w, h = panels[0].size
    grid = Image.new("RGB", (cols * w, rows * h), "white")
    for i, panel in enumerate(panels):
        grid.paste(panel, ((i % cols) * w, (i // cols) * h))
    grid.save(out)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("reports", nargs="+")
    ap.add_argument("--markdown")
    ap.add_argument("--plot")
    ap.add_argument("--table", help="also write the presets' and peers' bytes and PSNR per scene (Markdown) here")
    args = ap.parse_args()
    scenes = load(args.reports)
    text = markdown(scenes)
    print(text)
    if args.markdown:
        open(args.markdown, "w").write(text + "\n")
    if args.table:
        open(args.table, "w").write(preset_table(scenes) + "\n")
    if args.plot:
        plot(scenes, args.plot)


if __name__ == "__main__":
    main()
