"""One exit-code convention for every command: bad input or usage exits 2 with one line naming the path or option
and what was expected; never a traceback; no output left behind."""
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from conftest import ROOT, run_cli

from cli.main import main
from splatstream.atomic import is_mount_point, mountinfo_points
from splatstream.io import read_gaussians
from splatstream.ply import write_gaussians_ply
from splatstream.store import load_manifest

DONUT = ROOT / "samples" / "donut.ply"
STREAMED_SOG = ROOT / "tests" / "fixtures" / "foreign" / "fruit_drops_lod"  # another tool's scene directory


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    out = tmp_path_factory.mktemp("scene") / "donut"
    r = run_cli("encode", DONUT, out, "-q")
    assert r.returncode == 0, r.stderr
    return out


def cases(tmp, scene):
    (tmp / "a_file").write_text("x")
    (tmp / "a_dir").mkdir()
    (tmp / "p.json").write_text('{"keyframes": [{"time": 0, "eye": [1, 1, 1], "target": [0, 0, 0]}]}')
    broken = read_gaussians(DONUT)
    broken.positions[7] = np.nan
    write_gaussians_ply(broken, tmp / "nan.ply")
    # view, render and eval said "pass --drop-invalid to drop them" and then refused that option; then they pointed
    # at encode and convert; every one takes it now (newuser63), and one splat of 45,624 "has", with separators
    n = f"{len(broken):,}"
    drop_hint = (f"1 of {n} splats has non-finite values (NaN or inf) (x: 1, y: 1, z: 1); --drop-invalid drops them "
                 "(encode, convert, render, view, eval)")
    return [
        (["render", tmp / "nan.ply", "--out", tmp / "o.png", "-q"], drop_hint),  # -q: no progress lines first
        (["view", tmp / "nan.ply", "--headless", "-q"], drop_hint),
        (["eval", tmp / "nan.ply", "--presets", "low", "-q"], drop_hint),
        (["convert", tmp / "nan.ply", tmp / "o.ply", "-q"], drop_hint),
        # an encoded scene has no invalid splats to drop: refused, not ignored
        (["render", scene, "--drop-invalid", "--out", tmp / "o.png"], "--drop-invalid: drops invalid splats of a "
                                                                      "splat file; "),
        (["view", scene, "--headless", "--drop-invalid"], "--drop-invalid: drops invalid splats of a splat file; "),
        # a directory output named as the file an engine loads, or as a one-file format, was written as a directory
        # of that name: sog/lod-meta.json/lod-meta.json (newuser64)
        (["export-sog-lod", scene, tmp / "sog" / "lod-meta.json", "-q"],
         f"{tmp / 'sog' / 'lod-meta.json'}: export-sog-lod writes a directory with lod-meta.json inside it; give the "
         f"directory ({tmp / 'sog'})"),
        (["export-sog-lod", scene, tmp / "g.sog", "-q"], "export-sog-lod writes a directory (lod-meta.json and its "
                                                         "files), not a .sog file; `splatstream decode SCENE "),
        (["export-3dtiles", scene, tmp / "t" / "tileset.json", "-q"],
         f"{tmp / 't' / 'tileset.json'}: export-3dtiles writes a directory with tileset.json inside it"),
        # render takes an encoded scene too, which the reader's message did not name (newuser64)
        (["render", tmp / "a_dir", "--out", tmp / "o.png"],
         f"{tmp / 'a_dir'}: not a scene directory (no manifest.msgpack) nor a SOG directory (no meta.json or "
         "lod-meta.json): render takes an encoded scene, a SOG or a splat file"),
        (["encode", tmp / "missing.ply", tmp / "o"], "missing.ply"),
        (["encode", DONUT, tmp / "o", "--up", "0,0,0"], "--up"),
        (["encode", DONUT, tmp / "o", "--up", "1,x,0"], "--up"),
        (["encode", DONUT, "/proc/o"], "/proc/o"),
        (["encode", DONUT, tmp / "a_file"], "a_file"),
        (["encode", DONUT, tmp / "o", "--preset", "ultra"], "--preset"),
        (["encode", DONUT, tmp / "o", "--zstd-level", "99"], "--zstd-level"),
        # a number said back as given, not reformatted ("--target-size -3.0": newuser62)
        (["encode", DONUT, tmp / "o", "--target-size", "-3"], "--target-size -3: expected a size above 0"),
        (["encode", DONUT, tmp / "o", "--target-psnr", "0"], "--target-psnr 0: expected a PSNR above 0 dB"),
        (["render", scene, "--max-sse", "-1", "--out", tmp / "o.png"], "--max-sse -1: expected 0 or more pixels"),
        (["view", scene, "--headless", "--gpu-mem-mb", "-2"], "--gpu-mem-mb -2: expected a positive number"),
        (["view", scene, "--headless", "--timeout", "0"], "--timeout 0: expected a positive number of seconds"),
        (["encode", DONUT, tmp / "o", "--sh-codebook", "many"], "many"),
        (["encode", tmp / "a_dir", tmp / "o"], "a_dir"),
        # one of our own scenes as input: it said only 'a directory without meta.json or lod-meta.json'
        (["encode", scene, tmp / "o", "--preset", "low"], f"{scene}: is a splatstream scene (manifest.msgpack), not "
                                                          f"a splat file: `splatstream decode {scene} scene.ply`"),
        (["convert", scene, tmp / "o.ply"], "is a splatstream scene (manifest.msgpack), not a splat file"),
        (["encode", tmp / "a_file", tmp / "o"], "a_file"),
        (["decode", tmp / "missing", tmp / "o.ply"], "missing"),
        (["decode", scene, "/proc/o.ply"], "/proc/o.ply"),
        (["decode", scene, tmp / "a_dir"], "a_dir"),
        (["decode", scene, tmp / "o.ply", "--tiles", ""], "--tiles: expected comma-separated integers, got ''"),
        (["info", tmp / "missing"], "missing"),
        (["info", tmp / "a_file"], "a_file"),
        (["info", tmp / "a_dir"], "a_dir"),
        (["decode", STREAMED_SOG, tmp / "o.ply"], "lod-meta.json here: a SOG scene"),  # says what reads it
        (["info", STREAMED_SOG / "lod-meta.json"], "lod-meta.json is read by `splatstream encode`, `convert`"),
        # render and eval read such a file too, and the hint left them out (newuser62)
        (["export-rad", DONUT, tmp / "o.rad"], "`convert`, `view`, `render` and `eval`)"),
        (["convert", tmp / "missing.ply", tmp / "o.ply"], "missing.ply"),
        (["convert", DONUT, tmp / "o.xyz"], "o.xyz"),
        (["convert", DONUT, tmp / "o.ply", "--scale", "0"], "--scale"),  # edits checked before the read
        (["convert", DONUT, tmp / "o.ply", "--filter-box", "1,1,1,0,0,0"], "--filter-box"),
        (["convert", DONUT, tmp / "o.ply", "--filter", "opacity>abc"], "abc"),
        (["render", tmp / "missing", "--out", tmp / "o.png"], "missing"),
        (["render", scene, "--out", tmp / "o.jpg"], "o.jpg"),
        (["render", scene, "--size", "0x0", "--out", tmp / "o.png"], "--size"),
        (["render", scene, "--eye", "1,1", "--out", tmp / "o.png"], "--eye"),
        # 'bad camera: camera eye and target coincide' named neither option; --fov-y 200 was 'camera fov_y_deg ...'
        (["render", scene, "--eye", "1,1,1", "--target", "1,1,1", "--out", tmp / "o.png"], "--eye and --target"),
        (["render", scene, "--fov-y", "200", "--out", tmp / "o.png"], "--fov-y 200: expected degrees in (0, 180)"),
        (["eval", scene], "is a directory"),
        (["eval", tmp / "missing.ply"], "missing.ply"),
        (["eval", DONUT, "--size", "5x5"], "--size"),
        (["serve", tmp / "missing"], "missing"),
        (["serve", tmp / "a_dir", "--port", "70000"], "--port"),
        (["serve", tmp / "a_dir", "--cors-origin", "viewer.example"], "--cors-origin viewer.example"),  # no scheme
        (["serve", tmp / "a_dir", "--cors-origin", "https://viewer.example/app"], "--cors-origin"),  # a path
        (["eval", DONUT, "--presets", "low", "--plot", tmp / "o.txt"], "o.txt"),  # refused before any encode
        (["export-rad", scene, tmp / "o.ply"], "o.ply"),  # a .rad under another extension
        (["export-rad", tmp / "missing", tmp / "o.rad"], "missing"),
        (["export-sog-lod", tmp / "missing", tmp / "s"], "missing"),
        (["export-sog-lod", scene, tmp / "a_file"], "a_file: exists and is not a directory (the output is a directory"),
        (["view", tmp / "missing", "--headless"], "missing"),
        (["view", "http://127.0.0.1:9/playbot/lod-meta.json", "--headless"],  # was a 404 for .../manifest.msgpack
         "lod-meta.json: over HTTP `view` streams a served scene (http://HOST/scenes/ID"),
        (["view", "https://cdn.example/scenes/garden.rad?v=2", "--headless"], "garden.rad?v=2: over HTTP"),
        (["view", scene, "--headless", "--size", "0x0"], "--size"),
        (["view", scene, "--headless", "--screenshot", tmp / "o.jpg"], "o.jpg"),
        (["view", scene, "--headless", "--fill-gap", "0"], "--fill-gap"),
        (["view", scene, "--headless", "--fill-root-kb", "-1"], "--fill-root-kb -1: expected 0 or more kilobytes"),
        (["view", scene, "--headless", "--eye", "1,1,1", "--target", "1,1,1"], "--eye and --target"),
        (["view", scene, "--headless", "--sh-bands", "0.9,x,1"], "--sh-bands"),
        # taken in a window without a word, and nothing written or kept (newuser60)
        (["view", scene, "--frames-dir", tmp], "--frames-dir: only with --headless"),
        (["view", scene, "--until-converged"], "--until-converged: only with --headless"),
        (["view", scene, "--headless", "--measure-frames", "-3"], "--measure-frames -3: expected 0 or more"),
        # a window's options with --headless, --frame-every without --frames-dir: taken without a word (newuser61)
        (["view", scene, "--headless", "--no-overlay"], "--no-overlay and --headless: --no-overlay is a window's"),
        (["view", scene, "--headless", "--no-vsync"], "--no-vsync and --headless"),
        (["view", scene, "--headless", "--exit-when-converged"], "--exit-when-converged and --headless"),
        (["view", scene, "--headless", "--frame-every", "3"], "--frame-every 3: spaces the PNGs of --frames-dir"),
        # the path's keyframes place the camera; --until-converged is for a path (newuser61)
        (["view", scene, "--headless", "--camera-path", tmp / "p.json", "--eye", "1,1,1", "--target", "0,0,0"],
         "--camera-path and --eye/--target: the path's keyframes place the camera"),
        (["view", scene, "--headless", "--camera-path", tmp / "p.json", "--fov-y", "30", "--up", "0,1,0"],
         "--camera-path and --up, --fov-y"),
        (["view", scene, "--headless", "--until-converged"], "--until-converged: keeps a --camera-path view going"),
        (["export-3dtiles", tmp / "missing", tmp / "t"], "missing"),
        (["export-3dtiles", scene, tmp / "t", "--latitude", "10"], "--longitude"),
        (["export-3dtiles", scene, tmp / "t", "--content", "weird"], "--content"),
        (["nonsense"], "nonsense"),
    ]


