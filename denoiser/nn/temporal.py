"""Temporal recurrence: the history state, its warping, and the predicted blend weights.

State (all ``[B, C, H, W]`` float32 at the frame's size, linear where radiance):

* ``"output"``   ``[B, 3, H, W]`` previous denoised output (linear HDR);
* ``"color"``    ``[B, 3, H, W]`` accumulated input color (the blended filter input, linear);
* ``"features"`` ``[B, F, H, W]`` accumulated learned features (tanh of a head, in [-1, 1]);
* ``"guide"``    ``[B, 7, H, W]`` previous guide features (albedo, normal, depth feature), so
  the network can compare warped and current geometry and reject stale history.

Per step: the state is warped to the current frame (:func:`~denoiser.nn.warp.warp_all`, which
also gives the coverage ``c`` in [0, 1]: the fraction of the bilinear footprint inside the image,
0 for an item whose history is discarded). Warped values are divided by ``c`` (where ``c > COVER_MIN``, else 0) so they
are convex combinations of previous pixels, and ``valid = c`` (0 where the history was reset).
The network sees, next to the current frame, ``log1p(history output / s)``,
``log1p(history color / s)`` (``s`` the current color scale), the warped guide (unless
``guide_input`` is off) and features and ``valid``. Its level-0 head predicts two logits and the next features:

    a = sigmoid(h_in)  * valid;  filter input = color    + a * (history color  - color)
    b = sigmoid(h_out) * valid;  output       = filtered + b * (history output - filtered)

Both blends are convex, so the output stays within [min, max] of the input and warped history.
A reset (first frame, camera cut) sets ``valid = 0`` and replaces history by zeros, so the
result cannot depend on the previous sequence.

Disocclusion gate (``reject_threshold`` ``t``; None = off, the behaviour of configs from before
it existed): history whose warped guide disagrees with the current guide is dropped before the
network sees it, ``valid = c * g`` with ``g = clamp(2 - D / t, 0, 1)`` (1 up to ``D = t``, 0 from
``D = 2 t``), a rule that holds whatever the learned blend predicts. ``D [B, 1, H, W]`` is the
largest of three disagreements between the warped previous guide ``P`` and the current one ``C``:

* depth (pointwise): ``|logit(P_depth) - logit(C_depth)|``; the logit of the depth feature
  ``d / (d + m)`` is ``log(d / m)``, so this is the log depth ratio (the feature clamped to
  ``[1e-6, 1 - 1e-6]``, so no-hit pixels agree with each other). It catches every disocclusion
  by an object at another depth, up to the pixel next to the object;
* normal (pointwise): ``1 - cos`` of the angle between the normals; where one normal is
  (nearly) zero (no hit) and the other is not, 1; where both are, 0;
* albedo (box): how far the previous albedo feature ``log1p(albedo)`` lies outside the
  [min, max] of the current albedo feature over the 3x3 neighbourhood, max over channels.
  The box keeps sub-pixel motion over sharp textures (the warp blends neighbouring texels)
  from rejecting history; the price is that an object told apart by its albedo alone leaves
  history in the one pixel next to it.

The depth term also compares ``log m`` of the two frames (the per-frame mean hit depth):
changes of ``m`` by less than ``t`` between two frames do not reject anything.

History clamp (``history_clamp`` ``k``; None = off, the behaviour of configs from before it
existed): before each blend, the warped history is clamped per channel to the box
``[mu - k sigma, mu + k sigma]`` of the frame it is blended into, over each pixel's 3x3
neighbourhood (mean and standard deviation of the in-image part): the history color to the box
of the current color, the history output to the box of the filtered frame. It is the
neighbourhood clamp of temporal anti-aliasing: history that the current frame cannot explain (a
turning object's interior, whose warped history the motion vectors cannot line up, or a shading
change) is pulled to what the current frame shows, whatever the learned blend predicts, while
history that agrees with the current frame passes unchanged. Noise widens the box, so on a
noisy input it rejects only gross disagreement; the filtered frame's box is tighter.

History disagreement (``history_disagreement``; False = off, the behaviour of configs from before
it existed): one more network input, ``disagreement [B, 1, H, W]``, how many standard deviations
of the current noisy colour's 3x3 neighbourhood the warped history colour lies from its mean,
squashed to [0, 1) (:func:`history_disagreement`; times ``valid``, so 0 without history). The
disocclusion gate compares guides, which agree on a turning object's interior; the clamp holds a
fixed box. This input lets the learned blend weights see the colour evidence itself (issue 33's
"learned rejection that sees the warped-history-vs-current difference"). Parameter transfer gives
its input channel zero weights when the teacher lacks it (:mod:`denoiser.lit.transfer`).

Probe (diagnostics, :mod:`denoiser.report.history_diagnosis`): ``TemporalRecurrence.probe`` is None
(the default: nothing recorded, one attribute test per step). Set to a dict, every
:meth:`~TemporalRecurrence.warp` puts into it the tensors of that step it does not return
otherwise: ``"cover" [B, 1, H, W]`` (bilinear coverage, 0 where history was reset) and
``"gate" [B, 1, H, W]`` (the disocclusion gate, all ones without one), beside the
returned ``"history"`` dict. It changes no value the network computes.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.errors import ConfigError
from denoiser.nn.graph_mode import fused_kernels, unfused, untraced
from denoiser.nn.graph_ops import graph_node
from denoiser.nn.inputs import GUIDE_CHANNELS, color_feature_part
from denoiser.nn.warp import WarpHistoryOp, warp_all

#: minimum bilinear coverage for a warped history value to count
COVER_MIN = 1e-4

STATE_KEYS = ("output", "color", "features", "guide")

#: the state entries an exported graph's fused warp writes channels-last ([B, H, W, C]): the U-Net's
#: first convolution reads them in that layout (denoiser.nn.warp.WarpHistoryOp)
CHANNELS_LAST_KEYS = ("features", "guide")

#: relative floor of the standard deviation in :func:`history_disagreement` (a flat neighbourhood)
DISAGREEMENT_EPS = 0.05

#: clamp of the depth feature before its logit (log depth ratio) in the disocclusion gate
DEPTH_LOGIT_EPS = 1e-6


def _box_max(x: torch.Tensor) -> torch.Tensor:
    """3x3 max of ``[B, C, H, W]`` over the in-image part of each neighbourhood (replicating the
    edge leaves a max unchanged), as elementwise maxima of shifted slices, rows then columns:
    same values as a 3x3 ``max_pool2d``, and ops an inference engine fuses (its pooling kernel
    on few channels at full resolution was slower than the rest of the gate together)."""
    xp = F.pad(x, (1, 1, 0, 0), mode="replicate")
    x = torch.maximum(torch.maximum(xp[..., :-2], xp[..., 1:-1]), xp[..., 2:])
    xp = F.pad(x, (0, 0, 1, 1), mode="replicate")
    return torch.maximum(torch.maximum(xp[..., :-2, :], xp[..., 1:-1, :]), xp[..., 2:, :])


def _box_excess(previous: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """How far ``previous [B, C, H, W]`` lies outside the 3x3 [min, max] of ``current`` (same
    shape), max over channels -> ``[B, 1, H, W]`` >= 0."""
    hi = _box_max(current)
    lo = -_box_max(-current)
    return torch.maximum(previous - hi, lo - previous).clamp_min(0).amax(dim=1, keepdim=True)


def box_moments(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(mean, variance)`` of ``x [B, C, H, W]`` over each pixel's 3x3 neighbourhood, the edges
    replicated (population variance), each ``[B, C, H, W]`` float32.

    The moments are taken of the differences to the centre pixel, ``d = x_n - x_c`` (mean
    ``x_c + E[d]``, variance ``E[d^2] - E[d]^2``), as nine shifted slices: the variance then does
    not lose the small spread of a bright neighbourhood to float32 cancellation, as
    ``E[x^2] - E[x]^2`` would."""
    x = x.float()
    h, w = x.shape[-2:]
    xp = F.pad(x, (1, 1, 1, 1), mode="replicate")
    total = torch.zeros_like(x)
    squares = torch.zeros_like(x)
    for dy in range(3):
        for dx in range(3):
            if dy == 1 and dx == 1:
                continue
            d = xp[..., dy:dy + h, dx:dx + w] - x
            total = total + d
            squares = squares + d * d
    mean_d = total / 9.0
    var = (squares / 9.0 - mean_d * mean_d).clamp_min(0.0)
    return x + mean_d, var


