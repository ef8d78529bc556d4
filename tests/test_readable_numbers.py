"""Numbers a user can read: plurals, 'read' for a local scene, the GPU memory the resident splats use (not the
pool), which B/splat is which, the help of every positional, and eval plot labels that never overlap."""
from __future__ import annotations

import copy
import json
import re

import numpy as np
from conftest import ROOT, run_cli

from cli.commands.view import transfer_and_memory
from splatstream.evaluate import _overlap, place_labels, plot_rate_distortion
from splatstream.progress import count


def test_counts_have_their_plurals():
    assert count(1, "tile") == "1 tile" and count(11, "tile") == "11 tiles" and count(0, "tile") == "0 tiles"
    assert count(1, "leaf", "leaves") == "1 leaf" and count(4, "leaf", "leaves") == "4 leaves"
    assert count(45624, "splat") == "45,624 splats"


def test_view_summary_says_read_for_local_and_reports_resident_memory():
    report = {"bytes_downloaded": 1_800_000, "resident_gpu_bytes": 228_152, "resident_splats": 4721,
              "gpu_budget_bytes": 1024 << 20, "gpu_bytes_peak": 1072480000, "fetch": {"manifest_source": "local"}}
    line = transfer_and_memory(report)
    assert line == "1.80 MB read, GPU 0.2 MiB for 4,721 resident splats (budget 1024 MiB)"
    report["fetch"]["manifest_source"] = "network"
    report["resident_splats"] = 1
    assert transfer_and_memory(report).startswith("1.80 MB downloaded, GPU 0.2 MiB for 1 resident splat (")


def test_view_summary_says_how_many_splats_were_drawn_against_the_budget():
    # playbot's kept tree under --max-splats 3000: level 1 (3,000 splats) drawn, the root (1,873) still resident;
    # the summary gave only the 4,873 resident, which reads as a budget exceeded
    report = {"bytes_downloaded": 116_362, "resident_gpu_bytes": 169_000, "resident_splats": 4873,
              "drawn_splats": 3000, "gpu_budget_bytes": 1024 << 20, "fetch": {"manifest_source": "local"}}
    assert transfer_and_memory(report, 3000) == ("3,000 splats drawn (--max-splats 3,000), 0.12 MB read, GPU 0.2 MiB "
                                                 "for 4,873 resident splats (budget 1024 MiB)")
    assert transfer_and_memory(report).startswith("3,000 splats drawn, 0.12 MB read, ")


def test_view_summary_gives_a_fractional_budget_and_the_bytes_from_the_disk_cache():
    # --gpu-mem-mb 0.5 on the logo: 'GPU 0.5 MiB for 23,784 resident splats (budget 0 MiB)', read as over budget;
    # a second view of a served scene: '0.00 MB downloaded' and nothing about the 0.10 MB the disk cache gave
    report = {"bytes_downloaded": 0, "resident_gpu_bytes": 148_036, "resident_splats": 5436, "drawn_splats": 4833,
              "gpu_budget_bytes": 1 << 19, "fetch": {"manifest_source": "revalidated", "bytes_from_cache": 103_107}}
    assert transfer_and_memory(report) == ("4,833 splats drawn, 0.00 MB downloaded (0.10 MB from the disk cache), "
                                           "GPU 0.1 MiB for 5,436 resident splats (budget 0.5 MiB)")
    report["gpu_budget_bytes"] = int(0.07 * 2**20)
    assert transfer_and_memory(report).endswith("(budget 0.07 MiB)")
    report["gpu_budget_bytes"] = int(1e9) << 20  # `--gpu-mem-mb 1e9` said 'budget 1e+09 MiB' (newuser60)
    assert transfer_and_memory(report).endswith("(budget 1,000,000,000 MiB)")
    report["gpu_budget_bytes"], report["fetch"]["bytes_from_cache"] = 1024 << 20, 0
    assert transfer_and_memory(report).endswith("0.00 MB downloaded, GPU 0.1 MiB for 5,436 resident splats "
                                                "(budget 1024 MiB)")