def test_bad_arguments_exit_2_with_one_line(tmp_path, scene):
    for args, named in cases(tmp_path, scene):
        r = run_cli(*args)
        where = " ".join(map(str, args))
        assert r.returncode == 2, (where, r.returncode, r.stderr)
        assert "Traceback" not in r.stderr, where
        lines = [ln for ln in r.stderr.strip().splitlines() if ln]
        assert len(lines) == 1, (where, r.stderr)
        assert named in lines[0], (where, lines[0])
        assert not (tmp_path / "o").exists() and not (tmp_path / "o.ply").exists() and not (tmp_path / "o.png").exists()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")], where  # no temporaries left


def test_encode_sh_format_refused_where_no_sh_band_is_kept(tmp_path, scene):
    """`encode --sh FORMAT` on an SH0 input (or with --sh-degree 0) was taken without a word, with no SH plane to
    format (newuser62): refused once the input is read, in one line naming the option, the input and its SH degree,
    nothing written; in memory, by partitions, and for a kept foreign tree. The presets (each with an SH format of its
    own) still encode SH0 inputs, and --sh on an input with SH bands is taken."""
    def refused(*args: object, said: tuple[str, ...]) -> None:
        r = run_cli("encode", *args, tmp_path / "o", "-q")
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert r.stderr.strip().count("\n") == 0 and all(s in r.stderr for s in said), r.stderr
        assert not (tmp_path / "o").exists()

    refused(DONUT, "--sh", "f16x4", "--no-lod", said=("--sh f16x4: ", str(DONUT), "has SH degree 0"))
    refused(DONUT, "--sh", "norm8x4", "--memory-per-worker", "2MB", said=("--sh norm8x4: ", "has SH degree 0"))
    fruit = ROOT / "tests" / "data" / "real" / "fruit_drops_sh3.ply"
    refused(fruit, "--sh", "f16x4", "--sh-degree", "0", "--no-lod",
            said=("--sh f16x4: --sh-degree 0 drops every SH band", str(fruit), "(SH degree 3)"))
    r = run_cli("export-sog-lod", scene, tmp_path / "sog", "-q")  # an SH0 streamed SOG: its tree is kept
    assert r.returncode == 0, r.stderr
    refused(tmp_path / "sog", "--sh", "f16x4", said=("--sh f16x4: ", str(tmp_path / "sog"), "has SH degree 0"))
    for preset in ("very-high", "medium", "low"):
        r = run_cli("encode", DONUT, tmp_path / preset, "--preset", preset, "--no-lod", "-q")
        assert r.returncode == 0, r.stderr
        assert load_manifest(tmp_path / preset).sh_degree == 0
    r = run_cli("encode", fruit, tmp_path / "sh", "--sh", "f16x4", "--no-lod", "-q")
    assert r.returncode == 0, r.stderr
    assert load_manifest(tmp_path / "sh").formats["sh"] == "f16x4"


