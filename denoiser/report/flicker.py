"""Flicker without a reference: the warping error (``warp`` of :mod:`denoiser.metrics`) of a stream of frames.

The formula and how to read it are said once, in :mod:`denoiser.metrics` (``warp``,
:func:`~denoiser.metrics.masked_warp_error`). This module aligns frame t-1 to frame t with
frame t's backward motion (:mod:`denoiser.nn.warp`, bilinear) and builds the visibility mask
``M_t`` ``[N, 1, H, W]``, the same for every stream of the same frames:

* *in frame*: the bilinear footprint of ``p + motion(p)`` lies wholly inside frame t-1
  (:func:`~denoiser.nn.warp.coverage` ``>= 1 - 1e-6``), and the motion is finite;
* *visible in both frames* (disocclusions dropped), one of two tests:

  - ``forward-backward`` where frame t-1's forward motion exists (Blender's ``Vector`` (Z, W),
    the layout's optional buffer ``motion_next``: position in t-1 minus position in t, the same
    sign as ``motion``): with ``f`` that motion warped to t, kept where
    ``|m - f|^2 <= FB_ALPHA (|m|^2 + |f|^2) + FB_BETA`` (Ruder et al. 2016, "Artistic style transfer
    for videos", the test Lai et al. use for their occlusion masks);
  - ``guide`` otherwise: the disagreement ``D`` of the networks' disocclusion gate between the
    warped previous guide (albedo, normal, depth features) and the current one
    (:func:`denoiser.nn.temporal.guide_disagreement`), kept where ``D <= GATE_THRESHOLD`` (where the
    gate of the shipped networks, ``reject_threshold`` 0.1, passes history whole);
  - ``in-frame`` when the frames come with neither (no disocclusion test: said in every report).

:class:`FlickerMeter` streams frames (one at a time, several named streams: a noisy input and
its denoised output, methods side by side) and keeps per stream the per-frame warp error and
the share of pixels kept; NaN on the first frame and at cuts. :func:`warp_error` is the same
over a whole sequence held in memory. :func:`read_motion` reads what a layout's files give.
:func:`ordering_agreement` is the check that the measure orders methods as tPSNR does, from
``denoiser-eval``'s per-sequence rows.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from denoiser.errors import ExrError
from denoiser.metrics import masked_warp_error, tonemap
from denoiser.nn.inputs import guide_features
from denoiser.nn.temporal import guide_disagreement
from denoiser.nn.warp import coverage, grid_from_positions, sample_positions

#: coverage a kept pixel needs: its whole bilinear footprint inside the previous frame
COVER_FULL = 1.0 - 1e-6
#: forward-backward test ``|m - f|^2 <= FB_ALPHA (|m|^2 + |f|^2) + FB_BETA`` (pixels^2; Ruder et al.)
FB_ALPHA, FB_BETA = 0.01, 0.5
#: largest disocclusion-gate disagreement ``D`` kept (the shipped networks' ``reject_threshold``)
GATE_THRESHOLD = 0.1
#: the visibility tests, in the order they are preferred
MASKS = ("forward-backward", "guide", "in-frame")


@dataclass
class Alignment:
    """Frame t-1 aligned to frame t: the sampling grid and the visibility mask.

    grid: ``[N, H, W, 2]`` (``grid_sample``, ``align_corners=False``); visible: bool ``[N, 1, H, W]``;
    mask: which test built it (:data:`MASKS`).
    """

    grid: torch.Tensor
    visible: torch.Tensor
    mask: str

    def warp(self, previous: torch.Tensor) -> torch.Tensor:
        """``previous`` ``[N, C, H, W]`` (frame t-1) sampled at ``p + motion(p)``: ``[N, C, H, W]`` float32."""
        return F.grid_sample(previous.float(), self.grid, mode="bilinear", padding_mode="zeros", align_corners=False)

    def error(self, previous_tm: torch.Tensor, current_tm: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Warp error and share kept, ``([N], [N])``, of tonemapped frames ``[N, 3, H, W]`` at t-1 and t."""
        return masked_warp_error(current_tm, self.warp(previous_tm), self.visible)


