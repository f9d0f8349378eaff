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
What the measurements say (the table, the plot, ``denoiser-denoise``'s report, the check that the
measure orders methods as tPSNR does) is :mod:`denoiser.report.flicker_report`.
"""

from __future__ import annotations

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