def test_a_directory_of_other_files_is_never_replaced(tmp_path, scene):
    """A directory output (a scene, a 3D Tiles tileset, a streamed SOG) replaces an existing directory only where
    it is empty or holds that kind of output (manifest.msgpack, tileset.json, lod-meta.json): a mistyped path to a
    directory of the user's own files is one line, exit 2, and the files stay."""
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("the user's own")
    for args, marker in ((["encode", DONUT, mine], "manifest.msgpack"),
                         (["export-3dtiles", scene, mine], "tileset.json"),
                         (["export-sog-lod", scene, mine], "lod-meta.json")):
        r = run_cli(*args, "-q")
        assert r.returncode == 2, r.stderr
        assert r.stderr.strip() == (f"splatstream {args[0]}: error: {mine}: exists and holds other files (notes.txt) "
                                    f"but no {marker}: not replaced; give a new or empty directory, or remove this "
                                    "one first")
        assert sorted(p.name for p in mine.iterdir()) == ["notes.txt"]
        assert (mine / "notes.txt").read_text() == "the user's own"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left
    # an empty directory, and each kind's own earlier output, are still replaced
    for command, out, marker in (("encode", "scene", "manifest.msgpack"), ("export-3dtiles", "tiles", "tileset.json"),
                                 ("export-sog-lod", "sog", "lod-meta.json")):
        (tmp_path / out).mkdir()
        for _ in range(2):
            r = run_cli(command, DONUT if command == "encode" else scene, tmp_path / out, "-q")
            assert r.returncode == 0, r.stderr
            assert (tmp_path / out / marker).is_file()


