"""Ship release networks: ``python -m denoiser.commands.tools.release_ship`` (make release's ship stage).

Usage::

    python -m denoiser.commands.tools.release_ship teacher=reports/release/runs/teacher \\
        student=reports/release/runs/student_s0 [out=denoiser/models] [fp16=auto|true|false] \\
        [data=release,release_motion,...] [figure=Title:reports/release/summary.md ...] [goals=goals.json]

Each of ``teacher`` / ``student`` is a checkpoint file or a training run directory (its
``best.ckpt``, else ``last.ckpt``). Writes into ``out`` (atomically, file by file): ``<name>.pt``
(the net config and its weights only: no optimizer, no pickled object; float16 storage when
``fp16=auto`` and the outputs stay within :data:`denoiser.release.FP16_TOLERANCE`, or ``true``),
``release.json`` (the manifest: :mod:`denoiser.report.model_card`) and ``README.md`` (the model card
it renders to). A file above :data:`denoiser.release.MAX_FILE_BYTES` is refused. ``figure=Title:path``
copies a report's Markdown into the card (repeatable); ``goals=`` a JSON list of
``{goal, met, figure}``. Then ``release:teacher`` / ``release:student`` load them everywhere.
"""

from __future__ import annotations

import datetime as dt
import json
import sys
from pathlib import Path

import torch

from denoiser.atomic import atomic_path, atomic_write_text
from denoiser.checkpoint import NET_PREFIX, load_denoiser, net_config, read_checkpoint, resolve_checkpoint
from denoiser.commands.app import CommandParser, report_user_error
from denoiser.configs import plain
from denoiser.errors import UserError
from denoiser.release import CARD, FP16_TOLERANCE, MANIFEST, MAX_FILE_BYTES, NAMES, fp16_output_error
from denoiser.report.model_card import file_sha256, render_card
from denoiser.report.provenance import git_commit


def _run_seed(ckpt_path: Path):
    """The seed of the training run that wrote ``ckpt_path`` (``<run>/.hydra/config.yaml``), else None."""
    from omegaconf import OmegaConf

    cfg = ckpt_path.parent.parent / ".hydra" / "config.yaml"
    return OmegaConf.load(cfg).get("seed") if cfg.is_file() else None


def ship_network(name: str, source: str, out: Path, fp16: str = "auto") -> dict:
    """Write ``<out>/<name>.pt`` from the checkpoint ``source``; its manifest entry."""
    path = resolve_checkpoint(source)
    ckpt = read_checkpoint(path)
    cfg = net_config(ckpt, path)
    net = load_denoiser(path)
    error = fp16_output_error(net)
    half = fp16 == "true" or (fp16 == "auto" and error <= FP16_TOLERANCE)
    state = {NET_PREFIX + k: (v.to(torch.float16) if half and v.is_floating_point() else v).detach().cpu().clone()
             for k, v in net.state_dict().items()}
    target = out / f"{name}.pt"
    with atomic_path(target) as tmp:
        torch.save({"hyper_parameters": {"net": dict(plain(cfg))}, "state_dict": state}, tmp)
        size = tmp.stat().st_size
        if size > MAX_FILE_BYTES:
            raise UserError(f"{source}: the {name}'s weights take {size / 2**20:.1f} MiB, over the "
                            f"{MAX_FILE_BYTES // 2**20} MiB a shipped file may take (try fp16=true)")
    return {"file": target.name, "sha256": file_sha256(target), "bytes": target.stat().st_size,
            "dtype": "float16" if half else "float32", "fp16_output_error": error,
            "parameters": sum(p.numel() for p in net.parameters()), "net": cfg.get("_target_"),
            "source": str(path), "global_step": ckpt.get("global_step"), "seed": _run_seed(path)}


def ship(networks: dict[str, str], out: str | Path, fp16: str = "auto", data=(), figures=(), goals=()) -> dict:
    """Ship ``{name: checkpoint}`` into ``out``; writes the manifest and the card; returns the manifest."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    manifest = {"commit": git_commit(), "created": dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
                "rebuild": "make release", "networks": {}, "data": list(data), "figures": [], "goals": list(goals)}
    for name, source in networks.items():
        manifest["networks"][name] = ship_network(name, source, out, fp16)
    for title, source in figures:
        text = Path(source).read_text() if Path(source).is_file() else None
        if text is None:
            raise UserError(f"{source}: no such report to copy into the model card")
        manifest["figures"].append({"title": title, "source": str(source), "text": text})
    atomic_write_text(out / MANIFEST, json.dumps(manifest, indent=2) + "\n")
    atomic_write_text(out / CARD, render_card(manifest))
    return manifest


def main(argv=None) -> int:
    parser = CommandParser("denoiser.commands.tools.release_ship", __doc__)
    for name in NAMES:
        parser.add_argument(f"--{name}", help=f"the {name}'s checkpoint or run directory")
    parser.add_argument("--out", default=None, help="folder shipped into (default: denoiser/models of this checkout)")
    parser.add_argument("--fp16", default="auto", choices=["auto", "true", "false"])
    parser.add_argument("--data", default="", help="comma-separated render sets / roots the networks were trained on")
    parser.add_argument("--figure", action="append", default=[], help="Title:path of a report copied into the card")
    parser.add_argument("--goals", default=None, help="a JSON file: [{goal, met, figure}]")
    args = parser.parse_args(argv)
    try:
        from denoiser.release import models_dir

        networks = {n: getattr(args, n) for n in NAMES if getattr(args, n)}
        if not networks:
            raise UserError("release_ship: give teacher=<checkpoint> and/or student=<checkpoint>")
        figures = []
        for f in args.figure:
            if ":" not in f:
                raise UserError(f"figure={f}: expected Title:path")
            figures.append(tuple(f.split(":", 1)))
        goals = json.loads(Path(args.goals).read_text()) if args.goals else []
        manifest = ship(networks, args.out or models_dir(), args.fp16, [d for d in args.data.split(",") if d],
                        figures, goals)
    except UserError as exc:
        report_user_error(exc)
    for name, n in manifest["networks"].items():
        print(f"shipped release:{name}: {n['file']} ({n['bytes'] / 2**20:.1f} MiB, {n['dtype']}, "
              f"step {n['global_step']}) from {n['source']}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
