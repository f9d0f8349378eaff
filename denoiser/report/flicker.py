"""Flicker without a reference: the warping error (``warp`` of :mod:`denoiser.metrics`) of a stream of frames.

The formula and how to read it are said once, in :mod:`denoiser.metrics` (``warp``,
:func:`~denoiser.metrics.masked_warp_error`). This module aligns frame t-1 to frame t with
frame t's backward motion, as the network's warp does (:mod:`denoiser.nn.warp`: the sample
position ``p + motion(p)``, NaN motion read as 0 and clamped to ``MOTION_LIMIT`` frame sizes,
bilinear), and builds the visibility mask ``M_t``, the same for every stream of the same frames:

* *in frame*: the bilinear footprint of ``p + motion(p)`` lies wholly inside frame t-1 (what
  :func:`~denoiser.nn.warp.coverage` ``= 1`` says), and the motion is finite;
* *visible in both frames* (disocclusions dropped), one of two tests:

  - ``forward-backward`` where frame t-1's forward motion exists (Blender's ``Vector`` (Z, W),
    the layout's optional buffer ``motion_next``: position in t-1 minus position in t, the same
    sign as ``motion``): with ``f`` that motion warped to t, kept where
    ``|m - f|^2 <= FB_ALPHA (|m|^2 + |f|^2) + FB_BETA`` (Ruder et al. 2016, "Artistic style transfer
    for videos", the test Lai et al. use for their occlusion masks);
  - ``guide`` otherwise: the depth and normal terms of the networks' disocclusion gate
    (:func:`denoiser.nn.temporal.guide_disagreement`: log depth ratio of the depth features
    ``d / (d + m)``, ``1 - cos`` of the normals) between frame t-1's warped features and frame t's,
    kept where ``D <= GATE_THRESHOLD`` (where the gate of the shipped networks, ``reject_threshold``
    0.1, passes history whole). The gate's albedo term is left out (it reads a 3x3 box);
  - ``in-frame`` when the frames come with neither (no disocclusion test: said in every report).

``stride`` s: the measure is taken at the pixels ``(s/2 + i s, s/2 + j s)`` (every pixel for
s = 1): the mean over a regular subset of the kept pixels, the exact per-pixel value at each of
them (frame t-1's tonemapped values interpolated from its four neighbours), so it estimates the
full mean at 1/s² of the cost. ``denoiser-denoise`` uses a stride to keep its cost small; the
evaluation and ``denoiser-flicker`` every pixel.

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

from denoiser.errors import ExrError
from denoiser.metrics import masked_warp_error, tonemap
from denoiser.nn.inputs import DEPTH_FAR, depth_mean, normal_feature, sanitize
from denoiser.nn.temporal import guide_disagreement
from denoiser.nn.warp import MOTION_LIMIT

#: forward-backward test ``|m - f|^2 <= FB_ALPHA (|m|^2 + |f|^2) + FB_BETA`` (pixels^2; Ruder et al.)
FB_ALPHA, FB_BETA = 0.01, 0.5
#: largest disocclusion-gate disagreement ``D`` kept (the shipped networks' ``reject_threshold``)
GATE_THRESHOLD = 0.1
#: the visibility tests, in the order they are preferred
MASKS = ("forward-backward", "guide", "in-frame")
#: the buffers of the guide test (:func:`frame_aux`)
AUX = ("normal", "depth")


def sample_points(h: int, w: int, stride: int) -> torch.Tensor:
    """Flat indices ``[n]`` (``y * w + x``) of the pixels measured at ``stride``: ``(s//2 + i s, s//2 + j s)``."""
    if stride < 1:
        raise ValueError(f"flicker: stride must be >= 1, got {stride}")
    ys = torch.arange(stride // 2 if h > stride // 2 else 0, h, stride)
    xs = torch.arange(stride // 2 if w > stride // 2 else 0, w, stride)
    return (ys[:, None] * w + xs[None, :]).reshape(-1)


def _at(x, index: torch.Tensor) -> torch.Tensor:
    """``x`` at the flat pixel indices ``index`` (any shape) -> ``[C, *index.shape]`` float32; ``x`` a
    tensor ``[1, C, H, W]`` or an array ``[H, W, C]`` as a layout reads it (no copy of the whole frame)."""
    if isinstance(x, np.ndarray):
        c = x.shape[-1]
        flat = torch.from_numpy(np.ascontiguousarray(x).reshape(-1, c))
        return flat[index.reshape(-1)].float().T.reshape(c, *index.shape)
    flat = x.reshape(x.shape[1], -1)
    return flat[:, index.reshape(-1)].float().reshape(x.shape[1], *index.shape)


def _size(x) -> tuple[int, int]:
    """``(H, W)`` of a ``[1, C, H, W]`` tensor or an ``[H, W, C]`` array."""
    return tuple(x.shape[:2]) if isinstance(x, np.ndarray) else tuple(x.shape[-2:])


@dataclass
class Alignment:
    """Frame t-1 aligned to frame t at the measured pixels.

    points: ``[n]`` flat indices of the measured pixels of frame t; taps: ``[4, n]`` flat indices of
    their bilinear neighbours in frame t-1; weights: ``[4, n]``; visible: bool ``[n]`` (the mask);
    mask: which test built it (:data:`MASKS`).
    """

    points: torch.Tensor
    taps: torch.Tensor
    weights: torch.Tensor
    visible: torch.Tensor
    mask: str

    def warp(self, previous: torch.Tensor, transform=None) -> torch.Tensor:
        """``previous`` ``[1, C, H, W]`` (frame t-1) interpolated at ``p + motion(p)``, ``[C, n]``;
        ``transform`` (e.g. the tonemapper) applied to the four neighbours before interpolating."""
        values = _at(previous, self.taps)  # [C, 4, n]
        if transform is not None:
            values = transform(values)
        return (values * self.weights[None]).sum(dim=1)

    def error(self, previous: torch.Tensor, current: torch.Tensor) -> tuple[float, float]:
        """Warp error (×1e3) and share kept of linear frames ``[1, 3, H, W]`` at t-1 and t: the warped
        *tonemapped* frame t-1 against the tonemapped frame t (:func:`~denoiser.metrics.masked_warp_error`)."""
        cur = tonemap(_at(current, self.points))
        prev = self.warp(previous, tonemap)
        error, kept = masked_warp_error(cur[None, :, None], prev[None, :, None], self.visible.view(1, 1, 1, -1))
        return float(error[0]), float(kept[0])


def align(motion: torch.Tensor, previous_aux: Mapping | None = None, aux: Mapping | None = None,
          previous_next_motion: torch.Tensor | None = None, stride: int = 1) -> Alignment:
    """The :class:`Alignment` of frame t-1 to frame t (module docstring).

    motion: ``[1, 2, H, W]`` (or ``[H, W, 2]``) frame t's backward motion (pixels, x right, y down); previous_aux,
    aux: :func:`frame_aux` of frames t-1 and t (``normal [1, 3, H, W]``, ``depth [1, 1, H, W]``) or
    None; previous_next_motion: ``[1, 2, H, W]`` frame t-1's forward motion (``motion_next``) or
    None. The forward-backward test is used when it is given, else the guide test when both aux
    are, else only the in-frame test.
    """
    h, w = _size(motion)
    points = sample_points(h, w, stride)
    raw = _at(motion, points)  # [2, n]
    limit = MOTION_LIMIT * max(h, w)
    m = sanitize(raw).clamp(-limit, limit)  # as denoiser.nn.warp.sample_positions reads motion
    sx, sy = (points % w).float() + m[0], torch.div(points, w, rounding_mode="floor").float() + m[1]
    visible = (sx >= 0) & (sx <= w - 1) & (sy >= 0) & (sy <= h - 1) & torch.isfinite(raw).all(dim=0)
    x0, y0 = sx.floor().clamp(0, w - 1), sy.floor().clamp(0, h - 1)
    fx, fy = (sx - x0).clamp(0, 1), (sy - y0).clamp(0, 1)
    x1, y1 = (x0 + 1).clamp(max=w - 1), (y0 + 1).clamp(max=h - 1)
    x0, x1, y0, y1 = (v.long() for v in (x0, x1, y0, y1))
    taps = torch.stack([y0 * w + x0, y0 * w + x1, y1 * w + x0, y1 * w + x1])
    weights = torch.stack([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    alignment = Alignment(points, taps, weights, visible, "in-frame")
    if previous_next_motion is not None:
        f = alignment.warp(previous_next_motion, sanitize)
        lhs = ((m - f) ** 2).sum(dim=0)
        rhs = FB_ALPHA * ((m * m).sum(dim=0) + (f * f).sum(dim=0)) + FB_BETA
        alignment.visible, alignment.mask = visible & (lhs <= rhs), "forward-backward"
    elif previous_aux is not None and aux is not None:
        previous = (_features_at(previous_aux, taps, points) * weights[None]).sum(dim=1)  # warped, [7, n]
        current = _features_at(aux, points, points)
        d = guide_disagreement(previous[None, :, None], current[None, :, None])[0, 0, 0]
        alignment.visible, alignment.mask = visible & (d <= GATE_THRESHOLD), "guide"
    return alignment


def _features_at(aux: Mapping, index: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """The gate's guide features (:func:`denoiser.nn.inputs.guide_features`: albedo, normal, depth
    ``d / (d + m)``, ``m`` the mean hit depth of the frame's measured pixels ``points``) at the flat
    pixel indices ``index``, ``[7, *index.shape]``, the albedo channels zeros (its term is then 0)."""
    d = sanitize(_at(aux["depth"], index)).clamp(0, DEPTH_FAR)
    mean = depth_mean(sanitize(_at(aux["depth"], points)).clamp(0, DEPTH_FAR).view(1, 1, 1, -1))
    normal = normal_feature(sanitize(_at(aux["normal"], index)))
    return torch.cat([torch.zeros_like(normal), normal, d / (d + mean.reshape(()))], dim=0)


def frame_aux(arrays: Mapping[str, object]) -> dict | None:
    """What the guide test reads of a frame: ``{"normal", "depth"}`` as given (``[1, C, H, W]``
    tensors or ``[H, W, C]`` arrays, read at the measured pixels only), or None without them."""
    if not all(b in arrays for b in AUX):
        return None
    return {b: arrays[b] for b in AUX}


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

    ``names``: the streams (e.g. ``["input", "output"]``); ``stride``: measure every ``stride``-th
    pixel in each direction (module docstring). Each :meth:`update` gets frame t of every stream
    (linear HDR ``[1, 3, H, W]``) with frame t's motion ``[1, 2, H, W]``, optional :func:`frame_aux`
    and forward motion ``[1, 2, H, W]``, and ``reset`` (first frame, cut).
    """

    names: Sequence[str]
    stride: int = 1
    values: dict[str, list[float]] = field(default_factory=dict)
    kept: dict[str, list[float]] = field(default_factory=dict)
    masks: set = field(default_factory=set)

    def __post_init__(self):
        self.names = list(self.names)
        self.values = {n: [] for n in self.names}
        self.kept = {n: [] for n in self.names}
        self._previous: dict[str, torch.Tensor] = {}
        self._aux: dict | None = None
        self._next_motion: torch.Tensor | None = None

    @torch.no_grad()
    def update(self, frames: Mapping[str, torch.Tensor], motion: torch.Tensor | None, reset: bool,
               aux: Mapping | None = None, next_motion: torch.Tensor | None = None) -> dict[str, float]:
        """Add frame t of every stream; returns ``{name: warp error of frame t}`` (NaN at a reset).
        ``motion`` may be None at a reset only."""
        missing = [n for n in self.names if n not in frames]
        if missing:
            raise ValueError(f"flicker: no frame for stream(s) {missing}")
        out = {}
        if reset or not self._previous:
            for n in self.names:
                self.values[n].append(float("nan"))
                self.kept[n].append(float("nan"))
                out[n] = float("nan")
        else:
            if motion is None:
                raise ValueError("flicker: frame t needs its motion (only a first frame or a cut may lack it)")
            alignment = align(motion, self._aux, aux, self._next_motion, self.stride)
            self.masks.add(alignment.mask)
            for n in self.names:
                error, kept = alignment.error(self._previous[n], frames[n])
                self.values[n].append(error)
                self.kept[n].append(kept)
                out[n] = error
        self._previous = {n: frames[n] for n in self.names}
        self._aux, self._next_motion = aux, next_motion
        return out

    def result(self, name: str) -> WarpError:
        return WarpError(list(self.values[name]), list(self.kept[name]), self.mask)

    @property
    def mask(self) -> str:
        """The visibility test used (the weakest when frames differed), or ``"none"`` before frame 2."""
        used = [m for m in MASKS if m in self.masks]
        return used[-1] if used else "none"


def warp_error(frames: torch.Tensor, motion: torch.Tensor, aux: Mapping | None = None,
               next_motion: torch.Tensor | None = None, reset: Sequence[bool] | torch.Tensor | None = None,
               stride: int = 1) -> WarpError:
    """The warp error of one sequence in memory.

    frames: ``[T, 3, H, W]`` linear HDR in order; motion: ``[T, 2, H, W]`` backward motion of each
    frame; aux: ``{"normal": [T, 3, H, W], "depth": [T, 1, H, W]}`` or None; next_motion:
    ``[T, 2, H, W]`` forward motion or None; reset: bool ``[T]`` (True at cuts; frame 0 always
    resets). Returns :class:`WarpError` (``[T]`` lists).
    """
    if frames.ndim != 4 or frames.shape[1] != 3 or motion.shape != (frames.shape[0], 2, *frames.shape[2:]):
        raise ValueError(f"warp error: expected frames [T, 3, H, W] and motion [T, 2, H, W], got "
                         f"{tuple(frames.shape)} and {tuple(motion.shape)}")
    meter = FlickerMeter(["x"], stride)
    for t in range(frames.shape[0]):
        cut = t == 0 or (reset is not None and bool(reset[t]))
        meter.update({"x": frames[t:t + 1]}, motion[t:t + 1], cut,
                     None if aux is None else frame_aux({k: aux[k][t:t + 1] for k in AUX}),
                     None if next_motion is None else next_motion[t:t + 1])
    return meter.result("x")


# ----------------------------------------------------------------------------- reading a layout's files


def flicker_buffers(layout, source) -> list[str]:
    """The buffers the flicker measure reads of ``source``'s frames: ``motion`` and, where the layout
    has the optional ``motion_next`` and the first frame's file holds it, that (the forward-backward
    test), else ``normal`` and ``depth`` where present (the guide test). A sequence without a
    ``motion`` buffer is an ExrError naming its first file."""
    from denoiser.data import exr

    if "motion" not in source.buffers:
        path = layout.file_for(source, 0, "color")
        raise ExrError(path, "no motion pass (the flicker measure needs the renderer's motion vectors: "
                             "Blender's Vector pass or the native motion.X/Y)")
    if "motion_next" in getattr(layout, "specs", {}):
        path = layout.file_for(source, 0, "motion_next")
        if layout.resolve(path, "motion_next", exr.list_channels(path)) is not None:
            return ["motion", "motion_next"]
    return ["motion", *(b for b in AUX if b in source.buffers)]


def read_motion(layout, source, index: int, arrays: Mapping[str, object] | None = None,
                buffers: Sequence[str] | None = None) -> dict:
    """What the flicker measure needs of frame ``index`` of ``source``: ``{"motion", "aux": frame_aux
    or None, "next_motion" or None}``, each as given or read (``[1, C, H, W]`` or ``[H, W, C]``).

    ``arrays``: buffers already read for the frame (``{buffer: [1, C, H, W]}`` or ``[H, W, C]``),
    so nothing is decoded twice; what is missing of ``buffers`` (default :func:`flicker_buffers`)
    is read.
    """
    arrays = dict(arrays or {})
    buffers = flicker_buffers(layout, source) if buffers is None else list(buffers)
    wanted = [b for b in buffers if b not in arrays]
    if wanted:
        read, _ = layout.read_frame(source, index, wanted)
        arrays.update(read)
    forward = "motion_next" in buffers
    return {"motion": arrays["motion"], "aux": None if forward else frame_aux(arrays),
            "next_motion": arrays["motion_next"] if forward else None}


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
              "measure_share": float(info.get("measure_seconds", 0.0)) / seconds, "frame_numbers": list(frames),
              "stride": meter.stride if meter is not None else None}
    lines = [f"# denoiser-denoise report: {info['input']}", "",
             (f"{len(frames)} frame(s) of {info['size'][1]}x{info['size'][0]} in {seconds:.1f} s "
              f"({record['frames_per_second']:.2f} frames/s), backend {info['backend']}, precision "
              f"{info['precision']}, {info['threads']} thread(s)."), ""]
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
                      (f"Warp error (Lai et al. 2018; denoiser/metrics.py `warp`): per frame, the mean over the "
                       f"pixels visible in both frames (test: {meter.mask}; every {_nth(meter.stride)} pixel in x and "
                       "y) of the squared distance between the tonemapped frame and the previous one warped along "
                       "the motion vectors, ×1e3; lower is steadier. It also counts real changes of shading (moving "
                       "lights and highlights): compare the output with the input and with other denoisers' frames "
                       "of the same render (denoiser-flicker), not with 0. "
                       f"The measure took {record['measure_share']:.1%} of the run."), "",
                      "![flicker over frames](flicker.png)", "",
                      "| frame | input | output |", "|---:|---:|---:|"]
            lines += [f"| {f} | {_fmt(a)} | {_fmt(b)} |" for f, a, b in
                      zip(frames, results["input"].per_frame, results["output"].per_frame)]
        else:
            lines.append("No flicker measured: no frame has a previous one (a single frame, or cuts everywhere).")
    atomic_write_text(out_dir / "report.json", json.dumps(record, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out_dir / "report.md", "\n".join(lines) + "\n")
    return record


def _nth(stride: int) -> str:
    return "" if stride == 1 else {2: "2nd", 3: "3rd"}.get(stride, f"{stride}th")


def _fmt(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.3f}"