def align(motion: torch.Tensor, previous_guide: torch.Tensor | None = None, guide: torch.Tensor | None = None,
          previous_next_motion: torch.Tensor | None = None) -> Alignment:
    """The :class:`Alignment` of frame t-1 to frame t (module docstring).

    motion: ``[N, 2, H, W]`` frame t's backward motion (pixels, x right, y down); previous_guide,
    guide: ``[N, 7, H, W]`` guide features of frames t-1 and t
    (:func:`~denoiser.nn.inputs.guide_features`) or None; previous_next_motion: ``[N, 2, H, W]``
    frame t-1's forward motion (``motion_next``) or None. The forward-backward test is used when
    it is given, else the guide test when both guides are, else only the in-frame test.
    """
    with torch.no_grad():
        motion = motion.float()
        sx, sy = sample_positions(motion)
        grid = grid_from_positions(sx, sy)
        visible = (coverage(sx, sy) >= COVER_FULL) & torch.isfinite(motion).all(dim=1, keepdim=True)
        if previous_next_motion is not None:
            f = F.grid_sample(previous_next_motion.float(), grid, mode="bilinear", padding_mode="zeros",
                              align_corners=False)
            m = torch.nan_to_num(motion, nan=0.0, posinf=0.0, neginf=0.0)
            lhs = ((m - f) ** 2).sum(dim=1, keepdim=True)
            rhs = FB_ALPHA * ((m * m).sum(dim=1, keepdim=True) + (f * f).sum(dim=1, keepdim=True)) + FB_BETA
            return Alignment(grid, visible & (lhs <= rhs), "forward-backward")
        if previous_guide is not None and guide is not None:
            warped = F.grid_sample(previous_guide.float(), grid, mode="bilinear", padding_mode="zeros",
                                   align_corners=False)
            return Alignment(grid, visible & (guide_disagreement(warped, guide) <= GATE_THRESHOLD), "guide")
        return Alignment(grid, visible, "in-frame")


@dataclass
class WarpError:
    """A sequence's warp error: ``per_frame`` ``[T]`` (×1e3, NaN on the first frame, at cuts and where
    no pixel is kept), ``kept`` ``[T]`` (share of pixels kept, NaN where undefined), the test used."""

    per_frame: list[float]
    kept: list[float]
    mask: str

    @property
    def mean(self) -> float:
        """Mean over the frames where it is defined (:func:`defined_mean`)."""
        return defined_mean(self.per_frame)

    @property
    def mean_kept(self) -> float:
        return defined_mean(self.kept)


def defined_mean(values: Sequence[float]) -> float:
    """Mean of the non-NaN values; a ValueError when there are none (a sequence of one frame, or
    one where no pixel is ever visible in two frames): the measure has no value then, never NaN."""
    vals = [float(v) for v in values if v is not None and not math.isnan(v)]
    if not vals:
        raise ValueError("warp error: no frame has a previous frame with visible pixels (needs 2+ frames "
                         "without a cut between them)")
    return sum(vals) / len(vals)


@dataclass
class FlickerMeter:
    """The warp error of named streams of the same frames, frame by frame.

    ``names``: the streams (e.g. ``["input", "output"]``). Each :meth:`update` gets frame t of every
    stream (linear HDR ``[1, 3, H, W]``) with frame t's motion ``[1, 2, H, W]``, optional guide
    ``[1, 7, H, W]`` and forward motion ``[1, 2, H, W]``, and ``reset`` (first frame, cut).
    """

    names: Sequence[str]
    values: dict[str, list[float]] = field(default_factory=dict)
    kept: dict[str, list[float]] = field(default_factory=dict)
    masks: set = field(default_factory=set)

    def __post_init__(self):
        self.names = list(self.names)
        self.values = {n: [] for n in self.names}
        self.kept = {n: [] for n in self.names}
        self._previous: dict[str, torch.Tensor] = {}
        self._guide: torch.Tensor | None = None
        self._next_motion: torch.Tensor | None = None

    def update(self, frames: Mapping[str, torch.Tensor], motion: torch.Tensor | None, reset: bool,
               guide: torch.Tensor | None = None, next_motion: torch.Tensor | None = None) -> dict[str, float]:
        """Add frame t of every stream; returns ``{name: warp error of frame t}`` (NaN at a reset).
        ``motion`` may be None at a reset only."""
        missing = [n for n in self.names if n not in frames]
        if missing:
            raise ValueError(f"flicker: no frame for stream(s) {missing}")
        current = {n: tonemap(frames[n]) for n in self.names}
        out = {}
        if reset or not self._previous:
            for n in self.names:
                self.values[n].append(float("nan"))
                self.kept[n].append(float("nan"))
                out[n] = float("nan")
        else:
            if motion is None:
                raise ValueError("flicker: frame t needs its motion (only a first frame or a cut may lack it)")
            alignment = align(motion, self._guide, guide, self._next_motion)
            self.masks.add(alignment.mask)
            for n in self.names:
                error, kept = alignment.error(self._previous[n], current[n])
                self.values[n].append(float(error[0]))
                self.kept[n].append(float(kept[0]))
                out[n] = float(error[0])
        self._previous, self._guide, self._next_motion = current, guide, next_motion
        return out

    def result(self, name: str) -> WarpError:
        return WarpError(list(self.values[name]), list(self.kept[name]), self.mask)

    @property
    def mask(self) -> str:
        """The visibility test used (the weakest when frames differed), or ``"none"`` before frame 2."""
        used = [m for m in MASKS if m in self.masks]
        return used[-1] if used else "none"


