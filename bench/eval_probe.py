"""`splatstream eval` of preset variants not (yet) in format/presets.py, with eval's cameras, size and renderer.

    python bench/eval_probe.py SCENE --json OUT.json [eval options] -- CONFIG [CONFIG ...]

CONFIG is bench/sh_coding_probe.py's "LABEL:PRESET[,ATTR=FORMAT...][,pos_g=G][,scale_g=G][,rgb_g=G][,zstd=L]...":
a temporary preset `probe-LABEL` with the base preset's formats, tile steps, SH codebook and zstd level, then the
config's. The report's rows are labelled `probe-LABEL`; `bench/eval_merge.py TARGET.json OUT.json --rename
probe-LABEL=NAME` puts a variant into a round's report once it has become the named preset NAME with the same
settings (the merge checks input, cameras, size and renderer). Used for issue 32's `medium` positions and guitar's
near misses (BENCHMARKS.md, "Size against quality").
"""
from __future__ import annotations

import os
import sys

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
sys.path.insert(0, os.path.dirname(__file__))

from sh_coding_probe import parse_config, register  # noqa: E402

from cli.main import main  # noqa: E402


def run(argv: list[str]) -> int:
    if "--" not in argv:
        raise SystemExit(__doc__)
    cut = argv.index("--")
    eval_args, configs = argv[:cut], argv[cut + 1:]
    names = [register(*parse_config(c)) for c in configs]
    return main(["eval", *eval_args, "--presets", ",".join(names)])


if __name__ == "__main__":
    sys.exit(run(sys.argv[1:]))