def test_view_summary_says_a_splat_file_was_read_whole_and_its_tiles_counted(tmp_path):
    # `view guitar.spz --max-splats 30000` said '0.52 MB read' of a 1.40 MB file it had read whole and encoded in
    # memory: the bytes are that encode's tiles
    report = {"bytes_downloaded": 516_856, "resident_gpu_bytes": 600_000, "resident_splats": 31_855,
              "drawn_splats": 29_767, "gpu_budget_bytes": 1024 << 20, "fetch": {"manifest_source": "local"},
              "source": str(ROOT / "tests" / "data" / "real" / "guitar.compressed.ply")}
    assert transfer_and_memory(report).startswith(
        "29,767 splats drawn, 0.52 MB read from its in-memory encode (the file read whole first), GPU ")
    scene = tmp_path / "scene"
    scene.mkdir()
    (scene / "manifest.msgpack").write_bytes(b"")
    report["source"] = str(scene)  # a scene directory's payloads are read as they are
    assert transfer_and_memory(report).startswith("29,767 splats drawn, 0.52 MB read, GPU ")


def test_info_help_describes_its_positional():
    r = run_cli("info", "--help")
    assert r.returncode == 0
    after = r.stdout.split("positional arguments:")[1].split("options:")[0]
    assert "SCENE_DIR" in after and "manifest.msgpack" in after  # named as the usage line names it


def test_encode_and_info_say_which_bytes_per_splat_is_which_in_plain_words(tmp_path):
    r = run_cli("encode", ROOT / "samples" / "donut.ply", tmp_path / "d", "--max-leaf-splats", "100000")
    assert r.returncode == 0, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert ": 45,624 splats, " in last and ", 1 tile, " in last
    assert "B/splat at full detail, " in last and " with all LOD levels)" in last
    r = run_cli("info", tmp_path / "d")
    assert "tiles      1 in 1 level, 1 leaf holding 45,624 splats" in r.stdout
    assert "splats     45,624  SH degree 0" in r.stdout  # '500000' beside '500,000' two lines down on playbot
    assert "  level 0: 1 tile, 45,624 splats, " in r.stdout


def test_info_gives_the_leaf_size_with_separators():
    # playbot's kept tree: 'leaves of at most 251845 splats' (newuser63)
    from cli.commands.info import _lod_line

    lod = {"enabled": True, "max_leaf_splats": 251845, "reduction": 2.537496028288149, "merge": None,
           "viewing_scale_px": None}
    assert _lod_line(lod).endswith("; leaves of at most 251,845 splats, 2.5375x per level")


def test_a_one_splat_scene_gives_its_bytes_per_splat_with_separators(tmp_path):
    # newuser63: a 1-splat scene's encode said '0.00 MB on disk (105.00 B/splat at full detail, 2149.00 with all LOD
    # levels), 4148.00 B/splat on the GPU' and info '4148.00 B/splat' where every other number has its separators
    from splatstream.ply import read_gaussians_ply, write_gaussians_ply

    write_gaussians_ply(read_gaussians_ply(ROOT / "samples" / "donut.ply").subset(np.arange(1)), tmp_path / "one.ply")
    r = run_cli("encode", tmp_path / "one.ply", tmp_path / "one")
    assert r.returncode == 0, r.stderr
    info = json.loads(run_cli("info", tmp_path / "one", "--json").stdout)
    disk, gpu = info["bytes_on_disk"], info["gpu_bytes"]
    assert 1000 < disk < 10_000 and 1000 < gpu  # a manifest and one tile's planes for one splat
    last = r.stderr.strip().splitlines()[-1]
    assert f"1 tile, {disk:,} bytes on disk (" in last, last
    assert f", {disk:,}.00 with all LOD levels), {gpu:,}.00 B/splat on the GPU" in last, last
    text = run_cli("info", tmp_path / "one").stdout
    assert f"on disk    {disk:,} bytes ({disk:,}.00 B/splat, all levels)" in text, text
    assert f"GPU        {gpu:,} bytes ({gpu:,}.00 B/splat, full detail)" in text, text
    assert re.search(r"  position  \S+ +GPU \d,\d{3}\.\d\d B/splat", text), text