def warp_error(frames: torch.Tensor, motion: torch.Tensor, guide: torch.Tensor | None = None,
               next_motion: torch.Tensor | None = None, reset: Sequence[bool] | torch.Tensor | None = None
               ) -> WarpError:
    """The warp error of one sequence in memory.

    frames: ``[T, 3, H, W]`` linear HDR in order; motion: ``[T, 2, H, W]`` backward motion of each
    frame; guide: ``[T, 7, H, W]`` or None; next_motion: ``[T, 2, H, W]`` forward motion or None;
    reset: bool ``[T]`` (True at cuts; frame 0 always resets). Returns :class:`WarpError` (``[T]`` lists).
    """
    if frames.ndim != 4 or frames.shape[1] != 3 or motion.shape != (frames.shape[0], 2, *frames.shape[2:]):
        raise ValueError(f"warp error: expected frames [T, 3, H, W] and motion [T, 2, H, W], got "
                         f"{tuple(frames.shape)} and {tuple(motion.shape)}")
    meter = FlickerMeter(["x"])
    for t in range(frames.shape[0]):
        cut = t == 0 or (reset is not None and bool(reset[t]))
        meter.update({"x": frames[t:t + 1]}, motion[t:t + 1], cut,
                     None if guide is None else guide[t:t + 1],
                     None if next_motion is None else next_motion[t:t + 1])
    return meter.result("x")


# ----------------------------------------------------------------------------- reading a layout's files


def frame_guide(arrays: Mapping[str, object]) -> torch.Tensor | None:
    """The guide features ``[1, 7, H, W]`` of a frame's buffers (``{buffer: [1, C, H, W]}`` tensors
    or ``[H, W, C]`` arrays), or None when albedo, normal or depth is missing."""
    if not all(b in arrays for b in ("albedo", "normal", "depth")):
        return None
    return guide_features({b: _tensor(arrays[b]) for b in ("albedo", "normal", "depth")})


def _tensor(x) -> torch.Tensor:
    if isinstance(x, torch.Tensor):
        return x.float()
    return torch.from_numpy(np.ascontiguousarray(np.asarray(x, dtype=np.float32).transpose(2, 0, 1)))[None]


def read_motion(layout, source, index: int, arrays: Mapping[str, object] | None = None) -> dict:
    """What the flicker measure needs of frame ``index`` of ``source``: ``{"motion": [1, 2, H, W],
    "guide": [1, 7, H, W] or None, "next_motion": [1, 2, H, W] or None}``.

    ``arrays``: buffers already read for the frame (``{buffer: [1, C, H, W]}`` or ``[H, W, C]``),
    so nothing is decoded twice; what is missing is read. A sequence without a ``motion`` buffer is
    an ExrError naming its first file; ``next_motion`` is read where the layout has that optional
    buffer (Blender's ``Vector`` (Z, W)) and the file holds it.
    """
    arrays = dict(arrays or {})
    if "motion" not in source.buffers:
        path = layout.file_for(source, 0, "color")
        raise ExrError(path, "no motion pass (the flicker measure needs the renderer's motion vectors: "
                             "Blender's Vector pass or the native motion.X/Y)")
    wanted = [b for b in ("motion", "albedo", "normal", "depth") if b not in arrays and b in source.buffers]
    if wanted:
        read, _ = layout.read_frame(source, index, wanted)
        arrays.update(read)
    next_motion = None
    if "motion_next" in getattr(layout, "specs", {}):
        path = layout.file_for(source, index, "motion_next")
        from denoiser.data import exr

        if layout.resolve(path, "motion_next", exr.list_channels(path)) is not None:
            next_motion = _tensor(layout.read_file(path, ["motion_next"])[0]["motion_next"])
    return {"motion": _tensor(arrays["motion"]), "guide": frame_guide(arrays), "next_motion": next_motion}


# ----------------------------------------------------------------------------- agreement with tPSNR


