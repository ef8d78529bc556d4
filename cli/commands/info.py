"""`splatstream info SCENE_DIR [--json]`."""
from __future__ import annotations

import argparse
import json
from collections import Counter

from splatstream.format.manifest import Manifest, scene_summary
from splatstream.format.presets import PRESET_SH_CODEBOOK, PRESET_SUMMARY, PRESETS, rotation_choices
from splatstream.progress import count
from splatstream.store import load_manifest


def scene_info(m: Manifest) -> dict:
    s = scene_summary(m)
    leaves = m.leaves
    s.update({
        "leaf_splats": sum(t.splats for t in leaves),
        "leaf_tiles": len(leaves),
        "leaf_bytes_on_disk": m.leaf_bytes_on_disk,
        "bytes_per_splat_on_disk": m.bytes_on_disk / m.splats,
        "formats": {a: f for a, f in m.formats.items() if a != "sh" or m.sh_degree > 0},
        "attributes": {a: v.to_dict() for a, v in m.attributes.items()},
        "bytes_per_level": _bytes_per_level(m),
        "camera": m.camera.to_dict(),
        "sh_codebook": _codebook(m),
        "preset_summary": PRESET_SUMMARY.get(m.preset),
        "preset_overrides": _overrides(m),
        "section_filters": dict(sorted(Counter(sec.filter for _, _, p in m.payloads() for sec in p.sections).items())),
        "lod": _lod(m),
    })
    return s


def _lod(m: Manifest) -> dict:
    """The manifest's `lod` map; `merge` and `viewing_scale_px` None where the scene does not record how its tree
    was built (format 1.9: absent from older scenes and imported trees); `kept_from_input` where the tree is one
    the encoder kept from its input (Manifest.lod_tree_kept); `viewing_scale_px` has one px per level from the first
    merged one where the scene records them so (1.10's `viewing_scale_levels_px`)."""
    lod = m.lod
    return {"enabled": lod.enabled, "kept_from_input": m.lod_tree_kept,
            "max_leaf_splats": lod.max_leaf_splats, "reduction": lod.reduction,
            "refine": lod.refine, "merge": lod.merge,
            "viewing_scale_px": list(lod.viewing_scale_px) if lod.viewing_scale_px is not None else None,
            "refinement": lod.refinement.to_dict() if lod.refinement is not None else None}


def _refinement_line(lod: dict) -> str | None:
    """How the merged levels were refined (format 1.11, encode --lod-refine), for the text output; None: not."""
    r = lod.get("refinement")
    if r is None:
        return None
    kept = ", ".join(f"{lv['level']}: {lv['kept']}" for lv in r["levels"])
    cams = r["cameras"]
    variants = ", ".join(f"{k} = " + "+".join(v) for k, v in r["variants"].items())
    return (f"{r['method']} at {r['size_px']} px, {r['iterations']} steps per variant ({variants}), "
            f"{cams['training']} training / {cams['validation']} validation cameras; kept per level {kept}")


def _lod_line(lod: dict) -> str | None:
    """How the tree was built, for the text output (None: no tree)."""
    if not lod["enabled"]:
        return None
    shape = f"leaves of at most {lod['max_leaf_splats']:,} splats, {lod['reduction']:g}x per level"
    scales = lod["viewing_scale_px"]
    if lod.get("kept_from_input"):  # (a scene of 1.9 or later without the build record: Manifest.lod_tree_kept)
        return f"kept from the input (its own LOD tree: a streamed SOG's or a .rad's; encode --rebuild-lod builds " \
               f"ours); {shape}"
    if lod["merge"] is None and scales is None:
        return f"merge and viewing scales not recorded (a scene before format 1.9, whose tree may also be one kept " \
               f"from a streamed SOG or .rad input); {shape}"
    merge = f"merge {lod['merge']}" if lod["merge"] is not None else "merge not recorded"
    if scales is None:
        viewing = "viewing scales not recorded"
    elif len(scales) == 2:
        viewing = f"opacity/colour matched at {scales[0]:g} px (first merged level), {scales[1]:g} px (above)"
    else:  # format 1.10: one per level from the first merged one, the last on every level above
        viewing = f"opacity/colour matched at {scales[0]:g} px (first merged level), " \
                  f"{' / '.join(f'{v:g}' for v in scales[1:])} px (the levels above, the last on every higher one)"
    return f"{merge}, {viewing}; {shape}"


