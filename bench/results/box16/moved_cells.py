"""The cells of BENCHMARKS.md "Format 1.16" whose cut moved (issue 31, branch box16): per moved view, the tiles drawn
by 1.15 only and by 1.16 only (id, level, splats), and the drawn splats and bytes of each. Reads before/ and after/
and the encoded scenes (ENC/before/SCENE, ENC/after/SCENE): `python bench/results/box16/moved_cells.py ENC`."""
import json
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))))
from splatstream.store import load_manifest  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))


def main() -> None:
    enc = sys.argv[1]
    out = []
    for f in sorted(os.listdir(os.path.join(HERE, "after"))):
        scene = f.removesuffix("_np.json")
        a = json.load(open(os.path.join(HERE, "after", f)))
        b = json.load(open(os.path.join(HERE, "before", f)))
        tiles = None
        for ra, rb in zip(a["rows"], b["rows"], strict=True):
            for i, (x, y) in enumerate(zip(ra["views"], rb["views"], strict=True)):
                if sorted(x["draw"]) == sorted(y["draw"]) and x["drawn_tile_bytes"] == y["drawn_tile_bytes"]:
                    continue
                if tiles is None:
                    tiles = {t.id: t for t in load_manifest(os.path.join(enc, "after", scene)).tiles}
                only15 = sorted(set(y["draw"]) - set(x["draw"]))
                only16 = sorted(set(x["draw"]) - set(y["draw"]))
                out.append({"scene": scene, "fraction": ra["fraction"], "budget": ra["budget"], "view": i,
                            "only_1_15": [(t, tiles[t].level, tiles[t].splats) for t in only15],
                            "only_1_16": [(t, tiles[t].level, tiles[t].splats) for t in only16],
                            "drawn_splats": [y["drawn_splats"], x["drawn_splats"]],
                            "drawn_tile_bytes": [y["drawn_tile_bytes"], x["drawn_tile_bytes"]],
                            "downloaded": [y["downloaded"], x["downloaded"]]})
                print(json.dumps(out[-1]))
    json.dump(out, open(os.path.join(HERE, "moved.json"), "w"), indent=1)


if __name__ == "__main__":
    main()