def ordering_agreement(rows: Sequence[Mapping], methods: Sequence[str], resamples: int = 2000, seed: int = 0,
                       confidence: float = 0.95) -> dict:
    """Does the warp error order methods as tPSNR does? From ``denoiser-eval``'s per-sequence rows
    (``metrics.csv``: ``method``, ``sequence``, ``warp``, ``tpsnr``; ``sequence=mean`` rows skipped).

    Per sequence holding every one of ``methods`` with both values: the methods' order by warp
    error (ascending) against their order by tPSNR (descending); ``agreement`` is the share of
    those sequences whose two orders are the same. ``spearman`` is the rank correlation over all
    (method, sequence) pairs between ``-warp`` and ``tpsnr`` (so +1 is full agreement) with its
    percentile bootstrap interval over sequences (``resamples`` draws, ``seed``). Returns
    ``{"sequences", "agreement", "spearman", "lo", "hi", "per_sequence": {seq: bool}}``.
    """
    table: dict[str, dict[str, tuple[float, float]]] = {}
    for r in rows:
        if str(r["sequence"]) == "mean" or str(r["method"]) not in methods:
            continue
        w, t = _cell(r.get("warp")), _cell(r.get("tpsnr"))
        if w is not None and t is not None:
            table.setdefault(str(r["sequence"]), {})[str(r["method"])] = (w, t)
    seqs = [s for s, per in table.items() if all(m in per for m in methods)]
    if not seqs:
        raise ValueError(f"ordering agreement: no sequence has warp and tpsnr for every one of {list(methods)}")
    same = {}
    for s in seqs:
        by_warp = sorted(methods, key=lambda m: table[s][m][0])
        by_tpsnr = sorted(methods, key=lambda m: -table[s][m][1])
        same[s] = by_warp == by_tpsnr

    def rho(chosen) -> float:
        x = [-table[s][m][0] for s in chosen for m in methods]
        y = [table[s][m][1] for s in chosen for m in methods]
        return _spearman(x, y)

    rng = np.random.default_rng(seed)
    draws = [rho([seqs[i] for i in rng.integers(0, len(seqs), len(seqs))]) for _ in range(resamples)]
    draws = [d for d in draws if not math.isnan(d)]
    alpha = (1.0 - confidence) / 2.0
    lo, hi = (float(np.quantile(draws, alpha)), float(np.quantile(draws, 1.0 - alpha))) if draws else (math.nan,) * 2
    return {"sequences": len(seqs), "agreement": sum(same.values()) / len(seqs), "spearman": rho(seqs),
            "lo": lo, "hi": hi, "per_sequence": same}


def _cell(value) -> float | None:
    if value in (None, ""):
        return None
    value = float(value)
    return None if math.isnan(value) else value


def _ranks(x: Sequence[float]) -> np.ndarray:
    """Average ranks (ties share their mean rank), 1-based."""
    x = np.asarray(x, dtype=np.float64)
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(1, len(x) + 1)
    for v in np.unique(x):
        tied = x == v
        ranks[tied] = ranks[tied].mean()
    return ranks


