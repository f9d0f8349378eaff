"""How a recurrent denoiser's output follows the noise level of its input.

For each factor ``f`` the noisy colour of every frame is replaced by ``reference + f * (color -
reference)`` (the residual scaled by ``f``: the variance of a render with ``spp / f^2`` samples;
:func:`denoiser.data.augment.scale_noise`, the training augmentation's rule), with the per-sample
colours, when the sequence has them, scaled alike; ``f = 1`` is the sequence itself. The network runs over the whole
sequence (state carried, reset at cuts) and the table gives the PSNR (dB, tonemapped,
:func:`denoiser.metrics.psnr`) of its input and its output on frame 0 (no history) and over frames
2+ (the history in use). A denoiser that adapts to the noise gives a cleaner output for a cleaner
input and, for a clean enough input, at least the input's PSNR; one trained on a single noise
level blurs every input to about the same output (docs/results_log.md, "Fast object motion:
noise-level augmentation"). With ``grey``, every frame's colour, per-sample colours, albedo and
reference are first replaced by their luminance (:data:`denoiser.metrics.LUMINANCE`) in all three
channels, so that one network's figures on the colour and the grey versions of a sequence show
what its colours cost.

    python -m denoiser.commands.tools.noise_response ckpt=S.ckpt sequences=[data/blender/val/fast_101] layout=blender
"""

from __future__ import annotations

import os
import textwrap
from collections.abc import Sequence
from pathlib import Path

import torch

from denoiser.errors import UserError

#: history frames: the frames-2+ figure averages frames from this index on
FIRST_HISTORY_FRAME = 2


def scaled_inputs(inputs: dict, reference: torch.Tensor, factor: float) -> dict:
    """``inputs`` (:func:`denoiser.data.evalset.read_frame`'s: ``color [1, 3, H, W]``, ``samples [1, S, 3,
    H, W]`` optional) with the colour residual against ``reference [1, 3, H, W]`` scaled by ``factor``
    (:func:`denoiser.data.augment.scale_noise`; clamped at 0, which only ``factor > 1`` can need)."""
    from denoiser.data.augment import scale_noise

    out = scale_noise({**inputs, "reference": reference}, factor)
    del out["reference"]
    for key in ("color", "samples"):
        if key in out:
            out[key] = out[key].clamp_min(0)
    return out


def grey(x: torch.Tensor) -> torch.Tensor:
    """``[..., 3, H, W]`` linear RGB -> its luminance in all three channels (same shape)."""
    from denoiser.metrics import LUMINANCE

    w = torch.tensor(LUMINANCE, dtype=x.dtype, device=x.device).view(3, 1, 1)
    return (x * w).sum(dim=-3, keepdim=True).expand_as(x).contiguous()


def grey_frame(inputs: dict, reference: torch.Tensor) -> tuple[dict, torch.Tensor]:
    """``(inputs, reference)`` with ``color``, ``samples``, ``albedo`` and ``reference`` in grey."""
    out = dict(inputs)
    for key in ("color", "samples", "albedo"):
        if key in out:
            out[key] = grey(out[key])
    return out, grey(reference)


def response(net, dataset, source, factors: Sequence[float], grey_inputs: bool = False) -> list[dict]:
    """One row per factor: ``{"factor", "input_f0", "output_f0", "input_f2", "output_f2"}`` (PSNR dB;
    the ``_f2`` means are over frames 2+, None for sequences of 2 frames or fewer). ``net``: a
    :class:`~denoiser.nn.denoiser.Denoiser` in eval mode; ``dataset``, ``source``: as
    :func:`denoiser.report.history_diagnosis.open_sequence` returns them; ``grey_inputs``: the
    sequence in grey (:func:`grey_frame`)."""
    from denoiser.data.evalset import read_frame
    from denoiser.metrics import psnr
    from denoiser.recurrent import RecurrentRunner

    frames = [read_frame(dataset, source, i) for i in range(source.frames)]
    if grey_inputs:
        frames = [(*grey_frame(inputs, ref), reset) for inputs, ref, reset in frames]
    rows = []
    for f in factors:
        if not f > 0:
            raise UserError(f"factors: need factors > 0, got {f}")
        scaled = [(scaled_inputs(inputs, ref, float(f)), ref, reset) for inputs, ref, reset in frames]
        with torch.no_grad():
            outputs = list(RecurrentRunner(net.step).run((x, reset) for x, _, reset in scaled))
        p_in = [float(psnr(x["color"].float(), ref.float())) for x, ref, _ in scaled]
        p_out = [float(psnr(o.float(), ref.float())) for o, (_, ref, _) in zip(outputs, scaled)]
        later = slice(FIRST_HISTORY_FRAME, None)
        rows.append({"inputs": "grey" if grey_inputs else "colour", "factor": float(f), "input_f0": p_in[0], "output_f0": p_out[0],
                     "input_f2": _mean(p_in[later]), "output_f2": _mean(p_out[later])})
    return rows


