"""Where a recurrent denoiser's history goes wrong: per-pixel maps and region statistics of one frame.

Issue 33: under fast object motion a student's output on frames 2+ was no better than its noisy
input. This module runs a checkpoint over a sequence through the one recurrent runner
(:class:`~denoiser.recurrent.RecurrentRunner`) up to a chosen frame and records, for that frame,
what the temporal recurrence did (:mod:`denoiser.nn.temporal`): the predicted blend weights
``a`` (history color into the filter input) and ``b`` (history output into the output), the
disocclusion gate, the bilinear coverage, and the warped history itself, read through
``TemporalRecurrence.probe`` (records tensors, changes no value).

Errors are per pixel on tonemapped values (:func:`denoiser.metrics.tonemap`, the domain of
PSNR): ``e(x) = mean over RGB of (tonemap(x) - tonemap(ref))^2``, and a region's "PSNR" is
``10 log10(1 / mean e)``. The warped history is *wrong* at a pixel when its error exceeds the
noisy input's error averaged over the ``LOCAL_BOX`` x ``LOCAL_BOX`` neighbourhood (the local
noise level: history worse than simply taking the noisy input), *right* otherwise.

Regions from the motion vectors (a camera pan moves everything alike, so motion is taken
relative to the frame's median motion): *moving* = ``|motion - median| > MOVING_PX``; *edge* =
the band of ``EDGE_PX`` pixels on both sides of the moving mask's boundary; *interior* = moving
minus edge; *background* = the rest; *uncovered* = background pixels that were moving in the
previous frame (an object was there at t-1 and is gone at t: disocclusions, exact for a static
camera). Rows ``gate < 1`` are the pixels where the disocclusion gate rejects history at least
partly.

Outputs (:func:`diagnose`): ``<out>/<sequence>_f<frame>.png`` (a grid of maps) and
``<out>/<sequence>_f<frame>.md`` (the statistics table and the decision fractions).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from denoiser.atomic import atomic_save_figure, atomic_write_text
from denoiser.buffers import FRAME_INPUTS
from denoiser.errors import UserError, first_line
from denoiser.metrics import mse_to_psnr, tonemap
from denoiser.recurrent import RecurrentRunner

#: px: a pixel moves when its motion differs from the frame's median motion by more than this
MOVING_PX = 0.5
#: px: half-width of the band around the moving mask's boundary counted as "edge"
EDGE_PX = 2
#: box size of the noisy input's local error level that tells wrong history from right
LOCAL_BOX = 5
#: the default frame is the one with the largest mean motion among frames >= this
FIRST_FRAME = 2
#: weight above which a pixel "keeps" its history
KEEP = 0.5


@dataclass
class Capture:
    """One frame's tensors: ``images`` ``{name: [1, 3, H, W]}`` linear HDR (noisy, output,
    reference, warped history), ``weights`` ``{name: [1, 1, H, W]}`` in [0, 1] (``history_in``
    a, ``history_out`` b, ``gate``, ``cover``), ``motion [1, 2, H, W]`` and ``previous_motion
    [1, 2, H, W]`` (pixels, backward), ``frame`` its index."""

    frame: int
    images: dict[str, torch.Tensor]
    weights: dict[str, torch.Tensor]
    motion: torch.Tensor
    previous_motion: torch.Tensor


def open_sequence(directory: str | os.PathLike, layout):
    """``(source, dataset)`` of one labeled sequence directory (UserError naming it otherwise)."""
    from denoiser.data.dataset import SequenceDataset

    source = layout.open_sequence(Path(directory))
    if not source.labeled:
        raise UserError(f"{directory}: sequence has no reference buffer; the diagnosis compares with it")
    missing = [b for b in FRAME_INPUTS if b not in source.buffers]
    if missing:
        raise UserError(f"{directory}: sequence lacks buffer(s) {', '.join(missing)}")
    return source, SequenceDataset([source], layout, list(FRAME_INPUTS), window=1, labeled=True, cache_dir=None)


def mean_motion(layout, source) -> list[float]:
    """Mean ``|motion|`` in pixels of every frame of ``source`` (frame 0: its own vectors)."""
    out = []
    for i in range(source.frames):
        arrays, _ = layout.read_frame(source, i, ["motion"])
        out.append(float(np.linalg.norm(arrays["motion"], axis=-1).mean()))
    return out


def pick_frame(motion: list[float], first: int = FIRST_FRAME) -> int:
    """The frame >= ``first`` (or the last, for shorter sequences) with the largest mean motion."""
    if not motion:
        raise UserError("sequence has no frames")
    first = min(first, len(motion) - 1)
    return first + int(np.argmax(motion[first:]))


def capture(net, dataset, source, frame: int, progress: bool = True) -> Capture:
    """Run ``net`` over frames ``0..frame`` of ``source`` (state carried, reset at cuts) and record
    the last one (:class:`Capture`). ``net``: a :class:`~denoiser.nn.denoiser.Denoiser` with
    temporal recurrence, in eval mode; its probe is switched on for the run and off after."""
    from tqdm.auto import tqdm

    from denoiser.data.evalset import read_frame
    from denoiser.nn.inputs import demodulation_albedo

    temporal = getattr(net, "temporal", None)
    if temporal is None:
        raise UserError("the network has no temporal recurrence (net.temporal is null): no history to diagnose")
    if not 0 <= frame < source.frames:
        raise UserError(f"{source.directory}: frame {frame} out of range (0..{source.frames - 1})")
    seen: dict[int, tuple[dict, torch.Tensor]] = {}

    def frames():
        for i in tqdm(range(frame + 1), desc=f"diagnose {source.name}", unit="frame", disable=not progress):
            inputs, reference, reset = read_frame(dataset, source, i)
            seen.clear()
            seen[i] = inputs, reference
            yield inputs, reset

    runner = RecurrentRunner(net.step)
    temporal.probe = {}
    try:
        with torch.no_grad():
            for output in runner.run(frames()):
                pass
        probe = dict(temporal.probe)
    finally:
        temporal.probe = None
    inputs, reference = seen[frame]
    weights = runner.extras[0]["weights"]
    warped = probe["history"]["output"]
    if getattr(net, "demodulate", False):  # the state holds irradiance: remodulate as the output is
        warped = warped * weights.get("remodulation", demodulation_albedo(inputs["albedo"]))
    previous = read_frame(dataset, source, frame - 1)[0]["motion"] if frame > 0 else torch.zeros_like(inputs["motion"])
    return Capture(
        frame=frame,
        images={"noisy": inputs["color"].float(), "output": output.float(), "reference": reference.float(),
                "warped history": warped.float()},
        weights={"history_in": weights["history_in"].float(), "history_out": weights["history_out"].float(),
                 "gate": probe["gate"].float(), "cover": probe["cover"].float()},
        motion=inputs["motion"].float(), previous_motion=previous.float())


def pixel_error(image: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Squared tonemapped error, mean over RGB: ``[1, 3, H, W]`` pair -> ``[1, 1, H, W]``."""
    return (tonemap(image) - tonemap(reference)).pow(2).mean(dim=1, keepdim=True)