def test_view_without_the_gl_client_says_how_to_install_it():
    """`view` where moderngl is missing (installed without the [view] extra): the install hint, exit 2."""
    import subprocess
    import sys

    code = ("import sys; sys.modules['moderngl'] = None\n"
            "from cli.main import main\n"
            f"sys.argv = ['splatstream', 'view', {str(DONUT)!r}, '--headless']\n"
            "sys.exit(main())\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    assert "pip install 'splatstream[view]'" in r.stderr.strip().splitlines()[-1]


def test_an_unreachable_object_store_is_one_line_before_the_encode():
    """An output URL whose store refuses us (here a filesystem whose listing fails as s3fs's does without
    credentials) is refused at the start with one line naming the URL, exit 2, not an 'internal error' raised by
    the first payload's write after the whole encode."""
    import subprocess
    import sys

    pytest.importorskip("fsspec")
    code = ("import sys, fsspec\n"
            "from fsspec.spec import AbstractFileSystem\n"
            "class NoCredentials(Exception): pass\n"
            "class Refusing(AbstractFileSystem):\n"
            "    protocol = 'refusing'\n"
            "    def ls(self, path, detail=True, **kw): raise NoCredentials('Unable to locate credentials')\n"
            "    def pipe_file(self, path, value, **kw): raise AssertionError('wrote ' + path)\n"
            "fsspec.register_implementation('refusing', Refusing, clobber=True)\n"
            "from cli.main import main\n"
            f"sys.exit(main(['encode', {str(DONUT)!r}, 'refusing://bucket/scene']))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2, r.stderr
    lines = [ln for ln in r.stderr.strip().splitlines() if ln]
    assert len(lines) == 1, r.stderr  # before any progress line: nothing was read or encoded
    assert lines[0].startswith("splatstream encode: error: refusing://bucket/scene: cannot reach the object store "
                               "(NoCredentials: Unable to locate credentials)"), lines[0]


@pytest.mark.parametrize("damage", ["flipped", "missing"])
def test_view_of_a_local_scene_with_a_damaged_payload_exits_2_at_once(tmp_path, scene, gl_context, damage):
    """A scene directory whose payload was changed (its SHA-256 differs from the manifest) or removed: reading it
    again gives the same bytes, so `view` names the file and the field after a second read and exits 2, instead
    of retrying until --timeout and exiting 1 (a --timeout of 60 s: a regression fails, it does not hang)."""
    import hashlib
    import shutil

    from splatstream.store import load_manifest

    copy = tmp_path / "donut"
    shutil.copytree(scene, copy)
    m = load_manifest(copy)
    entry = m.tile(m.root).groups["base"]  # wanted by every view
    path = copy / entry.file
    data = bytearray(path.read_bytes())
    if damage == "flipped":
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
        expected = (f"{path}: sha256: SHA-256 {hashlib.sha256(data).hexdigest()}, the manifest says {entry.sha256} "
                    "(the file is damaged or was replaced)")
    else:
        path.unlink()
        expected = f"{path}: payload file named in the manifest is missing"
    record = tmp_path / "metrics.json"
    r = run_cli("view", copy, "--headless", "-q", "--size", "64x48", "--timeout", "60", "--record", record)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == f"splatstream view: error: {expected}"
    assert not record.exists()  # no half-written output


def test_a_mount_point_is_refused_before_the_work_not_after(tmp_path, scene, monkeypatch, capsys):
    """An output directory that is a mount point (a container's volume: `docker run -v $PWD/out:/out ... encode
    scene.ply /out`) cannot be replaced by the rename that puts a finished output in place: on a tmpfs mounted
    there, encode and export-sog-lod ran to the end and failed with 'Device or resource busy', exit 1. Now one line
    before any work, exit 2, naming a directory inside it. (The mount is stood in for: making one needs root.)"""
    volume = tmp_path / "volume"
    volume.mkdir()
    real_ismount = os.path.ismount
    monkeypatch.setattr(os.path, "ismount", lambda p: os.path.abspath(p) == str(volume) or real_ismount(p))
    for args in (["encode", str(DONUT), str(volume)], ["export-sog-lod", str(scene), str(volume)],
                 ["export-3dtiles", str(scene), str(volume)]):
        assert main([*args, "-q"]) == 2
        err = capsys.readouterr().err
        assert err.strip() == (f"splatstream {args[0]}: error: {volume}: is a mount point, which the finished output "
                               f"cannot replace (it is renamed into place); give a directory inside it, e.g. "
                               f"{volume / 'scene'}"), err
        assert not list(volume.iterdir()) and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    assert main(["encode", str(DONUT), str(volume / "scene"), "-q"]) == 0
    assert (volume / "scene" / "manifest.msgpack").is_file()


def test_mountinfo_points_undo_the_kernels_escapes(tmp_path):
    text = ("22 1 8:1 / / rw,relatime shared:1 - ext4 /dev/sda1 rw\n"
            "95 22 8:1 /home/u/out /srv/my\\040volume rw,relatime shared:1 - ext4 /dev/sda1 rw\n")
    assert mountinfo_points(text) == {"/", "/srv/my volume"}
    (tmp_path / "vol").mkdir()
    info = tmp_path / "mountinfo"
    info.write_text(f"95 22 8:1 /x {tmp_path / 'vol'} rw - ext4 /dev/sda1 rw\n")
    assert is_mount_point(str(tmp_path / "vol"), str(info)) and not is_mount_point(str(tmp_path), str(info))


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("unshare") is None or shutil.which("mount") is None,
                    reason="a bind mount needs root and unshare")
def test_a_bind_mount_on_the_same_file_system_is_refused_before_the_work(tmp_path):
    """os.path.ismount compares a directory's device with its parent's, so a bind mount within one file system (a
    container volume from the host's disk, `mount --bind`) was not seen: `encode donut.ply VOL` ran the whole encode
    and then failed with 'VOL: Device or resource busy', exit 1 (newuser64). The kernel's list of mount points is read
    too now: one line before any work, exit 2. A private mount namespace (unshare -m) keeps the mount to the test."""
    volume = tmp_path / "volume"
    volume.mkdir()
    script = (f'mount --bind "{volume}" "{volume}" || exit 99; '
              f'exec "{sys.executable}" -m cli encode "{DONUT}" "{volume}" -q')
    r = subprocess.run(["unshare", "-m", "sh", "-c", script], capture_output=True, text=True, cwd=ROOT,
                       stdin=subprocess.DEVNULL, timeout=600)
    if r.returncode == 99:
        pytest.skip(f"no bind mount here: {r.stderr.strip()}")
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip() == (f"splatstream encode: error: {volume}: is a mount point, which the finished output "
                                f"cannot replace (it is renamed into place); give a directory inside it, e.g. "
                                f"{volume / 'scene'}"), r.stderr
    assert not list(volume.iterdir()) and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("argv, said", [
    (["info", "scene"], "splatstream info: terminated (SIGTERM)"),
    (["serve", "root"], "splatstream serve: terminated (SIGTERM)"),
    (["view", "scene", "--headless"], "splatstream view: terminated (SIGTERM)"),
    (["view", "scene", "--headless", "--record", "r.json"],
     "splatstream view: terminated (SIGTERM); partial output removed"),
    (["decode", "scene", "x.ply"], "splatstream decode: terminated (SIGTERM); partial output removed"),
])
def test_sigterm_says_partial_output_removed_only_where_there_was_output(argv, said, monkeypatch, capsys):
    """`serve` stopped before its start line said 'terminated (SIGTERM); partial output removed' (newuser58)."""
    import importlib

    import cli.main as cli_main

    def terminated(args):
        raise cli_main.Terminated

    module = importlib.import_module(f"cli.commands.{argv[0]}")
    monkeypatch.setattr(module, "run", terminated)
    assert main(argv) == 143
    assert capsys.readouterr().err.strip() == said


@pytest.mark.parametrize("command, output", [("convert", "o.ply"), ("export-rad", "o.rad"),
                                             ("export-sog-lod", "o_sog")])
def test_a_full_disk_names_the_output_being_written(tmp_path, scene, command, output):
    """A write that finds no room (a full disk; here a file size limit, the same failure of write(2), EFBIG) said
    only 'error: No space left on device' / 'File too large', naming no file: it names the output, and nothing
    is left there."""
    import resource
    import subprocess
    import sys

    source = DONUT if command == "convert" else scene

    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, 20_000))  # (Python ignores SIGXFSZ: write fails)

    r = subprocess.run([sys.executable, "-m", "cli", command, str(source), str(tmp_path / output), "-q"],
                       capture_output=True, text=True, stdin=subprocess.DEVNULL, timeout=600,
                       preexec_fn=limit_file_size)
    assert r.returncode == 1, r.stderr
    said = r.stderr.strip().splitlines()[-1]
    assert said.startswith(f"splatstream {command}: error: writing {tmp_path / output}: "), r.stderr
    assert "File too large" in said or " requested and " in said, said  # numpy's tofile has its own words
    assert not (tmp_path / output).exists() and not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_an_exported_tileset_given_as_a_scene_says_what_it_is(tmp_path):
    """export-3dtiles' output given to info/decode/render/convert/encode said only 'not a splatstream scene
    directory', 'a directory without meta.json or lod-meta.json' or 'unrecognised file format' (`view` already
    said what it is): each says it is a 3D Tiles tileset, which CesiumJS draws, and to give the scene instead."""
    tiles = tmp_path / "tiles"
    (tiles / "tiles").mkdir(parents=True)
    (tiles / "tileset.json").write_text('{"asset": {"version": "1.1"}, "geometricError": 1, "root": {}}')
    for argv in (["info", tiles], ["decode", tiles, tmp_path / "o.ply"], ["export-rad", tiles, tmp_path / "o.rad"],
                 ["render", tiles, "--out", tmp_path / "o.png", "-q"], ["encode", tiles, tmp_path / "o", "-q"],
                 ["convert", tiles / "tileset.json", tmp_path / "o.ply", "-q"]):
        r = run_cli(*argv)
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert "3D Tiles tileset" in r.stderr and "export-3dtiles" in r.stderr, (argv[0], r.stderr)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiles"]


