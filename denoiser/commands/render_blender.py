"""``denoiser-render-blender``: a user's ``.blend`` file rendered with Cycles into the layout that
``layout=blender`` reads::

    denoiser-render-blender scene=shot.blend frames=1-48 out=data/mine split=train spp=4 ref_spp=1024
    denoiser-render-blender scene=shot.blend frames=49-96 out=data/mine split=unlabeled   # noisy frames only

Writes ``<out>/<split>/<sequence>/noisy/<frame:04d>.exr`` (``spp`` samples, seed ``seed``), for every
split but ``unlabeled`` ``.../reference/<frame:04d>.exr`` (``ref_spp``, seed ``seed + 1000``), and
``render.json``, as ``scripts/blender_sequences.py`` writes the project's own scenes; ``sequence``
defaults to the file's name. Arguments are ``key=value`` (or ``--key=value``); ``--help`` lists them.
(Not a Hydra app: ``scene=`` would name the simulator's config group ``conf/scene/``.)

Blender runs in its own venv (``bpy`` needs Python 3.11; ``make blender-venv`` builds
``.venv-blender``): this command checks the arguments, runs ``scripts/blender_render.py`` with
``blender_python`` and then reads the first frame back through the blender layout. That script sets
the render settings the results depend on (``scripts/blender_cycles.py``; docs/guide.md, "Render
settings and passes") on the opened file, prints each one it changed, never saves the file, and refuses
with one line a scene that has motion blur on or no camera. Resumable: frames on disk are kept.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from denoiser.commands.app import CommandParser, report_user_error
from denoiser.errors import ConfigError, UserError

#: the checkout holding scripts/ (the bpy side is a script of the checkout, as its venv is)
CHECKOUT = Path(__file__).resolve().parents[2]
SCRIPT = CHECKOUT / "scripts" / "blender_render.py"
#: the splits of a dataset (conf/data/default.yaml); unlabeled has no reference
SPLITS = ("train", "val", "test", "unlabeled")
PROG = "denoiser-render-blender"


def frame_range(value) -> tuple[int, int] | None:
    """``frames=`` as ``(first, last)``: ``"a-b"`` or one frame ``n``; None keeps the file's range."""
    if value is None:
        return None
    match = re.fullmatch(r"\s*(\d+)\s*(?:-\s*(\d+))?\s*", str(value))
    if not match:
        raise ConfigError(f"frames={value}: not a frame range; give first-last, e.g. frames=1-48")
    first, last = int(match[1]), int(match[2] or match[1])
    if last < first:
        raise ConfigError(f"frames={value}: the last frame is before the first")
    return first, last


def parser() -> CommandParser:
    p = CommandParser("denoiser.commands.render_blender", __doc__)
    p.prog = PROG
    p.add_argument("--scene", type=Path, required=True, help="the .blend file (opened, never saved)")
    p.add_argument("--out", type=Path, required=True,
                   help="the dataset root: <out>/<split>/<sequence>/{noisy,reference}/<frame>.exr")
    p.add_argument("--split", default="train", help=f"{' | '.join(SPLITS)} (unlabeled: noisy frames only)")
    p.add_argument("--sequence", default=None, help="the sequence folder's name (default: the file's name)")
    p.add_argument("--frames", default=None, help="first-last, e.g. 1-48 (default: the file's frame range)")
    p.add_argument("--spp", type=int, default=4, help="samples per pixel of the noisy frames (default 4)")
    p.add_argument("--ref-spp", type=int, default=1024, help="samples per pixel of the references (default 1024)")
    p.add_argument("--seed", type=int, default=1, help="noisy seed; the references use seed + 1000 (default 1)")
    p.add_argument("--threads", type=int, default=0, help="Cycles CPU threads (default 0: the file's setting)")
    p.add_argument("--force", action="store_true", help="render every frame again (else frames on disk are kept)")
    p.add_argument("--blender-python", type=Path,
                   default=Path(os.environ.get("DENOISER_BLENDER_PYTHON", ".venv-blender/bin/python")),
                   help="a Python with bpy (default $DENOISER_BLENDER_PYTHON, else .venv-blender/bin/python; "
                        "make blender-venv builds it)")
    return p


def blender_command(args) -> tuple[list[str], Path]:
    """The bpy venv's command line for the parsed ``args`` and the sequence folder it writes;
    ConfigError (one line) for a bad value or no bpy venv."""
    scene = Path(args.scene)
    if not scene.is_file():
        raise ConfigError(f"scene={scene}: no such file")
    if scene.suffix != ".blend":
        raise ConfigError(f"scene={scene}: not a .blend file")
    if args.split not in SPLITS:
        raise ConfigError(f"split={args.split}: not one of {', '.join(SPLITS)}")
    for key in ("spp", "ref_spp"):
        if getattr(args, key) < 1:
            raise ConfigError(f"{key}={getattr(args, key)}: must be at least 1")
    python = Path(args.blender_python)
    if not python.is_file():
        raise ConfigError(f"blender_python={python}: no such Python; `make blender-venv` builds the bpy venv "
                          "(.venv-blender; `make blender` builds it too), or point blender_python= at one with bpy")
    if not SCRIPT.is_file():
        raise ConfigError(f"{SCRIPT}: missing; {PROG} runs from a checkout of the project (its scripts/)")
    seq_dir = Path(args.out) / args.split / (args.sequence or scene.stem)
    argv = [str(python), str(SCRIPT), "--scene", str(scene.resolve()), "--out", str(seq_dir),
            "--spp", str(args.spp), "--ref-spp", str(args.ref_spp), "--seed", str(args.seed),
            "--threads", str(args.threads)]
    frames = frame_range(args.frames)
    if frames:
        argv += ["--frames", str(frames[0]), str(frames[1])]
    if args.split == "unlabeled":
        argv.append("--no-reference")
    if args.force:
        argv.append("--force")
    return argv, seq_dir


def run(args) -> Path:
    """Render as ``args`` say (:func:`parser`) and read the first frame back; returns the sequence folder."""
    from denoiser.buffers import FRAME_INPUTS
    from denoiser.configs import load_layout

    argv, seq_dir = blender_command(args)
    proc = subprocess.run(argv, check=False, stderr=subprocess.PIPE, text=True)
    if proc.returncode != 0:
        lines = [line for line in proc.stderr.splitlines() if line.strip()]
        ours = [line for line in lines if line.startswith(f"{PROG}: ")]
        if not ours:
            sys.stderr.write(proc.stderr)
        reason = ours[-1].removeprefix(f"{PROG}: ") if ours else (lines[-1] if lines else "no message")
        raise UserError(f"Blender failed (exit {proc.returncode}): {reason}")
    sys.stderr.write(proc.stderr)
    layout = load_layout("blender")
    source = layout.open_sequence(seq_dir)
    layout.read_frame(source, 0, [*FRAME_INPUTS, *(["reference"] if source.labeled else [])])
    print(f"{PROG}: {seq_dir} reads with layout=blender: {source.frames} frame(s), {source.width}x{source.height}"
          + (", with references" if source.labeled else ", noisy only"))
    return seq_dir


def main(argv=None) -> int:
    args = parser().parse_args(argv)
    try:
        run(args)
    except UserError as exc:
        report_user_error(exc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