def _overrides(m: Manifest) -> dict[str, str] | None:
    """What the scene's formats and codebook change from its preset's (None: a preset this version does not know)."""
    if m.preset not in PRESETS:
        return None
    # a rotation format the preset's encoder measured and chose (presets.rotation_choices) is the preset's own
    out = {a: f for a, f in m.formats.items() if PRESETS[m.preset].get(a) != f and (a != "sh" or m.sh_degree > 0)
           and not (a == "rotation" and f in rotation_choices(m.preset))}
    if m.sh_degree > 0 and m.uses_codebook != (m.preset in PRESET_SH_CODEBOOK):
        out["sh_codebook"] = str(m.sh_codebook.entries) if m.sh_codebook else "off"
    return out


def _codebook(m: Manifest) -> dict | None:
    cb = m.sh_codebook
    if cb is None:
        return None
    groups = cb.groups.values()
    return {"entries": cb.entries, "format": cb.format, "index_format": cb.index_format,
            "bytes_on_disk": sum(g.bytes for g in groups), "gpu_bytes": sum(g.gpu_bytes for g in groups)}


def _bytes_per_level(m: Manifest) -> list[dict]:
    levels: dict[int, dict] = {}
    for t in m.tiles:
        lv = levels.setdefault(t.level, {"level": t.level, "tiles": 0, "splats": 0, "bytes_on_disk": 0,
                                         "gpu_bytes": 0})
        lv["tiles"] += 1
        lv["splats"] += t.splats
        for g in t.groups.values():
            lv["bytes_on_disk"] += g.bytes
            lv["gpu_bytes"] += g.gpu_bytes
    return [levels[k] for k in sorted(levels)]


def camera_line(cam: dict) -> str:
    """The scene's suggested camera, where a viewer opens (encode --camera-azimuth turns it about up)."""
    def vec(v) -> str:
        return ",".join(f"{x:.4g}" for x in v)

    return (f"camera     eye {vec(cam['eye'])} looking at {vec(cam['target'])}, up {vec(cam['up'])}, "
            f"fov_y {cam['fov_y']:g} deg (where a viewer opens; encode --camera-azimuth turns it)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("info", help="describe an encoded scene directory",
                       description="Print the facts of an encoded scene: splats, SH degree, preset, sizes on disk and "
                                   "in GPU memory per attribute, tiles and levels.")
    p.add_argument("scene_dir", metavar="SCENE_DIR",
                   help="an encoded scene directory (the one holding manifest.msgpack), as written "
                        "by `splatstream encode`")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    info = scene_info(load_manifest(args.scene_dir))
    if args.json:
        print(json.dumps(info))
        return 0
    print(f"scene      {info['name']}  (format version {info['version'][0]}.{info['version'][1]})")
    print(f"splats     {info['splats']:,}  SH degree {info['sh_degree']}  preset {info['preset']}")
    overrides = info["preset_overrides"]
    if info["preset_summary"]:
        changed = f"; differs from it in: {', '.join(f'{a}={f}' for a, f in overrides.items())}" if overrides else ""
        print(f"preset     {info['preset']}: {info['preset_summary']}{changed}")
    else:
        print(f"preset     {info['preset']} is not a preset of this version; the formats below are what counts")
    print(f"tiles      {info['tiles']:,} in {count(info['levels'], 'level')}, "
          f"{count(info['leaf_tiles'], 'leaf', 'leaves')} holding {count(info['leaf_splats'], 'splat')}")
    lod_line = _lod_line(info["lod"])
    if lod_line:
        print(f"LOD tree   {lod_line}")
    refined = _refinement_line(info["lod"])
    if refined:
        print(f"refined    {refined}")
    print(camera_line(info["camera"]))
    print(f"on disk    {info['bytes_on_disk']:,} bytes ({info['bytes_per_splat_on_disk']:,.2f} B/splat, all levels)")
    print(f"GPU        {info['gpu_bytes']:,} bytes ({info['gpu_bytes_per_splat']:,.2f} B/splat, full detail)")
    for name, a in (info["attributes"] or {}).items():
        print(f"  {name:<9} {a['format']:<9} GPU {a['gpu_bytes'] / info['splats']:7,.2f} B/splat   "
              f"disk {a['disk_bytes'] / info['splats']:7,.2f} B/splat")
    filters = ", ".join(f"{n} {f}" for f, n in info["section_filters"].items())
    print(f"payloads   sections stored as: {filters} (format.md 5)")
    cb = info["sh_codebook"]
    if cb:
        print(f"  SH codebook: {cb['entries']:,} entries in {cb['format']}, {cb['bytes_on_disk']:,} bytes on disk, "
              f"{cb['gpu_bytes']:,} on the GPU, shared by every tile ({cb['index_format']} index per splat)")
    for lv in info["bytes_per_level"]:
        print(f"  level {lv['level']}: {count(lv['tiles'], 'tile')}, {count(lv['splats'], 'splat')}, "
              f"{lv['bytes_on_disk']:,} bytes on disk")
    return 0