def test_info_of_a_scene_manifest_reads_its_scene(scene):
    # `info scene/manifest.msgpack` (a path completed one step too far) was refused as 'not a directory' (newuser60)
    by_dir, by_manifest = run_cli("info", scene), run_cli("info", scene / "manifest.msgpack")
    assert by_manifest.returncode == 0, by_manifest.stderr
    assert by_manifest.stdout == by_dir.stdout and "splats" in by_dir.stdout


def run_cli_on_a_terminal(*args: str, cwd=None) -> str:
    """The CLI with its stderr on a pseudo-terminal (the progress bar redrawn with carriage returns, as a user sees
    it): what the terminal received."""
    import pty
    import subprocess
    import sys

    master, slave = pty.openpty()
    try:
        proc = subprocess.Popen([sys.executable, "-m", "cli", *map(str, args)], stdin=subprocess.DEVNULL,
                                stdout=subprocess.DEVNULL, stderr=slave, cwd=cwd)
        os.close(slave)
        chunks = []
        while True:
            try:
                data = os.read(master, 65536)
            except OSError:  # EIO: the child closed the terminal
                break
            if not data:
                break
            chunks.append(data)
        proc.wait(timeout=600)
    finally:
        os.close(master)
    return b"".join(chunks).decode(errors="replace").replace("\r\n", "\n")


