"""Image-quality metrics shared by training (validation), evaluation and the benchmark.

Every function takes linear HDR radiance, float tensors shaped ``[N, 3, H, W]`` where ``N`` is
a batch ``B`` or a sequence of ``T`` frames, and returns one value per frame, ``[N]``.

Tonemapping (the one tonemapper used everywhere, docs/design.md §3.4)
    ``tonemap(x) = srgb_oetf(clamp(aces(exposure * max(x, 0)), 0, 1))`` with the ACES filmic
    fit of Narkowicz (2015), ``aces(x) = x (2.51 x + 0.03) / (x (2.43 x + 0.59) + 0.14)``,
    exposure 1, and the sRGB OETF (``12.92 x`` below 0.0031308, else
    ``1.055 x^(1/2.4) - 0.055``). Results are display values in [0, 1].

Metrics
    * ``psnr``: ``10 log10(1 / max(MSE, 1e-10))`` on tonemapped frames (so at most 100 dB),
      computed by ``torchmetrics.functional.peak_signal_noise_ratio`` with ``data_range=1``.
    * ``ssim``: ``torchmetrics.functional.structural_similarity_index_measure`` on tonemapped
      frames (Gaussian window 11, sigma 1.5, ``data_range=1``), averaged over pixels and channels.
    * ``relmse``: ``mean((x - y)^2 / (y^2 + 0.01))`` on linear HDR (``y`` the reference).
    * ``smape``: ``mean(|x - y| / (|x| + |y| + 0.01))`` on linear HDR (the same form as the
      training loss, docs/design.md §3.3).
    * ``tpsnr``: temporal stability. With ``d_x(t) = tonemap(x_t) - tonemap(x_{t-1})`` and the
      same for the reference, ``tpsnr(t) = 10 log10(1 / max(mean((d_x - d_y)^2), 1e-10))``:
      the PSNR (peak 1, as ``psnr``) of the output's frame-to-frame change against the
      reference's. It is undefined (NaN) on the first frame and at camera cuts.
    * ``warp``: temporal stability without a reference, the warping error of Lai et al. 2018
      ("Learning Blind Video Temporal Consistency", ``evaluate_WarpError.py``). With ``o_t`` the
      tonemapped frame t, ``w_t = warp(o_{t-1})`` frame t-1 warped to t with frame t's backward
      motion (the convention of :mod:`denoiser.nn.warp`: the surface at pixel ``p`` of frame t was
      at ``p + motion(p)`` in t-1; bilinear) and ``M_t`` the visibility mask (1 where the pixel's
      surface is seen in both frames), ``warp(t) = sum_p M_t(p) sum_c (o_t - w_t)^2 / sum_p M_t(p)``:
      the squared colour distance (summed over the 3 channels, as Lai et al.) averaged over the
      kept pixels; lower is steadier, 0 for a perfectly stable sequence. NaN on the first frame, at
      camera cuts and when no pixel is kept. The mask (:mod:`denoiser.report.flicker`, which also
      gives the share of pixels kept) drops pixels whose bilinear footprint leaves the previous
      frame, non-finite values, and disocclusions: by the forward-backward check of Ruder et al.
      2016 where the layout has motion in both directions (Blender's ``Vector`` pass), else by the
      depth/normal/albedo disagreement of the networks' disocclusion gate (:mod:`denoiser.nn.temporal`).
      Limits: it counts every change of the visible colour, the flicker of noise and of a
      denoiser but also real shading changes (moving lights, specular highlights and shadows that
      move over a surface, animated textures); and a blurry output scores well. Read it beside
      ``warp_ref``, the same measure on the reference frames, the floor that real shading
      changes alone give; where no reference exists, compare methods on the same frames only.
    * ``warp_ref``: ``warp`` of the reference frames (computed beside ``warp``).
    * ``flip``: HDR-FLIP (NVIDIA ``flip-evaluator``, ACES tonemapper, 67 pixels per degree),
      mean of the per-pixel error map, lower is better. The exposure range (start, stop,
      count) is fixed per sequence from its reference frames by :func:`flip_exposure` (FLIP's
      own rule applied to the luminance of all the sequence's reference pixels), so every
      frame and every method of a sequence is judged under the same exposures.

Aggregation (:class:`MetricAccumulator`): per-frame values; the first ``warmup`` frames after
a reset (start of a sequence or window, camera cut) are excluded where history matters (a
recurrent network has no history yet); a sequence's value is the mean over its kept frames;
the overall value is the mean over sequences (each sequence weighs the same, whatever its
length). NaN values (tPSNR on a first frame) are skipped in means. A frame-subset column
(:data:`FRAME_SUBSETS`: ``psnr_all`` over every frame, ``psnr_f2`` over frames 2+ of each
sequence, 1-based) is the mean
over every frame from a position on, warm-up or not. Under DDP each process sends
its per-sequence sums and counts (:meth:`MetricAccumulator.sequence_sums`) and every process
averages them the same way (:func:`combine_sequence_sums`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure


@dataclass(frozen=True)
class Metric:
    """How a metric is shown and compared, said once for every table (evaluation, summaries).

    ``label``: its name in a table header (with the unit); ``digits``: decimals shown;
    ``lower_is_better``: its direction (the header gets ↓, else ↑). A *frame subset* column
    (``of`` set) averages metric ``of`` over the frames of each sequence whose 0-based index is
    at least ``first_frame``, every such frame counted (the warm-up rule does not apply: the
    column is defined by frame position alone).
    """

    label: str
    digits: int
    lower_is_better: bool = False
    of: str | None = None
    first_frame: int = 0

    @property
    def header(self) -> str:
        """``"PSNR dB ↑"``: the label and the direction."""
        return f"{self.label} {'↓' if self.lower_is_better else '↑'}"

    @property
    def fmt(self) -> str:
        """The format spec of a value (``".2f"``)."""
        return f".{self.digits}f"


#: Metrics computed per frame, in table order.
METRICS: dict[str, Metric] = {
    "psnr": Metric("PSNR dB", 2),
    "ssim": Metric("SSIM", 4),
    "tpsnr": Metric("tPSNR dB", 2),
    "warp": Metric("warp err ×1e3", 3, lower_is_better=True),
    "warp_ref": Metric("warp err of reference ×1e3", 3, lower_is_better=True),
    "flip": Metric("FLIP", 4, lower_is_better=True),
    "relmse": Metric("relMSE", 4, lower_is_better=True),
    "smape": Metric("SMAPE", 4, lower_is_better=True),
}

#: Metrics whose per-frame values the caller computes (they need motion, which
#: :meth:`MetricAccumulator.update` does not see) and passes as ``values``: ``warp`` and
#: ``warp_ref`` (:mod:`denoiser.report.flicker`). Stored in units of 1e-3 (the label's ×1e3).
CALLER_METRICS = ("warp", "warp_ref")
#: ``warp`` is kept and shown in units of 1e-3 of the squared distance (values of a few units)
WARP_UNIT = 1e-3


def frame_subset(of: str, first_frame: int) -> Metric:
    """The column of metric ``of`` over frames ``first_frame + 1``, ... of each sequence (1-based
    in its label: ``frame_subset("psnr", 1)`` is "PSNR dB frames 2+")."""
    base = METRICS[of]
    frames = "all frames" if first_frame == 0 else f"frames {first_frame + 1}+"
    return Metric(f"{base.label} {frames}", base.digits, base.lower_is_better, of, first_frame)


#: Frame-subset columns (:meth:`MetricAccumulator.per_sequence` adds one wherever its metric is
#: computed): ``psnr_all`` over every frame (warm-up included), ``psnr_f2`` the quality once the
#: recurrent history is in use (frame 1 skipped), where temporal methods fail first.
FRAME_SUBSETS: dict[str, Metric] = {"psnr_all": frame_subset("psnr", 0), "psnr_f2": frame_subset("psnr", 1)}
#: Every column a table may show: the metrics, then the frame subsets.
COLUMNS: dict[str, Metric] = {**METRICS, **FRAME_SUBSETS}

#: Minimum MSE in PSNR-type metrics (caps them at 100 dB for identical frames).
MIN_MSE = 1e-10
#: Epsilon in relMSE's denominator ``y^2 + RELMSE_EPS``.
RELMSE_EPS = 0.01
#: Epsilon in SMAPE's denominator ``|x| + |y| + SMAPE_EPS``.
SMAPE_EPS = 0.01

# ACES filmic fit (Narkowicz 2015) coefficients.
_ACES_A, _ACES_B, _ACES_C, _ACES_D, _ACES_E = 2.51, 0.03, 2.43, 0.59, 0.14


# ----------------------------------------------------------------------------- tonemapping


def aces_fit(x: torch.Tensor) -> torch.Tensor:
    """ACES filmic curve (Narkowicz fit) of non-negative linear values, clamped to [0, 1]."""
    y = (x * (_ACES_A * x + _ACES_B)) / (x * (_ACES_C * x + _ACES_D) + _ACES_E)
    return y.clamp(0.0, 1.0)


def srgb_oetf(x: torch.Tensor) -> torch.Tensor:
    """sRGB opto-electronic transfer function of linear values in [0, 1]."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0.0031308).pow(1.0 / 2.4) - 0.055)


