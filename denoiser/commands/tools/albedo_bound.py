"""How far can a demodulating denoiser get on renders whose albedo pass is noisy?
``python -m denoiser.commands.tools.albedo_bound``.

A network with ``net.demodulate: true`` filters ``color / albedo`` and multiplies its output by
the *input's* albedo again. Renderers that average the albedo over the pixel's samples (Cycles'
``Denoising Albedo``, at 4 spp) give an albedo with the same sub-pixel texture noise as the
colour, and the remodulation puts that noise back. This command measures the ceiling it sets:
the reference irradiance (reference colour / reference albedo, both from the high-spp render)
remodulated with the noisy render's albedo, against the reference colour, with the metrics of
``denoiser-eval`` (PSNR on ACES+sRGB tonemapped frames, ``denoiser.metrics``).

Usage::

    python -m denoiser.commands.tools.albedo_bound data/blender/test [--out reports/blender/albedo_bound.md] [--warmup 2]

Reads the splits through the Blender layout (``conf/layout/blender.yaml``: its pass aliases and
view-layer prefixes), with one buffer more for this tool, the reference render's albedo
(``reference_albedo``); the first ``--warmup`` frames are skipped, as in ``denoiser-eval``.
Prints a Markdown table (noisy input, the bound) per sequence and the mean, and writes it to
``--out`` when given. ``out=...`` and ``warmup=...`` are accepted as well as ``--out ...``; a bad
input (no sequences, a missing reference frame) is one line ``error: ...`` on stderr and exit 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

from denoiser.atomic import atomic_write_text
from denoiser.commands.app import CommandParser, report_user_error
from denoiser.configs import load_layout
from denoiser.errors import UserError
from denoiser.metrics import psnr
from denoiser.nn.inputs import demodulation_albedo

#: the buffer this tool reads beside the layout's own (color, albedo, reference)
REFERENCE_ALBEDO = {"reference_albedo": {"file": "reference", "passes": ["Denoising Albedo"], "channels": ["R", "G", "B"]}}


def _tensor(array: np.ndarray) -> torch.Tensor:
    """``[H, W, 3]`` -> ``[1, 3, H, W]`` float32."""
    return torch.from_numpy(np.ascontiguousarray(array.transpose(2, 0, 1)))[None]


def sequence_bound(layout, seq: Path, warmup: int) -> tuple[float, float, int]:
    """Mean PSNR (noisy input, remodulation bound) over the frames of one sequence, and the frame count."""
    source = layout.open_sequence(seq)
    if not source.labeled:
        raise UserError(f"{seq}: no reference/ frames; the bound needs the reference render")
    rows = []
    for i in range(warmup, source.frames):
        arrays, _ = layout.read_frame(source, i, ["color", "albedo", "reference", "reference_albedo"])
        color, albedo, ref_color, ref_albedo = (_tensor(arrays[b]) for b in
                                                ("color", "albedo", "reference", "reference_albedo"))
        irradiance = ref_color / demodulation_albedo(ref_albedo)
        bound = irradiance * demodulation_albedo(albedo)
        rows.append((psnr(color, ref_color).item(), psnr(bound, ref_color).item()))
    if not rows:
        raise UserError(f"{seq}: no frames after the {warmup} warm-up frame(s)")
    a = np.array(rows).mean(axis=0)
    return float(a[0]), float(a[1]), len(rows)


def main(argv=None) -> int:
    p = CommandParser("denoiser.commands.tools.albedo_bound", __doc__)
    p.add_argument("split_dir", type=Path, help="a Blender-layout split, e.g. data/blender/test")
    p.add_argument("--warmup", type=int, default=2, help="frames skipped at the start (default 2, as denoiser-eval)")
    p.add_argument("--out", type=Path, default=None, help="also write the table to this Markdown file")
    args = p.parse_args(argv)
    try:
        if args.warmup < 0:
            raise UserError(f"warmup: {args.warmup} is negative (frames skipped at the start)")
        layout = load_layout("blender", REFERENCE_ALBEDO)
        seqs = layout.list_sequences(args.split_dir) if args.split_dir.is_dir() else []
        if not seqs:
            raise UserError(f"{args.split_dir}: no sequences (directories with noisy/ and reference/)")
        lines = ["| sequence | frames | noisy PSNR dB | bound PSNR dB (reference irradiance x noisy albedo) |",
                 "|---|---:|---:|---:|"]
        results = []
        for seq in seqs:
            n, b, frames = sequence_bound(layout, seq, args.warmup)
            results.append((n, b))
            lines.append(f"| {seq.name} | {frames} | {n:.2f} | {b:.2f} |")
        mean = np.array(results).mean(axis=0)
        lines.append(f"| mean |  | {mean[0]:.2f} | {mean[1]:.2f} |")
        text = "\n".join(lines) + "\n"
        if args.out is not None:
            try:
                args.out.parent.mkdir(parents=True, exist_ok=True)
                atomic_write_text(args.out, text)
            except OSError as e:
                raise UserError(f"{args.out}: cannot write: {e.strerror or e}") from None
    except UserError as e:  # ExrError included
        report_user_error(e)
    print(text, end="")
    return 0


if __name__ == "__main__":
    sys.exit(main())