def test_labels_never_overlap_where_points_crowd():
    # nine points within a few pixels of each other, and a marker in the way
    anchors = [(300 + 3 * i, 200 + 2 * (i % 3)) for i in range(9)]
    sizes = [(110, 18)] * 9
    markers = [(ax - 5, ay - 5, ax + 5, ay + 5) for ax, ay in anchors]
    boxes = place_labels(anchors, sizes, (0, 0, 800, 500), markers, [True] * 9)
    for i, a in enumerate(boxes):
        assert 0 <= a[0] and a[2] <= 800 and 0 <= a[1] and a[3] <= 500
        assert all(_overlap(a, m, 0.0) == 0 for m in markers)
        assert all(_overlap(a, b, 0.0) == 0 for b in boxes[i + 1:])


def test_eval_plot_labels_of_close_presets_do_not_overlap(tmp_path):
    """The README's presets as they sit on the donut: medium-low with its two variants, low-plus and
    low-plus-9bit, within a few tenths of a byte and a dB."""
    report = json.loads((ROOT / "bench" / "results" / "eval_donut.json").read_text())
    rows = report["rows"]
    by = {r["label"]: r for r in rows}
    for label, src, b, p in [("medium-low-12bit", "medium-low", 12.95, 60.7),
                             ("medium-low-9bit", "medium-low", 12.80, 60.5),
                             ("low-plus-9bit", "low-plus", 11.70, 52.1)]:
        row = copy.deepcopy(by[src])
        row.update(label=label, disk_bytes_per_splat=b, psnr_mean=p)
        rows.append(row)
    boxes = plot_rate_distortion(report, str(tmp_path / "plot.png"))
    labelled = [r for r in rows if r["kind"] == "preset"]
    assert len(boxes) == len(labelled) == 10
    for i, a in enumerate(boxes):
        assert all(_overlap(a, b, 0.0) == 0 for b in boxes[i + 1:]), (a, boxes)
    assert (tmp_path / "plot.png").stat().st_size > 10_000


def test_eval_plot_joins_the_presets_along_their_frontier():
    """The line is the best PSNR each size buys, smallest first: a dominated preset is not on it, a preset with
    fewer bytes and more dB than its list neighbours is (playbot's low-plus-10bit-cb8 drew a zigzag before).
    Coordinates as drawn: x grows with the bytes, y shrinks as the PSNR grows."""
    from splatstream.evaluate import _frontier

    coords = [(10.0, 400.0), (12.0, 380.0), (15.0, 200.0), (20.0, 350.0), (26.0, 190.0), (26.0, 185.0), (44.0, 100.0)]
    assert _frontier(coords) == [0, 1, 2, 5, 6]
    assert _frontier([]) == [] and _frontier([(1.0, 1.0)]) == [0]


def test_readme_donut_bytes_with_every_lod_level_are_todays(tmp_path):
    """The README's example of what the LOD levels add (the bundled donut at `medium`) is what `encode` prints
    today: it said 32.7 and 32.9 B/splat with all levels when the encoder wrote 32.19 and 32.38."""
    per_splat = {}
    for merge in ("auto", "grid"):
        r = run_cli("encode", ROOT / "samples" / "donut.ply", tmp_path / merge, "--lod-merge", merge)
        assert r.returncode == 0, r.stderr
        found = re.search(r"\(([\d.]+) B/splat at full detail, ([\d.]+) with all LOD levels\)", r.stderr + r.stdout)
        assert found, r.stderr
        per_splat[merge] = (float(found[1]), float(found[2]))
    (full, auto), (_, grid) = per_splat["auto"], per_splat["grid"]
    readme = " ".join((ROOT / "README.md").read_text().split())
    assert (f"the 45k-splat donut at `medium`: {full:.1f} B/splat at full detail, {auto:.1f} with all levels, "
            f"{grid:.1f} with `--lod-merge grid`") in readme


