"""Render a user's ``.blend`` file into one sequence of the layout ``layout=blender`` reads: the bpy
side of ``denoiser-render-blender`` (denoiser/commands/render_blender.py), which runs it with the
``bpy`` venv's Python (``make blender-venv``)::

    .venv-blender/bin/python scripts/blender_render.py --scene shot.blend --out data/mine/train/shot \\
        --frames 1 48 --spp 4 --ref-spp 1024

Writes ``<out>/noisy/<frame:04d>.exr`` (``--spp`` samples, seed ``--seed``), unless
``--no-reference`` ``<out>/reference/<frame:04d>.exr`` (``--ref-spp``, seed ``--seed + 1000``), and
``<out>/render.json`` (the settings, what was changed on the file, render seconds).

Sets on the opened file the render settings the results depend on and the passes
(``blender_cycles.py``: no adaptive sampling, Cycles' denoiser off, animated seed, a 1-pixel box
filter, no compositor; Z, Vector and Denoising Data), prints each setting it changed, and never
saves the file. Refuses (one line, exit 2) a scene with motion blur on, without a camera, or with
other than one view layer rendered. Resumes: frames on disk are kept, when render.json records the
same settings (else a one-line refusal; ``--force`` renders every frame again).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path

import bpy

sys.path.insert(0, str(Path(__file__).resolve().parent))
from blender_cycles import apply_settings, enable_passes, refusal, render_frames, set_exr_output

PROG = "denoiser-render-blender"
#: render.json keys that are not settings (resuming compares every other key)
RECORD_ONLY = ("frames", "changed", "seconds")


def refuse(message: str) -> None:
    print(f"{PROG}: {message}", file=sys.stderr, flush=True)
    sys.exit(2)


def parse_args(argv):
    if "--" in argv:                               # blender -b -P script.py -- args
        argv = argv[argv.index("--") + 1:]
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scene", type=Path, required=True, help="the .blend file (opened, never saved)")
    p.add_argument("--out", type=Path, required=True, help="the sequence folder")
    p.add_argument("--frames", type=int, nargs=2, default=None, metavar=("FIRST", "LAST"),
                   help="frame range (default: the file's)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel of the noisy render (default 4)")
    p.add_argument("--ref-spp", type=int, default=1024, help="samples per pixel of the reference (default 1024)")
    p.add_argument("--seed", type=int, default=1, help="noisy seed; the reference uses seed + 1000")
    p.add_argument("--threads", type=int, default=0, help="Cycles CPU threads (0: the file's setting)")
    p.add_argument("--no-reference", action="store_true", help="render only the noisy frames (unlabeled)")
    p.add_argument("--force", action="store_true", help="render every frame again")
    return p.parse_args(argv)


def file_sha256(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def main(argv=None) -> int:
    args = parse_args(sys.argv[1:] if argv is None else argv)
    try:
        bpy.ops.wm.open_mainfile(filepath=str(args.scene))
    except RuntimeError as exc:
        refuse(f"{args.scene}: Blender cannot open it ({str(exc).strip().splitlines()[-1]})")
    scene = bpy.context.scene
    why = refusal(scene)
    if why:
        refuse(f"{args.scene}: {why}")
    first, last = args.frames or (scene.frame_start, scene.frame_end)
    if last < first:
        refuse(f"frames {first}-{last}: the last frame is before the first")
    changed = apply_settings(scene) + [c for layer in scene.view_layers if layer.use for c in enable_passes(layer)]
    changed += set_exr_output(scene)
    if args.threads > 0:
        scene.render.threads_mode = "FIXED"
        scene.render.threads = args.threads
    r = scene.render
    width, height = r.resolution_x * r.resolution_percentage // 100, r.resolution_y * r.resolution_percentage // 100
    wanted = {"blender": bpy.app.version_string, "scene": args.scene.name, "scene_sha256": file_sha256(args.scene),
              "width": width, "height": height, "noisy": {"spp": args.spp, "seed": args.seed}}
    if not args.no_reference:
        wanted["reference"] = {"spp": args.ref_spp, "seed": args.seed + 1000}
    info_path = args.out / "render.json"
    info = {}
    if info_path.exists() and not args.force:
        try:
            info = json.loads(info_path.read_text())
        except ValueError as exc:
            refuse(f"{info_path}: not JSON ({exc}); --force renders every frame again")
        differ = [k for k in sorted(set(wanted) | set(info) - set(RECORD_ONLY)) if info.get(k) != wanted.get(k)]
        if differ:
            refuse(f"{info_path}: rendered with other settings ({', '.join(f'{k}: {info.get(k)} -> {wanted.get(k)}' for k in differ)}); "
                   "force=true renders every frame again, or choose another out=")
    print(f"{PROG}: {args.scene} (Blender {bpy.app.version_string}), {width}x{height}, frames {first}-{last}, "
          f"{args.spp} spp noisy" + ("" if args.no_reference else f", {args.ref_spp} spp reference") + f" -> {args.out}",
          flush=True)
    for line in changed:
        print(f"{PROG}: changed {line}", flush=True)
    if not changed:
        print(f"{PROG}: the file's render settings and passes are already as the layout needs", flush=True)
    frames = range(first, last + 1)
    seconds = info.get("seconds", {})
    passes = [("noisy", args.spp, args.seed)] + ([] if args.no_reference else [("reference", args.ref_spp, args.seed + 1000)])
    for name, spp, seed in passes:
        took = render_frames(scene, args.out / name, frames, spp, seed, name, keep=not args.force, prefix=PROG)
        seconds[name] = {**seconds.get(name, {}), **{str(f): round(s, 3) for f, s in took.items()}}
    on_disk = sorted(int(p.stem) for p in (args.out / "noisy").glob("*.exr") if p.stem.isdigit())
    record = {**wanted, "frames": on_disk, "changed": sorted(set(info.get("changed", [])) | set(changed)),
              "seconds": seconds}
    partial = info_path.with_name(info_path.name + ".partial")
    partial.write_text(json.dumps(record, indent=2) + "\n")
    partial.replace(info_path)
    print(f"{PROG}: {len(on_disk)} frame(s) in {args.out}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
