"""Denoiser: EmbedNet -> U-Net -> per-pixel kernels through a filter, recurrent in time.

One :meth:`Denoiser.step` serves training, distillation, evaluation, export and inference;
:meth:`Denoiser.forward` unrolls it over a window. Built by Hydra from ``conf/net/*.yaml``:
``embed`` and ``unet`` are partial constructors (the Denoiser supplies the channel counts that
follow from the other parts), ``filter`` and ``temporal`` are modules (``temporal: null`` turns
the recurrence off).

Per step (shapes for one frame ``[B, C, H, W]``):

1. inputs are sanitised (NaN, -Inf -> 0; +Inf -> 65504: :mod:`denoiser.nonfinite`) and transformed
   (:mod:`denoiser.nn.inputs`):
   color ``log1p(max(x,0)/s)`` with the per-image scale ``s``, albedo, normal, depth features;
2. EmbedNet runs per sample (``samples [B, S, 3, H, W]`` present) or per pixel;
3. with temporal recurrence the warped history (:mod:`denoiser.nn.temporal`) is appended;
4. the U-Net input is padded (replicate) at the right and bottom to a multiple of
   ``self.multiple`` (2^len(encoder)); everything is cropped back afterwards, so any frame
   size works, 1x1 included;
5. the history color is blended into the input color, the filter (pyramid / single kernel /
   direct) produces the filtered frame on linear radiance, the history output is blended in.

Albedo demodulation (``demodulate: true``; off by default and for stored configs without the
key): right after sanitising, ``color`` (and ``samples``) are divided by the demodulation albedo
``a'`` (:func:`~denoiser.nn.inputs.demodulation_albedo`: 1 where the albedo is below 0.01 or not
finite, so emitters and the sky pass through), and steps 2-5 run on this irradiance exactly as
they would on a color: the color scale, the network's color features, the filter and the history
all see irradiance, and the state's ``"output"`` and ``"color"`` hold irradiance. Only the
returned output is remodulated, ``output = a' * irradiance output``: a convex combination of
input and history irradiance, times the pixel's own albedo (so texture detail is not blurred by
the filter or dragged along by the history). With albedo 1 everywhere the result equals the
network without demodulation bit for bit.

Filter domain (``filter_domain``): ``linear`` (the default, and what a stored config without the
key means) averages linear radiance. ``log`` averages ``y = sign(x) log1p(|x| / s)`` (``s`` the
per-image color scale, :func:`~denoiser.nn.inputs.color_scale`) and maps the filtered ``y`` back
with ``sign(y) s expm1(|y|)`` (:func:`compress` and :func:`expand`). The filter's weights are bounded below
(:func:`~denoiser.nn.kernels.scale_logits`), so in linear radiance a small emitter thousands of
times brighter than its surroundings leaks into every kernel that covers it, a glow around the
lamp (docs/results_log.md, "Small bright emitters"); compressed, it weighs as a value a few times
larger. The price is a bias: a mean of logarithms is below the logarithm of the mean. Both maps
are monotone, so the output stays within [min, max] of the filter's inputs; the history blends
stay linear.

Filtered remodulation (``remodulate: filtered``, with ``demodulate: true``): the returned output
is ``output = A(a') * irradiance output`` instead, where ``A`` applies per-pixel 3x3 kernels
(softmax over the in-image taps, :func:`~denoiser.nn.kernels.apply_kernels`) whose 9 logits are
extra channels at the end of the level-0 head. Renderers that average the albedo over the
pixel's samples (Cycles at a few spp; the simulator's ``aux=samples``) give an albedo with the
colour's sub-pixel texture noise, which plain remodulation multiplies back into the output
(docs/results_log.md, "Demodulation on renders with a noisy albedo"); the learned kernel can
smooth it where the guide buffers say it is noise. Its centre-tap bias starts at
``REMODULATION_CENTRE_BIAS``, so an untrained kernel is about the identity (plain remodulation).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.buffers import NETWORK_INPUTS
from denoiser.errors import ConfigError
from denoiser.nn.graph_mode import in_graph
from denoiser.nn.inputs import (
    GUIDE_CHANNELS,
    color_feature,
    color_scale,
    demodulation_albedo,
    guide_features,
    sanitize,
)
from denoiser.nn.kernels import apply_kernels
from denoiser.nn.unet import head_channels
from denoiser.recurrent import unroll

#: where the filter averages radiance: linear (unbiased), or log-compressed (module docstring)
FILTER_DOMAINS = ("linear", "log")
#: remodulation modes: the input's albedo, or the albedo through learned 3x3 kernels
REMODULATE = ("input", "filtered")
REMODULATION_KERNEL = 3
#: initial bias of the centre tap's logit: the softmax gives it about 0.99 of the weight
REMODULATION_CENTRE_BIAS = 10.0


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad ``[B, C, H, W]`` at the right and bottom so H and W are multiples."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % multiple, (-w) % multiple
    if ph == 0 and pw == 0:
        return x
    return F.pad(x, (0, pw, 0, ph), mode="replicate")


def logit_energy(heads) -> torch.Tensor:
    """Mean square of the U-Net head outputs (every logit the filter, the temporal blend and the
    state features are made of): ``heads`` list of ``[B, C_i, H_i, W_i]`` (or None) -> ``[B]``
    float32, the mean over heads of each head's mean square.

    Why it is penalised in training (``model.logit_penalty``): the filter's softmaxes see
    scale-normalised logits (:func:`denoiser.nn.kernels.scale_logits`), so the loss hardly
    changes when every head output is multiplied by a large factor; nothing then holds the
    activations' scale, and once a step pushed it up it kept growing (the demo teacher's U-Net
    activations went from about 10 to 10^7 in 20 steps, its output froze at 25 dB). A small
    penalty on this energy gives the scale a restoring force, as the z-loss does for softmax
    logits in large language models.
    """
    values = [h.float().pow(2).mean(dim=(1, 2, 3)) for h in heads if h is not None and h.shape[1] > 0]
    return torch.stack(values).mean(dim=0)


def compress(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``sign(x) log1p(|x| / scale)``: x ``[B, C, H, W]`` linear, scale ``[B, 1, 1, 1]`` -> float32."""
    x = x.float()
    return torch.sign(x) * torch.log1p(x.abs() / scale)