def neighbourhood_clamp(history: torch.Tensor, current: torch.Tensor, k: float) -> torch.Tensor:
    """``history [B, C, H, W]`` clamped per channel to ``[mu - k sigma, mu + k sigma]``, the mean
    and (population) standard deviation of ``current [B, C, H, W]`` over each pixel's 3x3
    neighbourhood (:func:`box_moments`), the edges replicated. float32; finite for finite inputs."""
    mean, var = box_moments(current)
    # the epsilon keeps the square root's gradient finite where the neighbourhood is constant
    spread = k * torch.sqrt(var + 1e-12)
    return torch.minimum(torch.maximum(history.float(), mean - spread), mean + spread)


def clamp_blend(base: torch.Tensor, previous: torch.Tensor, weight: torch.Tensor, k: float) -> torch.Tensor:
    """The history clamp and blend: ``base + weight * (clamped - base)`` with ``clamped`` the
    :func:`neighbourhood_clamp` of ``previous`` to ``base``'s 3x3 neighbourhood. base, previous:
    ``[B, C, H, W]``; weight ``[B, 1, H, W]`` in [0, 1]; -> ``[B, C, H, W]`` float32. In a graph
    recorded with the extension's operations (:func:`denoiser.nn.graph_mode.kernels_as_op`) it is
    one ``denoiser::ClampBlend`` node."""
    if fused_kernels():
        return ClampBlendOp.apply(base.float(), previous.float(), weight.float(), float(k))
    return base + weight * (neighbourhood_clamp(previous, base, k) - base)