def test_very_high_is_called_near_lossless_as_it_decodes(tmp_path):
    """`encode --help` and `info` called very-high 'lossless' where the README says near-lossless: fruit_drops
    comes back with 73 % of its higher SH coefficients 1-2 ulp off (its renders are the input's)."""
    from splatstream.io import read_gaussians
    from splatstream.scene_decode import decode_scene

    src = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"
    r = run_cli("encode", src, tmp_path / "vh", "--preset", "very-high", "--no-lod", "-q")
    assert r.returncode == 0, r.stderr
    given, back = read_gaussians(src), decode_scene(tmp_path / "vh")
    a, b = np.sort(given.sh_rest.ravel()), np.sort(back.sh_rest.ravel())
    assert 0 < np.abs(a - b).max() < 1e-6 and (a != b).mean() > 0.5  # close, not bit-exact
    info = run_cli("info", tmp_path / "vh").stdout
    helptext = " ".join(run_cli("encode", "--help").stdout.split())
    for text in (info, helptext):
        assert "very-high" in text and "near-lossless" in text and "floats, lossless" not in text


def test_info_gives_byte_counts_with_thousands_separators(tmp_path):
    scene = tmp_path / "s"
    enc = run_cli("encode", ROOT / "samples" / "donut.ply", scene)
    assert enc.returncode == 0, enc.stderr
    out = run_cli("info", scene).stdout
    on_disk = re.search(r"^on disk +([\d,]+) bytes", out, re.M).group(1)
    per_level = re.findall(r"level \d+: .* ([\d,]+) bytes on disk$", out, re.M)
    assert "," in on_disk and all(re.fullmatch(r"\d{1,3}(,\d{3})*", n) for n in [on_disk, *per_level])


def test_info_says_a_tree_kept_from_a_streamed_sog_was_kept(tmp_path):
    """newuser63: `info` on a scene that kept a streamed SOG's own LOD tree said 'not recorded (a scene before
    format 1.9, or a tree splatstream did not build)' of a 1.12 scene; from 1.9 a splatstream scene with a tree and
    no build record holds a kept tree (format.md 6), and info says so. A tree it built says how, as before."""
    sog = ROOT / "tests" / "fixtures" / "foreign" / "fruit_drops_lod"
    r = run_cli("encode", sog, tmp_path / "kept", "-q")
    assert r.returncode == 0, r.stderr
    info = json.loads(run_cli("info", tmp_path / "kept", "--json").stdout)
    assert info["version"] >= [1, 9] and info["lod"]["enabled"] and info["lod"]["merge"] is None
    assert info["lod"]["kept_from_input"] is True
    line = next(s for s in run_cli("info", tmp_path / "kept").stdout.splitlines() if s.startswith("LOD tree"))
    assert line.startswith("LOD tree   kept from the input (its own LOD tree: a streamed SOG's or a .rad's; "
                           "encode --rebuild-lod builds ours); leaves of at most "), line
    r = run_cli("encode", ROOT / "samples" / "donut.ply", tmp_path / "built", "--max-leaf-splats", "8192", "-q")
    assert r.returncode == 0, r.stderr
    info = json.loads(run_cli("info", tmp_path / "built", "--json").stdout)
    assert info["lod"]["enabled"] and info["lod"]["merge"] is not None and info["lod"]["kept_from_input"] is False
    line = next(s for s in run_cli("info", tmp_path / "built").stdout.splitlines() if s.startswith("LOD tree"))
    assert line.startswith(f"LOD tree   merge {info['lod']['merge']}, "), line