@pytest.mark.parametrize("command", ["encode", "view"])
def test_a_failure_mid_stage_starts_its_own_line_on_a_terminal(tmp_path, command):
    """On a terminal, a command that failed while its progress bar was drawn printed its error glued onto the bar
    ("encode: read [   ]   0.0%     0.0ssplatstream encode: error: ..."; newuser62): the bar's line is ended first."""
    import shutil

    src = tmp_path / "logo"  # a SOG whose scales plane is cut short: found while reading it, the bar drawn
    shutil.copytree(ROOT / "tests" / "fixtures" / "foreign" / "logo_v1_sub300", src)
    (src / "scales.webp").write_bytes((src / "scales.webp").read_bytes()[:100])
    args = [src, tmp_path / "o"] if command == "encode" else [src, "--headless"]
    said = run_cli_on_a_terminal(command, *args)
    error = next(line for line in said.split("\n") if "error:" in line)
    assert error.startswith(f"splatstream {command}: error: {src}"), said  # a line of its own
    assert "scales.files[0]" in error, said
    assert "0.0%" in said and not (tmp_path / "o").exists()


def test_end_open_line_ends_a_bar_left_open_once():
    """The progress printer records a bar left mid-line on a terminal; end_open_line ends it once, and not a bar
    that ended (100 %) or was cleared by a note."""
    import io

    from splatstream.progress import ProgressPrinter, end_open_line

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    term = Terminal()
    bar = ProgressPrinter("encode", stream=term)
    bar("read", 0.0)
    end_open_line()
    end_open_line()
    assert term.getvalue().endswith("0.0s\n") and term.getvalue().count("\n") == 1
    bar("read", 1.0)  # ends its own line
    end_open_line()
    assert term.getvalue().endswith("100.0%     0.0s\n") and term.getvalue().count("\n") == 2
    bar("tiles", 0.5)
    bar.note("up 0,0,1")  # clears the bar and ends its line
    end_open_line()
    assert term.getvalue().endswith("encode: up 0,0,1\n") and term.getvalue().count("\n") == 3