def tonemap(x: torch.Tensor, exposure: float = 1.0) -> torch.Tensor:
    """Display values in [0, 1] of linear HDR radiance: ACES fit, then the sRGB OETF.

    ``x``: ``[..., 3, H, W]`` (any shape) linear HDR; negative values count as 0.
    Computed in float32 whatever the input dtype.
    """
    x = x.float().clamp_min(0.0) * exposure
    return srgb_oetf(aces_fit(x))


# ----------------------------------------------------------------------------- checks


def _check_pair(output: torch.Tensor, reference: torch.Tensor, name: str) -> None:
    if output.shape != reference.shape:
        raise ValueError(f"{name}: output {tuple(output.shape)} and reference {tuple(reference.shape)} differ")
    if output.ndim != 4 or output.shape[1] != 3:
        raise ValueError(f"{name}: expected [N, 3, H, W] frames, got {tuple(output.shape)}")


# ----------------------------------------------------------------------------- per-frame metrics


def mse_to_psnr(mse: torch.Tensor) -> torch.Tensor:
    """``10 log10(1 / max(mse, 1e-10))`` (peak 1)."""
    return 10.0 * torch.log10(1.0 / mse.clamp_min(MIN_MSE))


def psnr(output: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """PSNR in dB of tonemapped frames. ``output, reference``: ``[N, 3, H, W]`` linear HDR -> ``[N]``."""
    _check_pair(output, reference, "psnr")
    a, b = tonemap(output), tonemap(reference)
    mse = ((a - b) ** 2).mean(dim=(1, 2, 3))
    if bool((mse > MIN_MSE).all()):
        # torchmetrics' reference implementation (identical value; kept for traceability)
        return peak_signal_noise_ratio(a, b, data_range=1.0, reduction="none", dim=(1, 2, 3))
    return mse_to_psnr(mse)


def ssim(output: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """SSIM of tonemapped frames. ``output, reference``: ``[N, 3, H, W]`` linear HDR -> ``[N]``."""
    _check_pair(output, reference, "ssim")
    return structural_similarity_index_measure(
        tonemap(output), tonemap(reference), data_range=1.0, reduction="none")


def relmse(output: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Relative MSE ``mean((x-y)^2 / (y^2 + 0.01))`` on linear HDR. ``[N, 3, H, W]`` -> ``[N]``."""
    _check_pair(output, reference, "relmse")
    x, y = output.float(), reference.float()
    return ((x - y) ** 2 / (y * y + RELMSE_EPS)).mean(dim=(1, 2, 3))


def smape(output: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """SMAPE ``mean(|x-y| / (|x|+|y|+0.01))`` on linear HDR. ``[N, 3, H, W]`` -> ``[N]``."""
    _check_pair(output, reference, "smape")
    x, y = output.float(), reference.float()
    return ((x - y).abs() / (x.abs() + y.abs() + SMAPE_EPS)).mean(dim=(1, 2, 3))


def tpsnr(output: torch.Tensor, reference: torch.Tensor, reset: torch.Tensor | None = None) -> torch.Tensor:
    """Temporal PSNR of consecutive frames of one sequence (see module docstring).

    ``output, reference``: ``[T, 3, H, W]`` linear HDR, consecutive frames in order;
    ``reset``: optional bool ``[T]`` (True at camera cuts). Returns ``[T]``; entry 0 and the
    entries where ``reset`` is True are NaN (no previous frame to difference against).
    """
    _check_pair(output, reference, "tpsnr")
    a, b = tonemap(output), tonemap(reference)
    out = torch.full((a.shape[0],), float("nan"), device=a.device)
    if a.shape[0] > 1:
        out[1:] = tpsnr_pair(a[:-1], a[1:], b[:-1], b[1:])
    if reset is not None:
        out[reset.to(out.device).bool()] = float("nan")
    return out


def tpsnr_pair(prev_out_tm, out_tm, prev_ref_tm, ref_tm) -> torch.Tensor:
    """tPSNR from *tonemapped* frames ``[N, 3, H, W]`` at t-1 and t -> ``[N]``."""
    d = (out_tm - prev_out_tm) - (ref_tm - prev_ref_tm)
    return mse_to_psnr((d * d).mean(dim=(1, 2, 3)))


def masked_warp_error(current_tm: torch.Tensor, warped_tm: torch.Tensor, visible: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """The warping error of ``warp`` (module docstring) from tonemapped frames already aligned.

    current_tm: ``[N, 3, H, W]`` tonemapped frame t; warped_tm: ``[N, 3, H, W]`` tonemapped frame
    t-1 warped to t; visible: bool ``[N, 1, H, W]`` (the mask ``M_t``). Pixels where either frame
    is not finite are dropped whatever ``visible`` says. Returns ``(error [N], kept [N])``: the
    masked mean of the squared distance summed over channels, in units of :data:`WARP_UNIT`
    (NaN where no pixel is kept, never from a non-finite pixel), and the share of pixels kept.
    """
    if current_tm.shape != warped_tm.shape or current_tm.ndim != 4 or current_tm.shape[1] != 3:
        raise ValueError(f"warp error: expected two [N, 3, H, W] frames, got {tuple(current_tm.shape)} and "
                         f"{tuple(warped_tm.shape)}")
    d = current_tm.float() - warped_tm.float()
    dist = (d * d).sum(dim=1, keepdim=True)
    mask = visible.bool() & torch.isfinite(dist)
    count = mask.sum(dim=(1, 2, 3)).double()
    total = torch.where(mask, dist, 0.0).sum(dim=(1, 2, 3), dtype=torch.float64)
    error = torch.where(count > 0, total / count.clamp_min(1.0), float("nan")) / WARP_UNIT
    return error.float(), (count / float(mask[0].numel())).float()


# ----------------------------------------------------------------------------- HDR-FLIP

#: FLIP's ACES coefficients (numerator a, b, c; denominator d, e, f) and the target value 0.85
#: that defines the exposure range (Andersson et al. 2021, "Visualizing Errors in Rendered HDR").
_FLIP_ACES = (0.6 * 0.6 * 2.51, 0.6 * 0.03, 0.0, 0.6 * 0.6 * 2.43, 0.6 * 0.59, 0.14)
_FLIP_T = 0.85
#: Linear sRGB -> CIE Y (luminance) weights used by FLIP.
LUMINANCE = (0.2126729, 0.7151522, 0.0721750)


@dataclass(frozen=True)
class FlipExposure:
    """HDR-FLIP exposure range: ``num`` exposures from ``start`` to ``stop`` (log2 stops)."""

    start: float
    stop: float
    num: int

    def as_parameters(self) -> dict:
        return {"startExposure": float(self.start), "stopExposure": float(self.stop), "numExposures": int(self.num)}


def flip_exposure(reference: torch.Tensor | np.ndarray) -> FlipExposure:
    """FLIP's exposure range computed from *all* pixels of a sequence's reference frames.

    ``reference``: ``[T, 3, H, W]`` (or ``[3, H, W]``) linear HDR. Rule (as in FLIP):
    ``x*`` solves ``aces_flip(x*) = 0.85``; ``start = log2(x* / max Y)``, ``stop = log2(x* / median Y)``,
    ``num = max(2, ceil(stop - start))`` with ``Y`` the luminance of the reference pixels.
    An all-black reference gives the range (0, 0, 2).
    """
    ref = reference.detach().float().cpu().numpy() if isinstance(reference, torch.Tensor) else np.asarray(reference)
    if ref.ndim == 3:
        ref = ref[None]
    w = np.asarray(LUMINANCE, dtype=np.float64)
    lum = np.tensordot(np.clip(ref.astype(np.float64), 0.0, None), w, axes=([1], [0]))
    a, b, c, d, e, f = _FLIP_ACES
    qa, qb, qc = a - _FLIP_T * d, b - _FLIP_T * e, c - _FLIP_T * f
    x_star = 0.5 * (-qb + math.sqrt(qb * qb - 4.0 * qa * qc)) / qa
    y_max = float(lum.max())
    y_med = float(np.median(lum))
    if y_max <= 0.0:
        return FlipExposure(0.0, 0.0, 2)
    if y_med <= 0.0:  # mostly black frames: fall back to the mean of the lit pixels
        y_med = float(lum[lum > 0].mean())
    start = math.log2(x_star / y_max)
    stop = math.log2(x_star / y_med)
    return FlipExposure(start, stop, int(max(2, math.ceil(stop - start))))


def _flip_input(x: torch.Tensor, name: str) -> np.ndarray:
    """``[3, H, W]`` tensor -> contiguous float32 ``[H, W, 3]`` array validated for FLIP."""
    arr = x.detach().float().cpu().permute(1, 2, 0).contiguous().numpy()
    if not np.isfinite(arr).all():
        raise ValueError(f"flip: {name} contains NaN or Inf")
    # HDR-FLIP is defined on non-negative radiance; tiny negatives (e.g. from OIDN) count as black.
    return np.ascontiguousarray(np.clip(arr, 0.0, None), dtype=np.float32)


def flip(output: torch.Tensor, reference: torch.Tensor, exposure: FlipExposure | None = None) -> torch.Tensor:
    """Mean HDR-FLIP error per frame. ``output, reference``: ``[N, 3, H, W]`` linear HDR -> ``[N]``.

    ``exposure``: the sequence's range from :func:`flip_exposure`; when None it is computed
    from the given reference frames (all ``N`` of them), never per frame.
    """
    import flip_evaluator

    _check_pair(output, reference, "flip")
    if exposure is None:
        exposure = flip_exposure(reference)
    params = exposure.as_parameters()
    values = []
    for i in range(output.shape[0]):
        ref = _flip_input(reference[i], "reference")
        test = _flip_input(output[i], "output")
        _, mean, _ = flip_evaluator.evaluate(ref, test, "HDR", applyMagma=False, computeMeanError=True,
                                             parameters=dict(params))
        values.append(float(mean))
    return torch.tensor(values, dtype=torch.float32)


#: Per-frame metrics computed independently frame by frame: name -> function.
FRAME_METRICS = {"psnr": psnr, "ssim": ssim, "relmse": relmse, "smape": smape}


# ----------------------------------------------------------------------------- aggregation


@dataclass
class _SequenceState:
    """What the accumulator remembers of a sequence between updates (for tPSNR and warm-up)."""

    steps_since_reset: int = 0
    last_index: int | None = None
    prev_out_tm: torch.Tensor | None = None  # [3, H, W] tonemapped
    prev_ref_tm: torch.Tensor | None = None
    exposure: FlipExposure | None = None
    rows: list = field(default_factory=list)


def _nanmean(values: Iterable[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(sum(vals) / len(vals)) if vals else float("nan")


class MetricAccumulator:
    """Collects per-frame metrics over sequences; averages per sequence, then over sequences.

    Usable from a Lightning ``validation_step`` (windows ``[B, T, 3, H, W]`` with
    ``sequence``, ``frame_index`` and ``reset`` from the batch) and from evaluation (a whole
    sequence ``[T, 3, H, W]`` at a time, or frame by frame: state is carried between calls,
    so tPSNR links frame ``i`` to frame ``i-1`` of the same sequence across calls).

    ``metrics``: names from :data:`METRICS` (``flip`` is slow: about 6 s per 1080p frame).
    ``warmup``: frames after each reset (sequence/window start, camera cut) that are excluded
    from the means; they still advance the temporal state.
    """

    def __init__(self, metrics: Sequence[str] = ("psnr", "ssim", "tpsnr", "relmse", "smape"), warmup: int = 0):
        unknown = [m for m in metrics if m not in METRICS]
        if unknown:
            raise ValueError(f"unknown metric(s) {unknown}; known: {list(METRICS)}")
        if warmup < 0:
            raise ValueError(f"warmup must be >= 0, got {warmup}")
        self.metrics = [m for m in METRICS if m in metrics]
        #: frame-subset columns of the metrics computed (``psnr_f2`` when ``psnr`` is)
        self.subsets = [c for c, spec in FRAME_SUBSETS.items() if spec.of in self.metrics]
        self.warmup = int(warmup)
        self.reset()

    def reset(self) -> None:
        """Forget everything (call at the start of each validation epoch)."""
        self._seqs: OrderedDict[str, _SequenceState] = OrderedDict()

    def set_flip_exposure(self, sequence: str, reference: torch.Tensor | FlipExposure) -> None:
        """Fix the FLIP exposure of ``sequence`` from its reference ``[T, 3, H, W]`` (or a range).

        Without this, the range is taken from the reference frames of the sequence's first update.
        """
        state = self._seqs.setdefault(sequence, _SequenceState())
        state.exposure = reference if isinstance(reference, FlipExposure) else flip_exposure(reference)

    @torch.no_grad()
    def update(self, output: torch.Tensor, reference: torch.Tensor, sequence: str | Sequence[str],
               frame_index: torch.Tensor | Sequence[int] | None = None,
               reset: torch.Tensor | Sequence[bool] | None = None,
               values: dict[str, Sequence[float]] | None = None) -> None:
        """Add frames.

        Either one sequence: ``output, reference`` ``[T, 3, H, W]`` linear HDR, ``sequence`` a
        str, ``frame_index`` ``[T]``, ``reset`` bool ``[T]``; or a batch of windows:
        ``[B, T, 3, H, W]``, ``sequence`` a list of B names, ``frame_index`` ``[B, T]``,
        ``reset`` ``[B, T]``. Frames must come in order within a sequence. Without
        ``frame_index`` frames are numbered after the last one seen; without ``reset`` only
        the first frame ever seen of a sequence resets. ``values``: the per-frame values of the
        :data:`CALLER_METRICS` computed (``{name: [T]}``, or ``[B, T]`` for windows; NaN where
        undefined); a caller metric not given is NaN.
        """
        if output.ndim == 4:
            fi = None if frame_index is None else torch.as_tensor(frame_index)[None]
            rs = None if reset is None else torch.as_tensor(reset)[None]
            vs = None if values is None else {k: [list(v)] for k, v in values.items()}
            return self.update(output[None], reference[None], [sequence], fi, rs, vs)
        if output.ndim != 5 or output.shape != reference.shape or output.shape[2] != 3:
            raise ValueError(f"expected [B, T, 3, H, W] output and reference, got {tuple(output.shape)} "
                             f"and {tuple(reference.shape)}")
        if isinstance(sequence, str):
            sequence = [sequence]
        if len(sequence) != output.shape[0]:
            raise ValueError(f"{len(sequence)} sequence names for a batch of {output.shape[0]}")
        for b, name in enumerate(sequence):
            fi = None if frame_index is None else [int(v) for v in torch.as_tensor(frame_index)[b].tolist()]
            rs = None if reset is None else [bool(v) for v in torch.as_tensor(reset)[b].tolist()]
            vs = {k: [float(x) for x in v[b]] for k, v in (values or {}).items()}
            self._update_sequence(str(name), output[b], reference[b], fi, rs, vs)

    def _update_sequence(self, name: str, out: torch.Tensor, ref: torch.Tensor,
                         frame_index: list[int] | None, reset: list[bool] | None,
                         values: dict[str, list[float]] | None = None) -> None:
        state = self._seqs.setdefault(name, _SequenceState())
        t_count = out.shape[0]
        if frame_index is None:
            start = 0 if state.last_index is None else state.last_index + 1
            frame_index = list(range(start, start + t_count))
        if reset is None:
            reset = [False] * t_count
        reset = [r or (state.last_index is None and t == 0) for t, r in enumerate(reset)]
        per_frame = {m: FRAME_METRICS[m](out, ref).tolist() for m in self.metrics if m in FRAME_METRICS}
        if "flip" in self.metrics and state.exposure is None:
            state.exposure = flip_exposure(ref)
        out_tm, ref_tm = tonemap(out), tonemap(ref)
        for t in range(t_count):
            idx = frame_index[t]
            contiguous = state.last_index is not None and idx == state.last_index + 1
            if reset[t]:
                state.steps_since_reset = 0
            row: dict = {"sequence": name, "frame": idx}
            for m, frame_values in per_frame.items():
                row[m] = float(frame_values[t])
            for m in CALLER_METRICS:
                if m in self.metrics:
                    row[m] = float(values[m][t]) if values and m in values else float("nan")
            if "tpsnr" in self.metrics:
                if not reset[t] and contiguous and state.prev_out_tm is not None:
                    row["tpsnr"] = float(tpsnr_pair(state.prev_out_tm[None], out_tm[t:t + 1],
                                                    state.prev_ref_tm[None], ref_tm[t:t + 1])[0])
                else:
                    row["tpsnr"] = float("nan")
            kept = state.steps_since_reset >= self.warmup
            if kept and "flip" in self.metrics:
                row["flip"] = float(flip(out[t:t + 1], ref[t:t + 1], state.exposure)[0])
            row["warmup"] = not kept
            state.rows.append(row)
            state.prev_out_tm, state.prev_ref_tm = out_tm[t], ref_tm[t]
            state.last_index = idx
            state.steps_since_reset += 1

    # ----------------------------------------------------------------- results

    def frame_rows(self, include_warmup: bool = True) -> list[dict]:
        """One dict per frame: ``sequence``, ``frame``, ``warmup`` and each metric."""
        return [r for s in self._seqs.values() for r in s.rows if include_warmup or not r["warmup"]]

    def per_sequence(self) -> OrderedDict[str, dict[str, float]]:
        """``{sequence: {metric: mean over kept frames, subset: mean over its frames, "frames":
        count kept}}`` in first-seen order (subsets: :attr:`subsets`, see :class:`Metric`)."""
        result: OrderedDict[str, dict[str, float]] = OrderedDict()
        for name, state in self._seqs.items():
            kept = [r for r in state.rows if not r["warmup"]]
            if not kept:
                continue
            values = {m: _nanmean(r.get(m, float("nan")) for r in kept) for m in self.metrics}
            for column in self.subsets:
                spec = FRAME_SUBSETS[column]
                values[column] = _nanmean(r[spec.of] for r in state.rows if r["frame"] >= spec.first_frame)
            values["frames"] = len(kept)
            result[name] = values
        return result

    @property
    def columns(self) -> list[str]:
        """The metrics, then their frame-subset columns: the keys of ``compute(subsets=True)``."""
        return [*self.metrics, *self.subsets]

    def compute(self, subsets: bool = False) -> dict[str, float]:
        """Overall ``{metric: mean over sequences of the per-sequence means}``; with ``subsets``,
        the frame-subset columns too (:attr:`columns`)."""
        seqs = self.per_sequence()
        return {m: _nanmean(v[m] for v in seqs.values()) for m in (self.columns if subsets else self.metrics)}

    def sequence_sums(self) -> dict[str, dict[str, tuple[float, int]]]:
        """``{sequence: {metric: (sum, count)}}`` over kept, non-NaN frames: what a process sends
        to the others under DDP (picklable); :func:`combine_sequence_sums` averages it."""
        result: dict[str, dict[str, tuple[float, int]]] = {}
        for name, state in self._seqs.items():
            kept = [r for r in state.rows if not r["warmup"]]
            if not kept:
                continue
            sums = {}
            for m in self.metrics:
                vals = [r[m] for r in kept if r.get(m) is not None and not math.isnan(r[m])]
                sums[m] = (float(sum(vals)), len(vals))
            result[name] = sums
        return result


def combine_sequence_sums(parts: Iterable[dict[str, dict[str, tuple[float, int]]]],
                          metrics: Sequence[str]) -> dict[str, float]:
    """``{metric: mean over sequences of (sum / count)}`` from the :meth:`MetricAccumulator.sequence_sums`
    of several processes. A sequence found in several parts counts once (the first part's), so a
    sequence that a process re-ran as padding is not counted twice; the overall mean is taken over
    the sequences in name order, the same whatever the number of processes."""
    merged: dict[str, dict[str, tuple[float, int]]] = {}
    for part in parts:
        for name, sums in part.items():
            merged.setdefault(name, sums)
    result = {}
    for m in metrics:
        means = [merged[n][m][0] / merged[n][m][1] for n in sorted(merged) if merged[n][m][1] > 0]
        result[m] = float(sum(means) / len(means)) if means else float("nan")
    return result

    def __len__(self) -> int:
        return sum(len(s.rows) for s in self._seqs.values())
