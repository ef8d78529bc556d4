"""The encoder's output bytes, pinned: every engine (in memory, partitioned in this process, Dask) and input kind
(a binary PLY read by row ranges, an input read whole and spilled, a PLY whose header names its up axis) gives the
scene directory the encoder wrote at commit 615105a, before its two planners became one (issue 33). The digests
were computed with that commit's code on the same inputs; a change here is a change of the format's output and
needs its own reason."""
from __future__ import annotations

import hashlib
import os

import pytest
from conftest import real

from splatstream import io, ply
from splatstream.encode import encode_file, plan
from splatstream.gaussians import Gaussians
from splatstream.io import read_gaussians
from splatstream.ply import gaussians_to_records, write_gaussians_ply
from splatstream.readers.splat import write_splat

# Small leaves and a small memory per worker: a tree of several levels split into partitions.
TREE = {"max_leaf_splats": 300}
SMALL_MEMORY = 1 << 20


def directory_digest(path: str) -> str:
    """One SHA-256 over every file's relative path and SHA-256, in path order."""
    lines = []
    for root, _, files in os.walk(path):
        for f in files:
            full = os.path.join(root, f)
            with open(full, "rb") as fh:
                lines.append(f"{os.path.relpath(full, path)} {hashlib.sha256(fh.read()).hexdigest()}\n")
    return hashlib.sha256("".join(sorted(lines)).encode()).hexdigest()


def write_inputs(base: str) -> dict[str, str]:
    """The inputs, written from a real scene: a binary PLY, a .splat (no row ranges: read whole and spilled) and
    a PLY whose header comment says z is up."""
    g = read_gaussians(real("fruit_drops_sh3.ply"))
    g = Gaussians.concatenate([g, g.subset(slice(0, 600))])  # equal centres: kd median ties
    paths = {"ply": os.path.join(base, "scene.ply"), "splat": os.path.join(base, "scene.splat"),
             "zup": os.path.join(base, "zup.ply")}
    write_gaussians_ply(g, paths["ply"])
    write_splat(g, paths["splat"])
    records = gaussians_to_records(g)
    header = (f"ply\nformat binary_little_endian 1.0\ncomment up_axis: z\nelement vertex {len(g)}\n"
              + "".join(f"property float {n}\n" for n in records.dtype.names) + "end_header\n")
    with open(paths["zup"], "wb") as f:
        f.write(header.encode() + records.tobytes())
    return paths


# (input, preset, extra options) -> digest of the scene directory at 615105a, the same on every engine; medium's
# since its log scales went onto a 1023-level tile step (issue 32: format/presets.py PRESET_STEPS; every engine
# agrees on the new digests, printed by this file's __main__); the LOD cases since merged opacities and colours
# are matched at the 2-px viewing scale (format_spec/lod.md 6 step 5, branch lodq; "no-lod" unchanged by that); the
# LOD cases again since their manifests are 1.8 tile tables (format.md 6.2, branch manifest18: payloads unchanged,
# "no-lod" a one-tile scene, unchanged)
DIGESTS: dict[tuple[str, str, str], str] = {
    ("ply", "medium", ""): "d015cbd4fd42f6fa6e5196fa935d5c837563f7fd659112d55b35c42aecd72e57",
    ("ply", "low", ""): "8e7eb3a51181b54a76dd7e208b8aa3a4854a3abec4c1b1d878ad8897373e5a9c",
    ("ply", "medium-low-sh8", ""): "00b65e9ddd3b3cc93bf3fb33c59fca7844371f0062680bcf682919d4ede9cfee",
    ("ply", "very-high", ""): "3b37025b8d829b99661e60e5087d8f9f0de77587292b8527d0d52d20cf7225d2",
    ("splat", "medium", ""): "8fbf105d5216032f7121da0e2aca2edecb3ce97652bea5e07a747324ccd8fe40",
    ("splat", "low", ""): "52a7c7640df520051dc14f283ffc8f1910a5772f5da5bbd4078753ce82cbbd1b",
    ("splat", "medium-low-sh8", ""): "6827761dd112ce5837086505b1a19e6ddcdc73b98362f3633ac6a331ac384cdd",
    ("splat", "very-high", ""): "120b6d055316063fdf10a83d7e4d31b75e08c9e5247108b92aafd6fe51e7e18b",
    ("ply", "medium", "no-lod"): "14b9b96880c0d3868c2a7a3c5e453dc71b9bfd2eead5995adb72376c77cb3434",
    ("ply", "low", "sh1"): "eeb857feaa8e37607be30cc1eef3c0b239fdc50a814f286be5562f3be7cabf14",
    ("zup", "medium", ""): "d11fc6020780f35ef7da08963e78bf4b646eafb3d028e8979d1bc79ab4988bf8",
}
# The cases run (a .splat's partitioned encode runs in memory unless on Dask: it is read whole anyway)
CASES = [("ply", "medium", "memory", ""), ("ply", "medium", "partitioned", ""), ("ply", "low", "memory", ""),
         ("ply", "low", "partitioned", ""), ("ply", "low", "dask", ""), ("ply", "medium-low-sh8", "partitioned", ""),
         ("ply", "very-high", "partitioned", ""), ("splat", "medium", "memory", ""), ("splat", "medium", "dask", ""),
         ("splat", "low", "memory", ""), ("ply", "medium", "memory", "no-lod"), ("ply", "low", "partitioned", "sh1"),
         ("zup", "medium", "memory", ""), ("zup", "medium", "partitioned", "")]