def _mean(values: list[float]) -> float | None:
    return sum(values) / len(values) if values else None


def _num(x: float | None, sign: bool = False) -> str:
    return "" if x is None else (f"{x:+.2f}" if sign else f"{x:.2f}")


def markdown(results: dict[str, list[dict]], title: str) -> str:
    """The table of :func:`run`'s results ``{sequence: rows}``."""
    lines = [f"# {title}", "",
             ("PSNR dB of the input (the residual against the reference scaled by f; f = 1 is the sequence) and of "
              "the network's output; frames 2+: the history in use; inputs grey: colour, albedo and reference "
              "replaced by their luminance. A denoiser that adapts to the noise keeps at least the input's PSNR "
              "once the input is clean enough."), "",
             ("| sequence | inputs | f | input, frame 0 | output, frame 0 | input, frames 2+ | output, frames 2+ | "
              "output - input, frames 2+ |"), "|---|---|---:|---:|---:|---:|---:|---:|"]
    for name, rows in results.items():
        for r in rows:
            gain = None if r["input_f2"] is None else r["output_f2"] - r["input_f2"]
            lines.append(f"| {name} | {r['inputs']} | {r['factor']:g} | {_num(r['input_f0'])} | {_num(r['output_f0'])} | "
                         f"{_num(r['input_f2'])} | {_num(r['output_f2'])} | {_num(gain, sign=True)} |")
    return "\n".join(lines) + "\n"


def save_plot(path: str | os.PathLike, results: dict[str, list[dict]], title: str) -> Path:
    """A PNG of :func:`run`'s results: per sequence, the output's PSNR over frames 2+ against the
    input's (one point per factor; colour solid, grey dashed), with the line output = input."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from denoiser.atomic import atomic_save_figure

    fig, ax = plt.subplots(figsize=(6.4, 4.8), dpi=100)
    points = []
    for i, (name, rows) in enumerate(results.items()):
        colour = f"C{i % 10}"
        for inputs, style in (("colour", "-"), ("grey", "--")):
            xy = sorted((r["input_f2"], r["output_f2"]) for r in rows if r["inputs"] == inputs and r["input_f2"] is not None)
            if xy:
                ax.plot(*zip(*xy), style, marker="o", color=colour, label=f"{name} ({inputs})")
                points += xy
    if points:
        lo, hi = min(min(p) for p in points), max(max(p) for p in points)
        ax.plot([lo, hi], [lo, hi], ":", color="grey", label="output = input")
    ax.set_xlabel("input PSNR dB, frames 2+ (the residual scaled by f)")
    ax.set_ylabel("output PSNR dB, frames 2+")
    ax.set_title("\n".join(textwrap.wrap(title, 70)), fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    return atomic_save_figure(fig, path)


def run(ckpt: str | os.PathLike, sequences: Sequence[str | os.PathLike], layout: str = "native",
        factors: Sequence[float] = (0.25, 0.5, 1.0, 2.0), out: str | os.PathLike | None = None,
        trust: bool = False, net=None, grey_too: bool = False, plot: str | os.PathLike | None = None
        ) -> tuple[dict[str, list[dict]], str]:
    """Load ``ckpt`` (or use ``net``), run :func:`response` on every sequence directory (in
    ``layout``; with ``grey_too``, on its grey version as well); write the table to ``out`` and the
    plot (:func:`save_plot`) to ``plot`` when given. Returns ``({sequence name: rows}, markdown)``."""
    from denoiser.atomic import atomic_write_text
    from denoiser.checkpoint import load_denoiser
    from denoiser.configs import load_layout
    from denoiser.report.history_diagnosis import open_sequence

    if not sequences:
        raise UserError("sequences: name at least one labeled sequence directory")
    if net is None:
        net = load_denoiser(ckpt, "cpu", trust=trust)
    net.eval()
    lay = load_layout(layout)
    results = {}
    for seq in sequences:
        source, dataset = open_sequence(seq, lay)
        rows = response(net, dataset, source, factors)
        if grey_too:
            rows += response(net, dataset, source, factors, grey_inputs=True)
        results[Path(seq).name] = rows
    title = f"Noise response of {ckpt if ckpt else 'a network'} (layout={layout})"
    text = markdown(results, title)
    if out is not None:
        atomic_write_text(Path(out), text)
    if plot is not None:
        save_plot(plot, results, title)
    return results, text


__all__ = ["grey", "grey_frame", "markdown", "response", "run", "save_plot", "scaled_inputs"]
