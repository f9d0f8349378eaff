"""Input sanitising and the feature transforms that keep HDR range safe for half precision.

The network never sees raw radiance: every input is mapped to a bounded or logarithmic range
(docs/design.md §3.3), while the filter itself works on linear radiance. All transforms run in float32
(call them outside autocast, or they upcast themselves) and are elementwise or per-image
reductions, so they are cheap.

Formulas (``x`` a tensor, ``B`` the batch):

* sanitise: the project's one non-finite rule, :func:`denoiser.nonfinite.replace_tensor`: NaN -> 0,
  -Inf -> 0, +Inf -> ``POSINF = 65504``, on every input buffer (depth and motion included). The
  EXR reader applies the same rule, so a frame given to the network directly (or to its ONNX
  export) and the same frame read from a file denoise alike;
* color scale (per image): ``s = mean_{c,h,w}(max(color, 0)) + COLOR_EPS``, ``COLOR_EPS = 1e-3``;
* color feature: ``log1p(max(x, 0) / s)``, at most ``log1p(65504 / 1e-3) ~ 18`` for sanitised
  inputs: fine in float16 and bfloat16;
* albedo feature: ``log1p(clamp(albedo, 0, ALBEDO_MAX))`` with ``ALBEDO_MAX = 100`` (renderers
  exceed 1 on some paths; the log keeps such values within ~4.6);
* normal feature: ``clamp(normal, -1, 1)``;
* depth feature: ``d / (d + m)`` in [0, 1), where ``d = clamp(depth, 0, DEPTH_FAR)``,
  ``DEPTH_FAR = 1e10`` (no-hit pixels written as 1e10 map to ~1; +Inf becomes 65504 by the rule
  above, like in the reader, and counts as a far hit), and ``m`` is the mean depth of the image's
  hit pixels (``d < DEPTH_HIT``, ``DEPTH_HIT = 1e9``) plus ``DEPTH_EPS = 1e-6`` (``m = 1`` when
  nothing is hit). The feature is scale invariant: scenes in millimetres or kilometres look alike.
* demodulation albedo (only with ``Denoiser(demodulate=True)``): ``a = clamp(sanitise(albedo), 0,
  ALBEDO_MAX)``, then per channel ``a' = 1`` where ``a < DEMOD_MIN = 0.01``, else ``a``. The
  network filters ``color / a'`` and multiplies by ``a'`` afterwards, so pixels without a usable
  albedo (emitters, the sky, renderers writing 0, NaN) pass through unchanged, and albedo above 1
  (which renderers produce) is used as is up to ``ALBEDO_MAX``.
"""

from __future__ import annotations

import torch

from denoiser.nn.graph_mode import fused_kernels, matmul_heads
from denoiser.nn.graph_ops import graph_node
from denoiser.nonfinite import POSINF, replace_tensor

COLOR_EPS = 1e-3
ALBEDO_MAX = 100.0
DEMOD_MIN = 0.01
DEPTH_FAR = 1e10
DEPTH_HIT = 1e9
DEPTH_EPS = 1e-6

#: channels of :func:`guide_features`: albedo (3), normal (3), depth (1)
GUIDE_CHANNELS = 7


def sanitize(x: torch.Tensor) -> torch.Tensor:
    """NaN, -Inf -> 0 and +Inf -> ``POSINF`` (:mod:`denoiser.nonfinite`); returns float32. ``x``: any shape."""
    return replace_tensor(x)


def color_scale(color: torch.Tensor) -> torch.Tensor:
    """Per-image normalisation scale ``mean(max(color, 0)) + COLOR_EPS``.

    color: ``[B, 3, H, W]`` linear HDR (sanitised) -> ``[B, 1, 1, 1]`` float32, > 0.
    """
    return color.float().clamp_min(0).mean(dim=(1, 2, 3), keepdim=True) + COLOR_EPS