def expand(y: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`compress`: ``sign(y) scale (exp(|y|) - 1)`` -> float32 linear."""
    y = y.float()
    return torch.sign(y) * scale * (torch.exp(y.abs()) - 1.0)


def detach_state(state: dict | None) -> dict | None:
    """Detach every tensor of a state dict (truncated backpropagation through time)."""
    return None if state is None else {k: v.detach() for k, v in state.items()}


class Denoiser(nn.Module):
    """Recurrent kernel-predicting denoiser.

    Args:
        embed: ``embed(in_channels=...) -> EmbedNet`` (partial constructor).
        unet: ``unet(in_channels=..., head_channels=[...]) -> UNet`` (partial constructor).
        filter: a filter module with ``head_channels``, ``multiple`` and
            ``forward(x, heads, scale) -> (output, weights)``
            (:class:`~denoiser.nn.pyramid.PyramidFilter` and the ablation filters).
        temporal: :class:`~denoiser.nn.temporal.TemporalRecurrence` or None (no recurrence).
        demodulate: filter the irradiance ``color / a'`` and remodulate (module docstring);
            False (the default, and what a stored config without the key means) filters color.
        remodulate: ``input`` (the default: multiply by ``a'``) or ``filtered`` (multiply by
            ``a'`` through learned 3x3 kernels; needs ``demodulate``; module docstring).
        filter_domain: ``linear`` (the default) or ``log``: what the filter averages (module docstring).

    Attributes:
        feature_channels: widths of ``extras["features"]`` (one map per U-Net level, finest
            first; the same count for every config with the same number of encoder blocks).
    """

    def __init__(self, embed: Callable[..., nn.Module], unet: Callable[..., nn.Module],
                 filter: nn.Module, temporal: nn.Module | None = None, demodulate: bool = False,
                 remodulate: str = "input", filter_domain: str = "linear"):
        super().__init__()
        if filter_domain not in FILTER_DOMAINS:
            raise ConfigError(f"net.filter_domain: unknown {filter_domain!r}; use {' or '.join(FILTER_DOMAINS)}")
        self.filter_domain = filter_domain
        self.demodulate = bool(demodulate)
        if remodulate not in REMODULATE:
            raise ConfigError(f"net.remodulate: unknown {remodulate!r}; use {' or '.join(REMODULATE)}")
        if remodulate == "filtered" and not self.demodulate:
            raise ConfigError("net.remodulate=filtered needs net.demodulate=true (it filters the remodulation albedo)")
        self.remodulate = remodulate
        #: level-0 head channels of the remodulation kernel's logits (at the end of the head)
        self.remodulation_channels = REMODULATION_KERNEL ** 2 if remodulate == "filtered" else 0
        self.embed = embed(in_channels=3 + GUIDE_CHANNELS)
        self.temporal = temporal
        self.filter = filter
        unet_in = self.embed.out_channels + (temporal.input_channels if temporal is not None else 0)
        heads = list(filter.head_channels)
        self.filter_head0 = heads[0]
        if temporal is not None:
            heads[0] += temporal.head_channels
        heads[0] += self.remodulation_channels
        self.unet = unet(in_channels=unet_in, head_channels=heads)
        if self.remodulation_channels:
            with torch.no_grad():  # start at about the identity kernel (plain remodulation)
                centre = -self.remodulation_channels + REMODULATION_KERNEL ** 2 // 2
                self.unet.heads[0].bias[centre] = REMODULATION_CENTRE_BIAS
        self.multiple = max(self.unet.multiple, filter.multiple)
        self.feature_channels = list(self.unet.feature_channels)

    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def embed_inputs(self, frame: dict, color: torch.Tensor, scale: torch.Tensor,
                     guide: torch.Tensor, albedo: torch.Tensor | None = None) -> torch.Tensor:
        """EmbedNet input: ``[B, 10, H, W]`` per pixel, or ``[B, S, 10, H, W]`` with samples.

        color: ``[B, 3, H, W]`` (already demodulated when ``albedo`` is given); scale ``[B, 1, 1, 1]``;
        guide ``[B, 7, H, W]``; albedo: demodulation albedo ``[B, 3, H, W]`` the samples are divided by, or None.
        """
        samples = frame.get("samples")
        if samples is None:
            return torch.cat([color_feature(color, scale), guide], dim=1)
        samples = sanitize(samples)
        if albedo is not None:
            samples = samples / albedo.unsqueeze(1)
        b, s, _, h, w = samples.shape
        feats = color_feature(samples, scale.unsqueeze(1))
        return torch.cat([feats, guide.unsqueeze(1).expand(b, s, GUIDE_CHANNELS, h, w)], dim=2)

    def step(self, frame: dict, state: dict | None = None, reset: torch.Tensor | None = None):
        """Denoise one frame.

        frame: ``color [B, 3, H, W]`` linear HDR, ``albedo [B, 3, H, W]``, ``normal [B, 3, H, W]``,
            ``depth [B, 1, H, W]``, ``motion [B, 2, H, W]`` (backward, pixels; zero if absent),
            optional ``samples [B, S, 3, H, W]``.
        state: previous step's state (dict of ``[B, C, H, W]``) or None (= reset all).
        reset: bool ``[B]`` or None; True discards that item's history.

        Returns ``(output [B, 3, H, W] float32 linear HDR, state, extras)`` (with ``demodulate``
        the state's ``output`` and ``color`` hold irradiance, see the module docstring) where extras has
        ``"features"`` (list of U-Net maps, ``feature_channels`` wide, at the padded size
        divided by 2^level) and ``"weights"`` (dict of ``[B, k, H, W]``: ``history_in``,
        ``history_out``, ``valid`` with temporal recurrence; ``partition`` for the pyramid).
        """
        color = sanitize(frame["color"])
        albedo = demodulation_albedo(frame["albedo"]) if self.demodulate else None
        if albedo is not None:
            color = color / albedo  # irradiance; exact (color / 1) where there is no usable albedo
        h, w = color.shape[-2:]
        scale = color_scale(color)
        guide = guide_features(frame)
        # the transforms run in float32; a network converted to bfloat16/float16 weights (fast
        # CPU/GPU inference without autocast) gets its inputs in its own dtype
        net_dtype = self.embed.layers[0].weight.dtype
        graph = in_graph()  # traced or exported
        if graph and frame.get("samples") is None:
            # exported: the EmbedNet's first layer runs per input part (no concatenation), the
            # colour feature taken by the EmbedNet (inside its node in the f32 graph)
            net_in = self.embed([color, guide.to(net_dtype)], color_scale=scale)
        else:
            net_in = self.embed(self.embed_inputs(frame, color, scale, guide, albedo).to(net_dtype))
        history = None
        if self.temporal is not None:
            motion = frame.get("motion")
            if motion is None:  # no motion vectors: a static camera and scene
                motion = torch.zeros_like(color[:, :2])
            history = self.temporal.warp(state, motion, reset, like=color, guide=guide)
            # traced or exported: the U-Net's first convolution runs per part (no concatenation)
            if graph:
                parts = [net_in] + [p.to(net_in.dtype) for p in self.temporal.input_parts(history, scale)]
                net_in = [pad_to_multiple(p, self.multiple) for p in parts]
            else:
                net_in = torch.cat([net_in, self.temporal.inputs(history, scale).to(net_in.dtype)], dim=1)
        if isinstance(net_in, torch.Tensor):
            net_in = pad_to_multiple(net_in, self.multiple)
        heads, features = self.unet(net_in)
        # heads[0] may be factored (unet.FactoredHead, exported graphs): the pyramid filter reads it as is
        factored = getattr(self.filter, "reads_factored_head", False)
        filter_heads = [head_channels(heads[0], 0, self.filter_head0, factored)] + list(heads[1:])
        weights: dict[str, torch.Tensor] = {}
        filter_in = color
        if history is not None:
            temporal_head = head_channels(heads[0], self.filter_head0)[:, :, :h, :w]
            filter_in, weights["history_in"] = self.temporal.blend_in(color, history, temporal_head)
        log = self.filter_domain == "log"
        padded = pad_to_multiple(filter_in, self.multiple)
        filtered, filter_weights = self.filter(compress(padded, scale) if log else padded, filter_heads, scale)
        if log:
            filtered = expand(filtered, scale)
        weights.update({k: v[..., :h, :w] for k, v in filter_weights.items()})
        output = filtered[..., :h, :w]
        new_state: dict[str, torch.Tensor] = {}
        if history is not None:
            output, weights["history_out"] = self.temporal.blend_out(output, history, temporal_head)
            weights["valid"] = history["valid"]
            new_state = self.temporal.next_state(output, filter_in, temporal_head, guide)
        if albedo is not None:
            if self.remodulation_channels:
                logits = head_channels(heads[0], -self.remodulation_channels)[:, :, :h, :w]
                albedo = apply_kernels(albedo, logits, getattr(self.filter, "logit_scale", None))
                weights["remodulation"] = albedo
            output = output * albedo
        extras = {"features": features, "weights": weights}
        if self.training:
            extras["logit_energy"] = logit_energy(heads)
        return output, new_state, extras

    def forward(self, frames: dict, state: dict | None = None, reset: torch.Tensor | None = None,
                detach_every: int = 0):
        """Unroll :meth:`step` over a window (:func:`denoiser.recurrent.unroll`).

        frames: batch dict with ``[B, T, C, H, W]`` tensors (``samples [B, T, S, 3, H, W]``);
            other keys are ignored. reset: bool ``[B, T]``; None uses ``frames["reset"]`` if
            present (else only ``state is None`` resets). detach_every: k > 0 detaches the state
            before every k-th step (truncated BPTT).

        Returns ``(outputs [B, T, 3, H, W], final state, list of T extras dicts)``.
        """
        if reset is None:
            reset = frames.get("reset")
        outputs, state, extras = unroll(self.step, frames, NETWORK_INPUTS, state, reset, detach_every, detach_state)
        return torch.stack(outputs, dim=1), state, extras