def history_disagreement(history: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """How far ``history [B, C, H, W]`` (warped history colour, linear) lies from the 3x3
    neighbourhood of ``current [B, C, H, W]`` (the current noisy colour), in its standard
    deviations: ``z = max_c |h_c - mu_c| / (sigma_c + DISAGREEMENT_EPS * (|mu_c| + 1e-3))``,
    returned as ``z / (1 + z)`` in [0, 1) ``[B, 1, H, W]`` float32 (0: the history is the
    neighbourhood's mean; near 1: many standard deviations off). The statistic the history clamp
    thresholds, given to the network as an input so that its blend can learn where to distrust
    the history (``history_disagreement``, module docstring)."""
    mean, var = box_moments(current)
    sigma = torch.sqrt(var + 1e-12) + DISAGREEMENT_EPS * (mean.abs() + 1e-3)
    z = ((history.float() - mean).abs() / sigma).amax(dim=1, keepdim=True)
    return z / (1.0 + z)


def _log_depth_ratio(previous: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """``|logit(p) - logit(c)|`` of two depth features ``d / (d + m)`` (``[B, 1, H, W]`` each),
    i.e. the absolute log ratio of ``d / m`` between the frames, with one logarithm:
    ``|log(p (1 - c) / (c (1 - p)))|``, the features clamped to ``[DEPTH_LOGIT_EPS, 1 - DEPTH_LOGIT_EPS]``."""
    p = previous.clamp(DEPTH_LOGIT_EPS, 1.0 - DEPTH_LOGIT_EPS)
    c = current.clamp(DEPTH_LOGIT_EPS, 1.0 - DEPTH_LOGIT_EPS)
    return torch.log((p * (1.0 - c)) / (c * (1.0 - p))).abs()


def guide_disagreement(previous: torch.Tensor, current: torch.Tensor) -> torch.Tensor:
    """Disagreement ``D`` of the disocclusion gate (module docstring).

    previous: ``[B, 7, H, W]`` warped previous guide; current: ``[B, 7, H, W]`` current guide
    (:func:`~denoiser.nn.inputs.guide_features`). Returns ``[B, 1, H, W]`` float32 >= 0.
    """
    pa, pn, pd = torch.split(previous.float(), [3, 3, 1], dim=1)
    ca, cn, cd = torch.split(current.float(), [3, 3, 1], dim=1)
    albedo = _box_excess(pa, ca)
    lp, lc = pn.norm(dim=1, keepdim=True), cn.norm(dim=1, keepdim=True)
    hp, hc = lp > 0.5, lc > 0.5
    cos = (pn * cn).sum(dim=1, keepdim=True) / (lp * lc).clamp_min(1e-6)
    normal = torch.where(hp & hc, 1.0 - cos, torch.where(hp == hc, 0.0, 1.0))
    depth = _log_depth_ratio(pd, cd)
    return torch.maximum(torch.maximum(albedo, normal), depth)


class TemporalRecurrence(nn.Module):
    """History handling for :class:`~denoiser.nn.denoiser.Denoiser` (no parameters of its own).

    Args:
        state_features: channels F of the learned recurrent features.
        reject_threshold: ``t`` of the disocclusion gate (module docstring), > 0; None (the
            default, and what a stored config without the key means) switches the gate off.
        history_clamp: ``k`` of the history clamp (module docstring), > 0; None (the default,
            and what a stored config without the key means) switches it off.
        history_disagreement: add the history disagreement input (module docstring); False (the
            default, and what a stored config without the key means) leaves the inputs as before.
        guide_input: the warped history guide (7 channels) is a U-Net input; False leaves it out
            (the disocclusion gate still reads it): 7 fewer input channels of the first
            full-resolution convolution. True is the default, and what a stored config without
            the key means.
    """

    def __init__(self, state_features: int = 8, reject_threshold: float | None = None,
                 history_clamp: float | None = None, history_disagreement: bool = False,
                 guide_input: bool = True):
        super().__init__()
        self.guide_input = bool(guide_input)
        self.history_disagreement = bool(history_disagreement)
        if history_clamp is not None and not float(history_clamp) > 0:
            raise ConfigError(f"net.temporal.history_clamp: must be > 0 or null, got {history_clamp}")
        self.history_clamp = None if history_clamp is None else float(history_clamp)
        self.state_features = int(state_features)
        if reject_threshold is not None and not float(reject_threshold) > 0:
            raise ConfigError(f"net.temporal.reject_threshold: must be > 0 or null, got {reject_threshold}")
        self.reject_threshold = None if reject_threshold is None else float(reject_threshold)
        #: channels added to the U-Net input, in order: ``(part, channels)`` (see :meth:`inputs`)
        self.input_layout = (("output", 3), ("color", 3),
                             *((("guide", GUIDE_CHANNELS),) if self.guide_input else ()),
                             ("features", self.state_features), ("valid", 1),
                             *((("disagreement", 1),) if self.history_disagreement else ()))
        self.input_channels = sum(n for _, n in self.input_layout)
        #: channels the level-0 head must predict, in order: ``(part, channels)``; the blend
        #: logits h_in, h_out, then the next state features
        self.head_layout = (("history_in", 1), ("history_out", 1), ("features", self.state_features))
        self.head_channels = sum(n for _, n in self.head_layout)
        starts = [sum(n for _, n in self.head_layout[:i]) for i in range(len(self.head_layout))]
        self._head = {part: slice(s, s + n) for (part, n), s in zip(self.head_layout, starts)}
        #: None, or a dict that :meth:`warp` fills with the step's coverage, gate and history (module docstring)
        self.probe: dict | None = None

    def state_channels(self) -> dict[str, int]:
        return {"output": 3, "color": 3, "features": self.state_features, "guide": GUIDE_CHANNELS}

    def zero_state(self, like: torch.Tensor) -> dict[str, torch.Tensor]:
        """All-zero state shaped like ``like`` ``[B, *, H, W]``."""
        b, _, h, w = like.shape
        return {k: like.new_zeros(b, c, h, w, dtype=torch.float32)
                for k, c in self.state_channels().items()}

    def gate(self, previous: torch.Tensor, current: torch.Tensor,
             previous_last: torch.Tensor | None = None) -> torch.Tensor:
        """Disocclusion gate ``clamp(2 - D / t, 0, 1)``: guides ``[B, 7, H, W]`` -> ``[B, 1, H, W]``
        in [0, 1] (all ones when ``reject_threshold`` is None). previous_last: the previous guide
        as ``[B, H, W, 7]`` where the fused warp wrote it so (read by the fused gate, not permuted)."""
        if self.reject_threshold is None:
            return torch.ones_like(current[:, :1], dtype=torch.float32)
        if fused_kernels():  # one denoiser::GuideGate node (denoiser.nn.graph_ops: the schema), the previous guide channels-last
            if previous_last is None:
                previous_last = previous.permute(0, 2, 3, 1)
            return GuideGateOp.apply(previous_last.float(), current.float(), self.reject_threshold)
        d = guide_disagreement(previous, current)
        return (2.0 - d / self.reject_threshold).clamp(0.0, 1.0)

    def warp(self, state: dict | None, motion: torch.Tensor, reset: torch.Tensor | None,
             like: torch.Tensor, guide: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Warp the state to the current frame.

        state: dict of ``STATE_KEYS`` tensors ``[B, C, H, W]`` or None/empty (= reset all);
        motion: ``[B, 2, H, W]``; reset: bool ``[B]`` or None; like: ``[B, 3, H, W]`` current color;
        guide: ``[B, 7, H, W]`` current guide features, needed by the disocclusion gate (None: no gate).
        Returns the warped, coverage-normalised history (same keys) plus ``"valid" [B, 1, H, W]``
        (coverage times the disocclusion gate), and with ``history_disagreement``
        ``"disagreement" [B, 1, H, W]`` (:func:`history_disagreement` of the history colour against
        ``like``, times ``valid``).
        """
        b = like.shape[0]
        if not state:
            state = self.zero_state(like)
            keep = torch.zeros(b, dtype=torch.bool, device=like.device)
        elif reset is None:
            keep = torch.ones(b, dtype=torch.bool, device=like.device)
        else:
            keep = ~reset.to(device=like.device, dtype=torch.bool).reshape(b)
        keep = keep.view(b, 1, 1, 1)
        # discarded history is never read (its sample positions lie off the image), so it
        # cannot leak, not even as NaN through 0 * x; its coverage is 0
        if fused_kernels():  # one denoiser::WarpHistory node (denoiser.nn.graph_ops: the schema)
            # the guide and features warped channels-last: the U-Net's first convolution reads them so
            last = tuple(k in CHANNELS_LAST_KEYS for k in STATE_KEYS)
            *values, valid = WarpHistoryOp.apply(motion.float(), keep, COVER_MIN, last,
                                                 *(state[k].float() for k in STATE_KEYS))
            history = {k: v.permute(0, 3, 1, 2) if l else v for k, v, l in zip(STATE_KEYS, values, last)}
            guide_last = values[STATE_KEYS.index("guide")]
        else:
            guide_last = None
            warped, cover = warp_all([state[k] for k in STATE_KEYS], motion, keep)
            ok = cover > COVER_MIN
            cover_safe = cover.clamp_min(COVER_MIN)
            history = {k: torch.where(ok, v / cover_safe, 0.0) for k, v in zip(STATE_KEYS, warped)}
            valid = torch.where(ok, cover, 0.0)
        history["valid"] = valid
        gate = None
        if self.reject_threshold is not None and guide is not None:
            gate = self.gate(history["guide"], guide, guide_last)
            history["valid"] = history["valid"] * gate
        if self.history_disagreement:
            history["disagreement"] = history_disagreement(history["color"], like) * history["valid"]
        if self.probe is not None:
            self.probe.update(cover=valid, history=dict(history),
                              gate=torch.ones_like(valid) if gate is None else gate)
        return history

    def input_parts(self, history: dict[str, torch.Tensor], scale: torch.Tensor) -> list[torch.Tensor]:
        """Network inputs from the warped history, one ``[B, C_i, H, W]`` float32 tensor per
        entry of ``input_layout``, in its order (what an exported graph feeds the U-Net's first
        convolution part by part). scale: ``[B, 1, 1, 1]`` current color scale.
        """
        parts = {"output": color_feature_part(history["output"], scale),
                 "color": color_feature_part(history["color"], scale),
                 "guide": history["guide"], "features": history["features"], "valid": history["valid"],
                 "disagreement": history.get("disagreement")}
        return [parts[part] for part, _ in self.input_layout]

    def inputs(self, history: dict[str, torch.Tensor], scale: torch.Tensor) -> torch.Tensor:
        """Network inputs from the warped history: ``[B, input_channels, H, W]`` float32, the
        concatenation of :meth:`input_parts`. scale: ``[B, 1, 1, 1]`` current color scale.
        """
        return torch.cat(self.input_parts(history, scale), dim=1)

    def blend_in(self, color: torch.Tensor, history: dict[str, torch.Tensor], head: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """Blend history color into the input: color ``[B, 3, H, W]``, head ``[B, head_channels, H, W]``.

        Returns ``(filter input [B, 3, H, W], weight a [B, 1, H, W])``.
        """
        a = torch.sigmoid(head[:, self._head["history_in"]].float()) * history["valid"]
        if self.history_clamp is not None:
            return clamp_blend(color, history["color"], a, self.history_clamp), a
        return color + a * (history["color"] - color), a

    def blend_out(self, filtered: torch.Tensor, history: dict[str, torch.Tensor], head: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """Blend the history output into the filtered frame; returns ``(output, weight b)``."""
        b = torch.sigmoid(head[:, self._head["history_out"]].float()) * history["valid"]
        if self.history_clamp is not None:
            return clamp_blend(filtered, history["output"], b, self.history_clamp), b
        return filtered + b * (history["output"] - filtered), b

    def next_state(self, output: torch.Tensor, color: torch.Tensor, head: torch.Tensor,
                   guide: torch.Tensor) -> dict[str, torch.Tensor]:
        """State for the next step (tensors ``[B, C, H, W]``, see module docstring)."""
        features = torch.tanh(head[:, self._head["features"]].float())
        return {"output": output, "color": color, "features": features, "guide": guide}


# ----------------------------------------------------------------------------- export stubs


class ClampBlendOp(torch.autograd.Function):
    """:func:`denoiser.nn.temporal.clamp_blend` recorded as one ``denoiser::ClampBlend`` node
    (attribute ``k``); the value is the plain computation.

    forward(base ``[B, C, H, W]``, previous ``[B, C, H, W]``, weight ``[B, 1, H, W]``, k float)
    -> ``[B, C, H, W]`` float32.
    """

    @staticmethod
    def forward(ctx, base, previous, weight, k):
        return untraced(unfused, clamp_blend, base, previous, weight, k)

    @staticmethod
    def symbolic(g, base, previous, weight, k):
        return graph_node(g, "ClampBlend", base, previous, weight, like=base, k=float(k))


class GuideGateOp(torch.autograd.Function):
    """:meth:`denoiser.nn.temporal.TemporalRecurrence.gate` recorded as one ``denoiser::GuideGate``
    node (attributes ``threshold``, ``previous_channels_last`` 1); the value is the plain computation.

    forward(previous ``[B, H, W, 7]`` channels-last (as :class:`WarpHistoryOp` writes the warped
    guide), current ``[B, 7, H, W]``, threshold float) -> ``[B, 1, H, W]`` float32 in [0, 1].
    """

    @staticmethod
    def forward(ctx, previous, current, threshold):
        return untraced(lambda: (2.0 - guide_disagreement(previous.permute(0, 3, 1, 2), current) / threshold
                                 ).clamp(0.0, 1.0))

    @staticmethod
    def symbolic(g, previous, current, threshold):
        out = graph_node(g, "GuideGate", previous, current, like=current, threshold=float(threshold),
                         previous_channels_last=1)
        sizes = current.type().varyingSizes()  # [B, 1, H, W] (None where not known)
        if sizes is not None and len(sizes) == 4:
            out.setType(current.type().with_sizes([sizes[0], 1, sizes[2], sizes[3]]))
        return out
