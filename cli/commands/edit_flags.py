"""The edit options' names (issue 36) and the one rewrite of the command line they need, without numpy:
cli/main.py applies it before the BLAS thread settings that must precede numpy's import."""
from __future__ import annotations

import re

# The edits of issue 36 (splatstream/edit.py), by splat-transform's long names, with the spellings beside
# them: (flags, metavar, what the value is, help).
EDIT_OPTIONS = [
    (("--translate",), "X,Y,Z", "translate", "move every splat by (X, Y, Z)"),
    (("--rotate",), "X,Y,Z|X,Y,Z,W", "rotate",
     "turn the scene about the origin by Euler angles in degrees (x first, then y, then z), or by a quaternion "
     "X,Y,Z,W (PlayCanvas's and glTF's order, w last; normalised); SH bands 1..3 turned with it"),
    (("--scale", "--scale-by"), "S", "scale", "scale the scene by S about the origin"),
    (("--filter-box", "--crop-box"), "X,Y,Z,X,Y,Z", "box", "keep the splats whose centre lies in the box "
                                                            "(min corner, max corner; faces included)"),
    (("--drop-box",), "X,Y,Z,X,Y,Z", "drop-box", "drop the splats whose centre lies in the box"),
    (("--filter-sphere", "--crop-sphere"), "X,Y,Z,R", "sphere", "keep the splats whose centre lies inside the "
                                                                 "sphere (centre, radius)"),
    (("--drop-sphere",), "X,Y,Z,R", "drop-sphere", "drop the splats whose centre lies inside the sphere"),
    (("--filter-value", "--filter"), "ATTR<OP>VALUE", "filter",
     "keep the splats whose attribute compares true: ATTR<OP>VALUE (OP one of < <= > >= == !=) or splat-transform's "
     "NAME,CMP,VALUE (CMP one of lt lte gt gte eq neq); ATTR one of x y z, opacity (0..1, after the sigmoid), "
     "scale_0..2 (after exp), f_dc_0..2 (colour 0..1), or opacity_raw, scale_N_raw, f_dc_N_raw as stored"),
    (("--filter-density",), "SIZE,MIN", "density",
     "floater removal: keep the splats whose grid cell (cubes of side SIZE in scene units) and its 26 neighbours "
     "hold at least MIN splat centres (not splat-transform's voxel --filter-floaters; a whole-scene step: encode "
     "runs it in memory and refuses it by partitions)"),
]


# A list of numbers that starts with a minus sign ("-1,-1.5,0"): argparse takes it for an option, not a value.
_NEGATIVE_LIST = re.compile(r"-[0-9.][0-9.,eE+-]*")


def attach_negative_values(argv: list[str]) -> list[str]:
    """`--filter-box -1,-1,-1,1,1,1` as `--filter-box=-1,...`: an edit option's value that starts with a minus sign
    attached to its flag, so argparse reads it as the value (splat-transform's users write it spaced)."""
    flags = {f for option in EDIT_OPTIONS for f in option[0]}
    out: list[str] = []
    for token in argv:
        if out and out[-1] in flags and _NEGATIVE_LIST.fullmatch(token):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out