def _spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation (Pearson's of the average ranks); NaN when a side is constant."""
    rx, ry = _ranks(x), _ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denom = math.sqrt(float((rx * rx).sum() * (ry * ry).sum()))
    return float((rx * ry).sum() / denom) if denom > 0 else math.nan


# ----------------------------------------------------------------------------- table, plot, record


def summary_rows(results: Mapping[str, WarpError]) -> list[dict]:
    """One row per stream: ``name``, ``mean`` (×1e3), ``kept`` (mean share of pixels), ``frames``
    measured, ``mask``; a stream without a defined value is a ValueError naming it."""
    rows = []
    for name, r in results.items():
        try:
            mean = r.mean
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
        rows.append({"name": name, "mean": mean, "kept": r.mean_kept,
                     "frames": sum(not math.isnan(v) for v in r.per_frame), "mask": r.mask})
    return rows


#: the columns of :func:`summary_table`: format and header
TABLE_FORMATS = {"mean": ".3f", "kept": ".1%"}
TABLE_HEADERS = {"name": "frames of", "mean": "warp err ×1e3 ↓", "kept": "pixels kept", "frames": "frames measured",
                 "mask": "visibility test"}


def summary_table(results: Mapping[str, WarpError], align: bool = True) -> str:
    """Markdown table of :func:`summary_rows` (one row per stream, the mean warp error first)."""
    from denoiser.tables import markdown_table

    return markdown_table(summary_rows(results), ["name", "mean", "kept", "frames", "mask"], TABLE_FORMATS,
                          TABLE_HEADERS, align=align)


def plot_flicker(path, results: Mapping[str, WarpError], title: str, frame_numbers: Sequence[int] | None = None):
    """PNG of the warp error over frames, one line per stream (frames counted from 1, or
    ``frame_numbers``), its mean in the legend; written atomically. Returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from denoiser.atomic import atomic_save_figure

    fig, ax = plt.subplots(figsize=(8, 4), dpi=120)
    for name, r in results.items():
        xs = list(frame_numbers) if frame_numbers is not None else list(range(1, len(r.per_frame) + 1))
        ax.plot(xs, r.per_frame, "o-", ms=3, lw=1.5, label=f"{name} (mean {r.mean:.3f})")
    ax.set_xlabel("frame")
    ax.set_ylabel("warp error ×1e3 (lower is steadier)")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return atomic_save_figure(fig, path)


def json_values(values: Sequence[float]) -> list[float | None]:
    """Per-frame values for JSON: NaN (first frame, cuts) as null."""
    return [None if math.isnan(v) else float(v) for v in values]


# ----------------------------------------------------------------------------- denoiser-denoise's report


def denoise_report(meter: FlickerMeter | None, frames: Sequence[int], info: Mapping, out_dir) -> dict:
    """``denoiser-denoise``'s record of a run, written into ``out_dir``: ``report.json``, ``report.md``
    and (with a meter) ``flicker.png``, the warp error of the input and the output over frames.

    meter: a :class:`FlickerMeter` of the streams ``input`` and ``output`` (None: the frames have no
    motion, no flicker measured); frames: the frame numbers (1-based) measured, one per meter entry;
    info: what the run was (``input``, ``frames``, ``seconds``, ``backend``, ``precision``, ``threads``,
    ``size``, ``measure_seconds``: the time the measure took). Returns the JSON record.
    """
    from pathlib import Path

    from denoiser.atomic import atomic_write_text

    out_dir = Path(out_dir)
    seconds = float(info["seconds"])
    seconds = max(seconds, 1e-9)
    record = {**info, "frames_per_second": len(frames) / seconds,
              "measure_share": float(info.get("measure_seconds", 0.0)) / seconds, "frame_numbers": list(frames)}
    lines = [f"# denoiser-denoise report: {info['input']}", "",
             f"{len(frames)} frame(s) of {info['size'][1]}x{info['size'][0]} in {seconds:.1f} s "
             f"({record['frames_per_second']:.2f} frames/s), backend {info['backend']}, precision {info['precision']}, "
             f"{info['threads']} thread(s).", ""]
    if meter is None:
        record["flicker"] = None
        lines.append("No flicker measured: the input frames have no motion pass.")
    else:
        results = {n: meter.result(n) for n in ("input", "output")}
        defined = any(not math.isnan(v) for v in results["output"].per_frame)
        record["flicker"] = {n: {"mean": r.mean if defined else None, "kept": r.mean_kept if defined else None,
                                 "per_frame": json_values(r.per_frame), "kept_per_frame": json_values(r.kept)}
                             for n, r in results.items()}
        record["flicker"]["mask"] = meter.mask
        if defined:
            plot_flicker(out_dir / "flicker.png", results, f"{info['input']}: warp error of the noisy input and "
                         "of the denoised output", frames)
            lines += ["## Flicker (warp error, no reference needed)", "",
                      summary_table(results, align=False).rstrip(), "",
                      f"Warp error (Lai et al. 2018; denoiser/metrics.py `warp`): per frame, the mean over the pixels "
                      f"visible in both frames (test: {meter.mask}) of the squared distance between the tonemapped "
                      "frame and the previous one warped along the motion vectors, ×1e3; lower is steadier. It also "
                      "counts real changes of shading (moving lights and highlights): compare the output with the "
                      "input and with other denoisers' frames of the same render (denoiser-flicker), not with 0. "
                      f"The measure took {record['measure_share']:.1%} of the run.", "",
                      "![flicker over frames](flicker.png)", "",
                      "| frame | input | output |", "|---:|---:|---:|"]
            lines += [f"| {f} | {_fmt(a)} | {_fmt(b)} |" for f, a, b in
                      zip(frames, results["input"].per_frame, results["output"].per_frame)]
        else:
            lines.append("No flicker measured: no frame has a previous one (a single frame, or cuts everywhere).")
    atomic_write_text(out_dir / "report.json", json.dumps(record, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out_dir / "report.md", "\n".join(lines) + "\n")
    return record


def _fmt(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.3f}"