def color_feature(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """``log1p(max(x, 0) / scale)``.

    x: ``[B, ..., H, W]`` linear HDR; scale: ``[B, 1, 1, 1]`` (broadcast over extra dims of x
    by the caller) -> same shape as x, float32, >= 0.
    """
    return log1p(x.float().clamp_min(0) / scale)


def color_feature_part(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """:func:`color_feature` of an input part of the U-Net's first convolution: x ``[B, C, H,
    W]``, scale ``[B, 1, 1, 1]`` -> ``[B, C, H, W]`` float32. In the f32 graph with the fused
    operations (:func:`~denoiser.nn.graph_mode.matmul_heads` and
    :func:`~denoiser.nn.graph_mode.fused_kernels`) one ``denoiser::ColorFeature`` node that writes
    it channels-last, as the convolution reads it, permuted back here (no reorder between them)."""
    if fused_kernels() and matmul_heads():
        return ColorFeatureOp.apply(x, scale).permute(0, 3, 1, 2)
    return color_feature(x, scale)


def albedo_feature(albedo: torch.Tensor) -> torch.Tensor:
    """``log1p(clamp(albedo, 0, ALBEDO_MAX))``: ``[B, 3, H, W]`` -> ``[B, 3, H, W]``."""
    return log1p(albedo.float().clamp(0, ALBEDO_MAX))


def log1p(x: torch.Tensor) -> torch.Tensor:
    """``torch.log1p``; exported with the fused operations (:func:`~denoiser.nn.graph_mode.kernels_as_op`)
    as one ``denoiser::Log1p`` node of the OpenVINO extension (OpenVINO's own ``Log`` is a slow
    reference implementation on the CPU: 8-11 ms per 3-channel 1080p buffer on 2 threads)."""
    if fused_kernels():
        return Log1pOp.apply(x)
    return torch.log1p(x)


def demodulation_albedo(albedo: torch.Tensor) -> torch.Tensor:
    """Albedo to divide the color by: ``[B, 3, H, W]`` (any values) -> ``[B, 3, H, W]`` float32 in
    ``{1} U [DEMOD_MIN, ALBEDO_MAX]``: sanitised, clamped to ``[0, ALBEDO_MAX]``, and 1 per channel
    where below ``DEMOD_MIN`` (demodulation is then the identity there)."""
    a = sanitize(albedo).clamp(0, ALBEDO_MAX)
    return torch.where(a < DEMOD_MIN, torch.ones_like(a), a)


def normal_feature(normal: torch.Tensor) -> torch.Tensor:
    """``clamp(normal, -1, 1)``: ``[B, 3, H, W]`` camera-space normals -> same shape."""
    return normal.float().clamp(-1, 1)


def depth_feature(depth: torch.Tensor) -> torch.Tensor:
    """Bounded depth ``d / (d + mean hit depth)``.

    depth: ``[B, 1, H, W]`` planar depth (no hit = large) -> ``[B, 1, H, W]`` in [0, 1).
    """
    d = depth.float().clamp(0, DEPTH_FAR)
    return d / (d + depth_mean(d))


def depth_mean(d: torch.Tensor) -> torch.Tensor:
    """The mean depth of an image's hits (``d < DEPTH_HIT``; 1 without any) plus ``DEPTH_EPS``:
    d ``[B, 1, H, W]`` clamped to ``[0, DEPTH_FAR]`` -> ``[B, 1, 1, 1]``."""
    hit = (d < DEPTH_HIT).float()
    count = hit.sum(dim=(1, 2, 3), keepdim=True)
    mean = (d * hit).sum(dim=(1, 2, 3), keepdim=True) / count.clamp_min(1)
    return torch.where(count > 0, mean, torch.ones_like(mean)) + DEPTH_EPS


def guide_features(frame: dict) -> torch.Tensor:
    """Auxiliary-buffer features of one frame, ``[B, GUIDE_CHANNELS=7, H, W]``.

    frame: dict with ``albedo [B, 3, H, W]``, ``normal [B, 3, H, W]``, ``depth [B, 1, H, W]``
    (sanitised or not). Order: albedo feature, normal feature, depth feature.
    """
    if fused_kernels() and matmul_heads():  # the f32 graph: one denoiser::GuideFeatures node
        depth = sanitize(frame["depth"]).clamp(0, DEPTH_FAR)
        return GuideFeaturesOp.apply(frame["albedo"].float(), frame["normal"].float(), frame["depth"].float(),
                                     depth_mean(depth), ALBEDO_MAX, DEPTH_FAR, POSINF)
    return plain_guide_features(sanitize(frame["albedo"]), sanitize(frame["normal"]), sanitize(frame["depth"]))


def plain_guide_features(albedo: torch.Tensor, normal: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
    """:func:`guide_features` of sanitised buffers (``albedo``, ``normal`` ``[B, 3, H, W]``,
    ``depth`` ``[B, 1, H, W]``) -> ``[B, 7, H, W]``."""
    return torch.cat([albedo_feature(albedo), normal_feature(normal), depth_feature(depth)], dim=1)


# ----------------------------------------------------------------------------- export stubs


class ColorFeatureOp(torch.autograd.Function):
    """:func:`denoiser.nn.inputs.color_feature` of a U-Net input part recorded as one
    ``denoiser::ColorFeature`` node: forward(x ``[B, C, H, W]``, scale ``[B, 1, 1, 1]``) ->
    ``[B, H, W, C]`` float32 channels-last (the layout the U-Net's first convolution reads; the
    caller permutes it to ``[B, C, H, W]``)."""

    @staticmethod
    def forward(ctx, x, scale):
        return torch.log1p(x.float().clamp_min(0) / scale).permute(0, 2, 3, 1).contiguous()

    @staticmethod
    def symbolic(g, x, scale):
        out = graph_node(g, "ColorFeature", x, scale, like=x)
        sizes = x.type().varyingSizes()  # [B, C, H, W] (None where not known)
        if sizes is not None and len(sizes) == 4:
            out.setType(x.type().with_sizes([sizes[0], sizes[2], sizes[3], sizes[1]]))
        return out


class GuideFeaturesOp(torch.autograd.Function):
    """:func:`denoiser.nn.inputs.guide_features` recorded as one ``denoiser::GuideFeatures`` node:
    forward(albedo ``[B, 3, H, W]``, normal ``[B, 3, H, W]``, depth ``[B, 1, H, W]`` (as given:
    the node sanitises them), mean ``[B, 1, 1, 1]`` (:func:`~denoiser.nn.inputs.depth_mean`),
    albedo_max, depth_far, posinf) -> ``[B, 7, H, W]`` float32 (the value: the plain features)."""

    @staticmethod
    def forward(ctx, albedo, normal, depth, mean, albedo_max, depth_far, posinf):
        return plain_guide_features(*(sanitize(x) for x in (albedo, normal, depth)))

    @staticmethod
    def symbolic(g, albedo, normal, depth, mean, albedo_max, depth_far, posinf):
        out = graph_node(g, "GuideFeatures", albedo, normal, depth, mean, like=albedo, albedo_max=float(albedo_max),
                         depth_far=float(depth_far), posinf=float(posinf))
        sizes = albedo.type().varyingSizes()
        if sizes is not None and len(sizes) == 4:
            out.setType(albedo.type().with_sizes([sizes[0], 7, sizes[2], sizes[3]]))
        return out


class Log1pOp(torch.autograd.Function):
    """:func:`denoiser.nn.inputs.log1p` recorded as one ``denoiser::Log1p`` node (the value: ``torch.log1p``)."""

    @staticmethod
    def forward(ctx, x):
        return torch.log1p(x)

    @staticmethod
    def symbolic(g, x):
        return graph_node(g, "Log1p", x, like=x)