ENGINES = {"memory": {}, "partitioned": {"memory_per_worker": SMALL_MEMORY}, "dask": {"workers": 2,
                                                                                     "memory_per_worker": SMALL_MEMORY}}
EXTRA = {"": TREE, "no-lod": {"lod": False}, "sh1": {**TREE, "sh_degree": 1}}


def encode_case(inputs: dict[str, str], out: str, source: str, preset: str, engine: str, extra: str) -> str:
    encode_file(inputs[source], out, preset=preset, **ENGINES[engine], **EXTRA[extra])
    return directory_digest(out)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory) -> dict[str, str]:
    return write_inputs(str(tmp_path_factory.mktemp("inputs")))


@pytest.mark.parametrize("case", CASES, ids=["-".join(c for c in case if c) for case in CASES])
def test_output_bytes_are_615105a_s(inputs, tmp_path, case):
    if case[2] == "dask":
        pytest.importorskip("distributed")
    source, preset, _, extra = case
    assert encode_case(inputs, str(tmp_path / "out"), *case) == DIGESTS[source, preset, extra]


@pytest.mark.parametrize("engine", ["memory", "partitioned"])
def test_the_input_is_sniffed_and_its_header_read_once(inputs, tmp_path, monkeypatch, engine):
    """Issue 33: one encode opens its input once (io.open_input) and screens the splats' domain once."""
    calls: dict[str, int] = {}

    def counted(module, name):
        original = getattr(module, name)

        def wrapper(*args, **kwargs):
            calls[name] = calls.get(name, 0) + 1
            return original(*args, **kwargs)
        monkeypatch.setattr(module, name, wrapper)

    for module, name in ((io, "_sniff"), (io, "read_header"), (ply, "read_header"), (io, "domain_violations"),
                         (plan, "domain_violations")):
        counted(module, name)
    encode_file(inputs["zup"], str(tmp_path / "out"), preset="medium", **ENGINES[engine], **TREE)
    assert calls == {"_sniff": 1, "read_header": 1, **({"domain_violations": 1} if engine == "memory" else {})}


if __name__ == "__main__":  # prints every case's digest with whichever splatstream is imported
    import sys
    import tempfile

    sys.path.insert(0, os.path.dirname(__file__))
    with tempfile.TemporaryDirectory() as tmp:
        paths = write_inputs(tmp)
        for i, case in enumerate(CASES):
            print(f"    {case!r}: \"{encode_case(paths, os.path.join(tmp, f'o{i}'), *case)}\",", flush=True)