def test_render_view_and_eval_drop_invalid_splats_as_encode_does(tmp_path):
    """newuser63: render, view and eval refused a file with NaN rows and pointed at `encode`/`convert
    --drop-invalid`; they take the option themselves now, with encode's meaning: the rows dropped, one warning."""
    pytest.importorskip("moderngl")
    broken = read_gaussians(DONUT).subset(np.arange(2000))
    broken.positions[7] = np.nan
    write_gaussians_ply(broken, tmp_path / "nan.ply")
    said = "1 of 2,000 splats has non-finite values (NaN or inf) (x: 1, y: 1, z: 1); dropped"
    r = run_cli("render", tmp_path / "nan.ply", "--out", tmp_path / "o.png", "--size", "64x48", "--drop-invalid")
    assert r.returncode == 0 and said in r.stderr, r.stderr
    assert "1,999 splats read" in r.stderr and (tmp_path / "o.png").stat().st_size > 0, r.stderr
    r = run_cli("view", tmp_path / "nan.ply", "--headless", "--size", "64x48", "--drop-invalid", "-q")
    assert r.returncode == 0 and said in r.stderr, r.stderr
    r = run_cli("eval", tmp_path / "nan.ply", "--presets", "low", "--views", "1", "--size", "64x48", "--drop-invalid",
                "--json", tmp_path / "e.json", "-q")
    assert r.returncode == 0 and said in r.stderr, r.stderr
    import json

    assert json.loads((tmp_path / "e.json").read_text())["input"]["splats"] == 1999


@pytest.mark.parametrize("args, said", [
    # argparse's own message came from the top-level parser and named no command (newuser64):
    # 'splatstream: error: unrecognized arguments: --target-psnr 50 (see splatstream --help)'
    (["eval", "x.ply", "--target-psnr", "50"],
     "splatstream eval: error: unrecognized arguments: --target-psnr 50 (--target-psnr is an option of encode) "
     "(see splatstream eval --help)"),
    (["view", "scene", "--maxsplats", "3"],
     "splatstream view: error: unrecognized arguments: --maxsplats 3 (--maxsplats: did you mean --max-splats?) "
     "(see splatstream view --help)"),
    (["info", "scene", "extra"],
     "splatstream info: error: unrecognized arguments: extra (see splatstream info --help)"),
    (["decode", "scene", "o.ply", "--bogus=1"],
     "splatstream decode: error: unrecognized arguments: --bogus=1 (see splatstream decode --help)"),
])
def test_an_unknown_argument_is_named_by_its_command(args, said, capsys):
    with pytest.raises(SystemExit) as exc:
        main(args)
    assert exc.value.code == 2
    assert capsys.readouterr().err.strip() == said