def _moving(motion: torch.Tensor) -> torch.Tensor:
    """``[1, 2, H, W]`` -> bool ``[1, 1, H, W]``: motion off the frame's median by > MOVING_PX."""
    median = motion.flatten(2).median(dim=2).values[..., None, None]
    return (motion - median).norm(dim=1, keepdim=True) > MOVING_PX


def _dilate(mask: torch.Tensor, r: int) -> torch.Tensor:
    return F.max_pool2d(mask.float(), 2 * r + 1, stride=1, padding=r) > 0.5


def regions(cap: Capture) -> dict[str, torch.Tensor]:
    """Pixel sets of the module docstring, each bool ``[1, 1, H, W]``: all, background, edge,
    interior, uncovered, warped right, warped wrong, gate < 1."""
    moving = _moving(cap.motion)
    edge = _dilate(moving, EDGE_PX) & _dilate(~moving, EDGE_PX)
    noisy = pixel_error(cap.images["noisy"], cap.images["reference"])
    local = F.avg_pool2d(noisy, LOCAL_BOX, stride=1, padding=LOCAL_BOX // 2, count_include_pad=False)
    wrong = pixel_error(cap.images["warped history"], cap.images["reference"]) > local
    has_history = cap.weights["cover"] > 0
    return {
        "all": torch.ones_like(moving),
        "background": ~moving & ~edge,
        "edge": edge,
        "interior": moving & ~edge,
        "uncovered": ~moving & _moving(cap.previous_motion),
        "warped right": has_history & ~wrong,
        "warped wrong": has_history & wrong,
        "gate < 1": cap.weights["gate"] < 1.0,
    }


def _psnr(err: torch.Tensor, mask: torch.Tensor) -> float:
    return float(mse_to_psnr(err[mask].mean())) if bool(mask.any()) else float("nan")


def _mean(x: torch.Tensor, mask: torch.Tensor) -> float:
    return float(x[mask].mean()) if bool(mask.any()) else float("nan")


def statistics(cap: Capture) -> list[dict]:
    """One row per region of :func:`regions`: ``{"region", "pixels", "share", "psnr_noisy",
    "psnr_warped", "psnr_output", "a", "b", "gate", "cover", "keep_a", "keep_b"}`` (PSNR in dB
    of the region's pixels, the warped history's over those with history, coverage > 0; means of
    the weights; ``keep_*``: share of the region's pixels whose weight exceeds ``KEEP``)."""
    ref = cap.images["reference"]
    errors = {k: pixel_error(cap.images[k], ref) for k in ("noisy", "warped history", "output")}
    a, b = cap.weights["history_in"], cap.weights["history_out"]
    total = ref.shape[-1] * ref.shape[-2]
    rows = []
    for name, mask in regions(cap).items():
        rows.append({
            "region": name, "pixels": int(mask.sum()), "share": float(mask.sum()) / total,
            "psnr_noisy": _psnr(errors["noisy"], mask),
            "psnr_warped": _psnr(errors["warped history"], mask & (cap.weights["cover"] > 0)),
            "psnr_output": _psnr(errors["output"], mask),
            "a": _mean(a, mask), "b": _mean(b, mask), "gate": _mean(cap.weights["gate"], mask),
            "cover": _mean(cap.weights["cover"], mask),
            "keep_a": _mean((a > KEEP).float(), mask), "keep_b": _mean((b > KEEP).float(), mask),
        })
    return rows


def _num(value: float, places: int = 2) -> str:
    """A table number; NaN (an empty region) as n/a."""
    return "n/a" if np.isnan(value) else f"{value:.{places}f}"


def markdown(rows: list[dict], title: str) -> str:
    """The statistics table, then the few numbers that tell the failure modes apart."""
    header = ("| region | pixels | share | PSNR noisy dB | PSNR warped history dB | PSNR output dB "
              "| mean a (history in) | mean b (history out) | mean gate | mean cover | a > 0.5 | b > 0.5 |")
    lines = [f"# {title}", "", header, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        cells = [r["region"], str(r["pixels"]), _num(r["share"], 3)]
        cells += [_num(r[k]) for k in ("psnr_noisy", "psnr_warped", "psnr_output")]
        cells += [_num(r[k], 3) for k in ("a", "b", "gate", "cover", "keep_a", "keep_b")]
        lines.append("| " + " | ".join(cells) + " |")
    by = {r["region"]: r for r in rows}
    wrong, right, gated, uncovered = by["warped wrong"], by["warped right"], by["gate < 1"], by["uncovered"]
    lines += [
        "",
        (f"- history weight where the warped history is wrong vs right: a {_num(wrong['a'], 3)} vs "
         f"{_num(right['a'], 3)}, b {_num(wrong['b'], 3)} vs {_num(right['b'], 3)} "
         "(how to read: alike would mean the blend weights do not see the error)"),
        (f"- gate-rejected pixels (gate < 1): {_num(gated['share'], 3)} of the frame; of them a > 0.5: "
         f"{_num(gated['keep_a'], 3)}, b > 0.5: {_num(gated['keep_b'], 3)}"),
        (f"- uncovered pixels (background now, moving at t-1): {uncovered['pixels']}, mean gate "
         f"{_num(uncovered['gate'], 3)}, mean b {_num(uncovered['b'], 3)} (how to read: a gate near 1 would mean it misses the disocclusion)"),
        (f"- warped history PSNR edge / interior / background: {_num(by['edge']['psnr_warped'])} / "
         f"{_num(by['interior']['psnr_warped'])} / {_num(by['background']['psnr_warped'])} dB "
         "(how to read: a low interior means motion vectors or the warp wrong on the object; a low edge, disocclusions and "
         "mixed pixels)"),
        "",
    ]
    return "\n".join(lines)


def save_grid(path: str | os.PathLike, cap: Capture, title: str) -> Path:
    """Write the PNG grid of maps (row 1: images, row 2: weights, row 3: errors and motion)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from denoiser.report.plot_crops import to_display

    ref = cap.images["reference"]
    errors = {f"|{k} - ref|^2": pixel_error(cap.images[k], ref)[0, 0].numpy()
              for k in ("noisy", "warped history", "output")}
    vmax = float(np.quantile(errors["|noisy - ref|^2"], 0.99)) or 1.0
    motion = cap.motion[0].norm(dim=0).numpy()
    masks = regions(cap)
    labels = np.zeros(motion.shape, np.float32)      # 0 background, 1 edge, 2 interior, 3 uncovered
    for value, name in enumerate(("edge", "interior", "uncovered"), start=1):
        labels[masks[name][0, 0].numpy()] = value
    rows = [
        [(k, to_display(v), {}) for k, v in cap.images.items()],
        [*[(k, v[0, 0].numpy(), {"cmap": "viridis", "vmin": 0.0, "vmax": 1.0}) for k, v in cap.weights.items()],
         ("regions: bg/edge/interior/uncovered", labels, {"cmap": "tab10", "vmin": 0.0, "vmax": 10.0})],
        [*[(k, v, {"cmap": "magma", "vmin": 0.0, "vmax": vmax}) for k, v in errors.items()],
         ("|motion| px", motion, {"cmap": "inferno", "vmin": 0.0, "vmax": max(float(motion.max()), 1e-6)}),
         ("warped history wrong", masks["warped wrong"][0, 0].float().numpy(),
          {"cmap": "gray", "vmin": 0.0, "vmax": 1.0})],
    ]
    h, w = ref.shape[-2:]
    cols = max(len(r) for r in rows)
    scale = max(1.0, 160.0 / max(h, w))
    fig, axes = plt.subplots(len(rows), cols, figsize=(cols * (w * scale / 100 + 0.6), len(rows) * (h * scale / 100 + 0.5)),
                             dpi=100, squeeze=False)
    for ax_row, row in zip(axes, rows):
        for ax in ax_row:
            ax.axis("off")
        for ax, (label, image, style) in zip(ax_row, row):
            shown = ax.imshow(image, interpolation="nearest", **style)
            scalar = image.ndim == 2 and style.get("cmap") != "tab10"   # tab10: region labels
            ax.set_title(f"{label} (mean {image.mean():.3g})" if scalar else label, fontsize=7)
            if scalar:
                fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.02).ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    return atomic_save_figure(fig, path)


def diagnose(ckpt: str | os.PathLike, sequence: str | os.PathLike, layout: str = "native",
             out_dir: str | os.PathLike = "reports/diagnose", frame: int | None = None, trust: bool = False,
             net=None, progress: bool = True) -> dict:
    """Load ``ckpt`` (or use ``net``), run it over ``sequence`` (a directory in ``layout``) up to
    ``frame`` (None: :func:`pick_frame`), write the grid and the table into ``out_dir``.

    Returns ``{"png": path, "markdown": path, "frame": index, "rows": statistics, "capture": Capture}``.
    """
    from denoiser.checkpoint import load_denoiser
    from denoiser.configs import load_layout

    if net is None:
        net = load_denoiser(ckpt, "cpu", trust=trust)
    lay = load_layout(layout)
    source, dataset = open_sequence(sequence, lay)
    if frame is None:
        frame = pick_frame(mean_motion(lay, source))
    try:
        cap = capture(net, dataset, source, int(frame), progress=progress)
    except (KeyError, RuntimeError) as exc:  # e.g. a frame of another size than the first
        raise UserError(f"{sequence}: frame {frame}: {first_line(exc)}") from None
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    stem = f"{Path(sequence).name}_f{cap.frame}"
    title = f"{Path(sequence).name} frame {cap.frame} ({Path(ckpt).name if ckpt else 'network'}, layout={layout})"
    png = save_grid(out / f"{stem}.png", cap, title)
    rows = statistics(cap)
    md = out / f"{stem}.md"
    atomic_write_text(md, markdown(rows, title))
    return {"png": png, "markdown": md, "frame": cap.frame, "rows": rows, "capture": cap}


__all__ = ["Capture", "capture", "diagnose", "markdown", "open_sequence", "pick_frame",
           "pixel_error", "regions", "save_grid", "statistics"]
