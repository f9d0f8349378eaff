"""The networks' export hooks, in one place: when a graph is being recorded, the switches that
choose its form, the operations of the OpenVINO extension (their schema) and the autograd stubs
that record them. Eager training and inference never take these paths.

* :func:`in_graph`: ``net.step`` is being traced or exported (``torch.jit`` / ``torch.onnx``);
  the modules then record graph-friendly forms (slices instead of in-place loops, inputs split
  into parts instead of concatenated).
* :func:`kernels_as_op` / :func:`fused_kernels`: within the block, a recorded graph holds the
  kernel filters, the input transforms' ``log1p`` and (with matmul heads) the level-0 head's
  upsampled sum as single operations of the extension :mod:`denoiser.inference.ovext` (only an
  engine with it loaded runs such a graph); :func:`unfused` computes a fused node's value.
* :func:`heads_as_matmul` / :func:`matmul_heads`: within the block, the traced U-Net heads are
  matrix products (:func:`denoiser.nn.parts.pointwise_of_parts`) instead of 1x1 convolutions:
  faster in OpenVINO f32, slower in OpenVINO bf16 (there the convolution's bfloat16 output is
  reordered fast, and the ``MatMul`` runs in float32).
* :data:`OPERATIONS`: the extension's operations (ONNX domain :data:`DOMAIN`): inputs and
  attributes. Said once: the stubs record nodes through :func:`graph_node`, which checks them,
  and ``tests/test_ovext_schema.py`` checks the C++ source (``denoiser/inference/ovext/<name>.hpp``,
  the operation's name in snake case, and ``extension.cpp``) against it.
* The stubs (``torch.autograd.Function``): their value is the plain computation (the tracer
  records the node only); :class:`KernelApplyOp` (:func:`denoiser.nn.kernels.apply_kernels_graph`),
  :class:`EmbedNetOp` (:class:`denoiser.nn.embed.EmbedNet`, f32 graphs),
  :class:`PyramidFilterOp` (:class:`denoiser.nn.pyramid.PyramidFilter`), :class:`PyramidFilterHeadOp`
  (the same with head 0 as :class:`denoiser.nn.unet.FactoredHead`), :class:`Log1pOp`
  (:func:`denoiser.nn.inputs.log1p`), :class:`ColorFeatureOp`
  (:func:`denoiser.nn.inputs.color_feature_part`, f32 graphs), :class:`GuideFeaturesOp`
  (:func:`denoiser.nn.inputs.guide_features`, f32 graphs), :class:`FactoredHeadOp`
  (:meth:`denoiser.nn.unet.FactoredHead.tensor`, f32 graphs), :class:`ClampBlendOp`
  (:func:`denoiser.nn.temporal.clamp_blend`), :class:`GuideGateOp`
  (:meth:`denoiser.nn.temporal.TemporalRecurrence.gate`), :class:`WarpHistoryOp` (the sampling of
  :meth:`denoiser.nn.temporal.TemporalRecurrence.warp`).
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator
from typing import NamedTuple

import torch
import torch.nn.functional as F

#: the ONNX domain (and OpenVINO opset name) of the extension's operations
DOMAIN = "denoiser"


class Operation(NamedTuple):
    """One operation of the extension: ``inputs`` (the count; None: variadic) and ``attributes``
    ``{name: ONNX attribute type}`` (``FLOAT``, ``INT``, ``INTS``, ``STRING``)."""

    inputs: int | None
    attributes: dict[str, str]


OPERATIONS: dict[str, Operation] = {
    # x [B, C, H, W], logits [B, k*k, H, W] -> [B, C, H, W]
    "KernelApply": Operation(2, {"scale": "FLOAT", "has_scale": "INT"}),
    # x [B, 3, H, W], head_0 .. head_{L-1} -> [B, 3, H, W]
    "PyramidFilter": Operation(None, {"kernel_sizes": "INTS", "scale": "FLOAT", "has_scale": "INT"}),
    # x [B, 3, H, W], skip [B, H, W, C_s] (channels-last), weight [L + k0^2, C_s], z [B, L + k0^2, h, w],
    # head_1 .. head_{L-1} -> [B, 3, H, W]: PyramidFilter with head 0 = weight @ skip + up(z)
    "PyramidFilterHead": Operation(None, {"kernel_sizes": "INTS", "scale": "FLOAT", "has_scale": "INT",
                                          "mode": "STRING"}),
    # w0 [M, C], b0 [M], w1 [M, M], b1 [M], w2 [N, M], b2 [N], parts [B, C_i, H, W] -> [B, H, W, N]
    # (channels-last): EmbedNet's three 1x1 layers per pixel; with scale [B, 1, 1, 1] after b2 and
    # color_channels > 0, the first color_channels input channels are linear colour, their
    # log1p(max(x, 0) / scale) taken in the node
    "EmbedNet": Operation(None, {"negative_slope": "FLOAT", "color_channels": "INT"}),
    # x -> log1p(x)
    "Log1p": Operation(1, {}),
    # x [B, C, H, W], scale [B, 1, 1, 1] -> log1p(max(x, 0) / scale) as [B, H, W, C] (channels-last)
    "ColorFeature": Operation(2, {}),
    # albedo [B, 3, H, W], normal [B, 3, H, W], depth [B, 1, H, W], mean [B, 1, 1, 1] -> [B, 7, H, W]
    "GuideFeatures": Operation(4, {"albedo_max": "FLOAT", "depth_far": "FLOAT", "posinf": "FLOAT"}),
    # skip [B, H, W, C_s] (channels-last), weight [C, C_s], z [B, C, h, w] -> [B, C, H, W]:
    # weight @ skip + interpolate(z, (H, W), mode)
    "FactoredHead": Operation(3, {"mode": "STRING"}),
    # base [B, C, H, W], previous [B, C, H, W], weight [B, 1, H, W] -> [B, C, H, W]
    "ClampBlend": Operation(3, {"k": "FLOAT"}),
    # previous [B, H, W, 7] (previous_channels_last 1) or [B, 7, H, W], current [B, 7, H, W] -> [B, 1, H, W]
    "GuideGate": Operation(2, {"threshold": "FLOAT", "previous_channels_last": "INT"}),
    # motion [B, 2, H, W], keep [B, 1, 1, 1], buffer_0 [B, C_0, H, W], ... -> buffer_i warped [B, C_i, H, W]
    # or [B, H, W, C_i] where channels_last[i] is 1 (coverage-normalised), ..., valid [B, 1, H, W]: one
    # output per buffer, then valid
    "WarpHistory": Operation(None, {"motion_limit": "FLOAT", "posinf": "FLOAT", "outside": "FLOAT",
                                    "cover_min": "FLOAT", "channels_last": "INTS"}),
}
#: the suffix torch.onnx's ``g.op`` takes for each attribute type
_SUFFIX = {"FLOAT": "f", "INT": "i", "INTS": "i", "STRING": "s"}


def in_graph() -> bool:
    """Whether a graph is being recorded: traced (``torch.jit``) or exported (``torch.onnx``)."""
    return torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()


_KERNEL_OP = contextvars.ContextVar("kernel_op", default=False)
_MATMUL_HEADS = contextvars.ContextVar("matmul_heads", default=False)


@contextlib.contextmanager
def kernels_as_op(enabled: bool = True) -> Iterator[None]:
    """Within the block, a recorded graph holds the extension's operations (:data:`OPERATIONS`):
    :func:`denoiser.nn.kernels.apply_kernels_graph` as one ``denoiser::KernelApply`` node instead
    of slices, a softmax and k*k multiply-adds, a :class:`~denoiser.nn.pyramid.PyramidFilter` as
    one ``denoiser::PyramidFilter``, :func:`denoiser.nn.inputs.log1p` as one ``denoiser::Log1p``
    and, with :func:`heads_as_matmul`, the level-0 head from its factors as one
    ``denoiser::PyramidFilterHead`` (the filter's channels) and ``denoiser::FactoredHead`` (the
    others), and the f32 graph's input transforms and embedding as their operations."""
    token = _KERNEL_OP.set(bool(enabled))
    try:
        yield
    finally:
        _KERNEL_OP.reset(token)


def fused_kernels() -> bool:
    """Whether a graph being recorded holds the extension's operations (:func:`kernels_as_op`)."""
    return _KERNEL_OP.get() and in_graph()


def unfused(fn, *args):
    """``fn(*args)`` with :func:`kernels_as_op` off (the plain computation of a fused node)."""
    token = _KERNEL_OP.set(False)
    try:
        return fn(*args)
    finally:
        _KERNEL_OP.reset(token)


def untraced(fn, *args):
    """``fn(*args)`` with the tracer off: a stub's plain value whose ops (3x3 slices with sizes read
    from traced shapes) the tracer would record inside the node's block, a record the ONNX
    exporter's passes cannot take."""
    state = torch._C._get_tracing_state()
    torch._C._set_tracing_state(None)
    try:
        return fn(*args)
    finally:
        torch._C._set_tracing_state(state)


@contextlib.contextmanager
def heads_as_matmul(enabled: bool = True) -> Iterator[None]:
    """Within the block, traced U-Net heads are matrix products (:func:`denoiser.nn.parts.pointwise_of_parts`)
    instead of 1x1 convolutions (see the module docstring)."""
    token = _MATMUL_HEADS.set(bool(enabled))
    try:
        yield
    finally:
        _MATMUL_HEADS.reset(token)


def matmul_heads() -> bool:
    """Whether a graph being traced runs the U-Net's heads as :func:`denoiser.nn.parts.pointwise_of_parts`."""
    return _MATMUL_HEADS.get()


def graph_node(g, name: str, *inputs, like, outputs: int = 1, **attributes):
    """One node of the extension's operation ``name`` in the graph ``g`` (a ``symbolic``'s first
    argument), with the type of ``like`` (its first output's, with ``outputs`` > 1: a tuple of
    outputs, their types the caller's to set); the inputs and attributes must be :data:`OPERATIONS`'."""
    op = OPERATIONS[name]
    if op.inputs is not None and len(inputs) != op.inputs:
        raise ValueError(f"{DOMAIN}::{name}: {len(inputs)} inputs, the schema has {op.inputs}")
    if set(attributes) != set(op.attributes):
        raise ValueError(f"{DOMAIN}::{name}: attributes {sorted(attributes)}, the schema has {sorted(op.attributes)}")
    typed = {f"{key}_{_SUFFIX[op.attributes[key]]}": value for key, value in attributes.items()}
    if outputs > 1:
        return g.op(f"{DOMAIN}::{name}", *inputs, outputs=outputs, **typed)
    out = g.op(f"{DOMAIN}::{name}", *inputs, **typed)
    out.setType(like.type())
    return out


def _scale_attributes(scale: float | None) -> dict:
    """A kernel filter's logit normalisation as attributes: ``scale`` (1 when off) and ``has_scale``."""
    return {"scale": 1.0 if scale is None else float(scale), "has_scale": int(scale is not None)}


class KernelApplyOp(torch.autograd.Function):
    """:func:`denoiser.nn.kernels.apply_kernels_graph` recorded as one ``denoiser::KernelApply`` node.

    forward(x ``[B, C, H, W]`` float32, logits ``[B, k*k, H, W]`` float32, scale float or None)
    -> ``[B, C, H, W]`` float32, computed by the plain graph.
    """

    @staticmethod
    def forward(ctx, x, logits, scale):
        from denoiser.nn.kernels import apply_kernels_graph

        return unfused(apply_kernels_graph, x, logits, scale)

    @staticmethod
    def symbolic(g, x, logits, scale):
        return graph_node(g, "KernelApply", x, logits, like=x, **_scale_attributes(scale))


class PyramidFilterOp(torch.autograd.Function):
    """:meth:`denoiser.nn.pyramid.PyramidFilter.forward` recorded as one ``denoiser::PyramidFilter``
    node (inputs x and the L heads; attributes ``kernel_sizes``, ``scale``, ``has_scale``)."""

    @staticmethod
    def forward(ctx, x, kernel_sizes, scale, *heads):
        from denoiser.nn.pyramid import pyramid_filter

        return unfused(pyramid_filter, x, heads, kernel_sizes, scale)[0]

    @staticmethod
    def symbolic(g, x, kernel_sizes, scale, *heads):
        return graph_node(g, "PyramidFilter", x, *heads, like=x, kernel_sizes=list(kernel_sizes),
                          **_scale_attributes(scale))


class PyramidFilterHeadOp(torch.autograd.Function):
    """:meth:`denoiser.nn.pyramid.PyramidFilter.forward` with head 0 given by its factors
    (:class:`denoiser.nn.unet.FactoredHead`), recorded as one ``denoiser::PyramidFilterHead`` node:
    head 0 is ``weight @ skip + interpolate(z, (H, W), mode)``, computed row by row where the
    filter reads it instead of written at full resolution.

    forward(x ``[B, 3, H, W]``, skip ``[B, H, W, C_s]`` channels-last, weight ``[L + k0^2, C_s]``,
    z ``[B, L + k0^2, h, w]``, kernel_sizes, scale, mode, align, head_1 .. head_{L-1})
    -> ``[B, 3, H, W]`` float32, computed by the plain graph.
    """

    @staticmethod
    def forward(ctx, x, skip, weight, z, kernel_sizes, scale, mode, align, *heads):
        from denoiser.nn.parts import pointwise
        from denoiser.nn.pyramid import pyramid_filter

        head0 = pointwise(weight, None, skip.permute(0, 3, 1, 2)) + F.interpolate(
            z, size=x.shape[-2:], mode=mode, align_corners=align)
        return unfused(pyramid_filter, x, (head0, *heads), kernel_sizes, scale)[0]

    @staticmethod
    def symbolic(g, x, skip, weight, z, kernel_sizes, scale, mode, align, *heads):
        return graph_node(g, "PyramidFilterHead", x, skip, weight, z, *heads, like=x,
                          kernel_sizes=list(kernel_sizes), mode=mode, **_scale_attributes(scale))


class EmbedNetOp(torch.autograd.Function):
    """:class:`denoiser.nn.embed.EmbedNet`'s per-pixel path on a list of input parts, recorded as one
    ``denoiser::EmbedNet`` node (attributes ``negative_slope``, ``color_channels``): the three 1x1
    layers per pixel, the hidden values never written at full resolution.

    forward(negative_slope, color_channels, w0 ``[M, C]``, b0 ``[M]``, w1 ``[M, M]``, b1, w2 ``[N,
    M]``, b2 ``[N]``, scale ``[B, 1, 1, 1]``, *parts ``[B, C_i, H, W]`` with ``sum C_i == C``) ->
    ``[B, H, W, N]`` float32, channels-last (the layout the U-Net's first convolution reads; the
    caller permutes it to ``[B, N, H, W]``). The first ``color_channels`` input channels are
    linear colour: the node takes their :func:`denoiser.nn.inputs.color_feature` with ``scale``
    first (0: none, ``scale`` unread).
    """

    @staticmethod
    def forward(ctx, negative_slope, color_channels, w0, b0, w1, b1, w2, b2, scale, *parts):
        x = torch.cat(parts, 1)
        if color_channels:
            x = torch.cat([torch.log1p(x[:, :color_channels].clamp_min(0) / scale), x[:, color_channels:]], 1)
        x = x.permute(0, 2, 3, 1)
        for w, b in ((w0, b0), (w1, b1), (w2, b2)):
            x = F.leaky_relu(x @ w.t() + b, negative_slope)
        return x.contiguous()

    @staticmethod
    def symbolic(g, negative_slope, color_channels, w0, b0, w1, b1, w2, b2, scale, *parts):
        out = graph_node(g, "EmbedNet", w0, b0, w1, b1, w2, b2, scale, *parts, like=parts[0],
                         negative_slope=float(negative_slope), color_channels=int(color_channels))
        sizes = parts[0].type().varyingSizes()  # [B, H, W, N] (None where not known)
        n = w2.type().varyingSizes()
        if sizes is not None and len(sizes) == 4 and n is not None:
            out.setType(parts[0].type().with_sizes([sizes[0], sizes[2], sizes[3], n[0]]))
        return out


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
        from denoiser.nn import inputs  # a late import: that module imports this one

        return inputs.plain_guide_features(*(inputs.sanitize(x) for x in (albedo, normal, depth)))

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


class FactoredHeadOp(torch.autograd.Function):
    """:meth:`denoiser.nn.unet.FactoredHead.tensor` recorded as one ``denoiser::FactoredHead`` node
    (attribute ``mode``): forward(skip ``[B, H, W, C_s]`` channels-last, weight ``[C, C_s]``, z
    ``[B, C, h, w]``, mode, align) -> ``[B, C, H, W]`` float32, ``weight @ skip +
    interpolate(z)`` (the value: the plain computation)."""

    @staticmethod
    def forward(ctx, skip, weight, z, mode, align):
        from denoiser.nn.parts import pointwise

        a = pointwise(weight, None, skip.permute(0, 3, 1, 2))
        return a + F.interpolate(z, size=a.shape[-2:], mode=mode, align_corners=align)

    @staticmethod
    def symbolic(g, skip, weight, z, mode, align):
        out = graph_node(g, "FactoredHead", skip, weight, z, like=z, mode=mode)
        s, zs = skip.type().varyingSizes(), z.type().varyingSizes()  # [B, H, W, C_s], [B, C, h, w]
        if s is not None and zs is not None and len(s) == 4 and len(zs) == 4:
            out.setType(z.type().with_sizes([s[0], zs[1], s[1], s[2]]))
        return out


class ClampBlendOp(torch.autograd.Function):
    """:func:`denoiser.nn.temporal.clamp_blend` recorded as one ``denoiser::ClampBlend`` node
    (attribute ``k``); the value is the plain computation.

    forward(base ``[B, C, H, W]``, previous ``[B, C, H, W]``, weight ``[B, 1, H, W]``, k float)
    -> ``[B, C, H, W]`` float32.
    """

    @staticmethod
    def forward(ctx, base, previous, weight, k):
        from denoiser.nn.temporal import clamp_blend

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
        from denoiser.nn.temporal import guide_disagreement

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


class WarpHistoryOp(torch.autograd.Function):
    """The sampling of :meth:`denoiser.nn.temporal.TemporalRecurrence.warp` (before its gate)
    recorded as one ``denoiser::WarpHistory`` node (attributes ``motion_limit``, ``posinf``,
    ``outside``, ``cover_min``, ``channels_last``): the sample positions, bilinear weights and
    coverage computed once for every buffer; the value is the plain computation.

    forward(motion ``[B, 2, H, W]``, keep bool ``[B, 1, 1, 1]``, cover_min float, channels_last
    tuple of bools (one per buffer), buffer_0 ``[B, C_0, H, W]``, ...) -> (each buffer warped and
    divided by the coverage where it exceeds cover_min, else 0, float32, ``[B, C_i, H, W]``, or
    ``[B, H, W, C_i]`` (contiguous) where channels_last[i] (the layout of a convolution's input:
    the graph's permute back to ``[B, C_i, H, W]`` then moves nothing), ..., valid ``[B, 1, H,
    W]``: the coverage there, else 0).
    """

    @staticmethod
    def forward(ctx, motion, keep, cover_min, channels_last, *buffers):
        from denoiser.nn.warp import warp_all

        def plain():
            warped, cover = warp_all(buffers, motion, keep)
            ok = cover > cover_min
            safe = cover.clamp_min(cover_min)
            values = (torch.where(ok, v / safe, 0.0) for v in warped)
            return (*(v.permute(0, 2, 3, 1).contiguous() if last else v for v, last in zip(values, channels_last)),
                    torch.where(ok, cover, 0.0))

        return untraced(plain)

    @staticmethod
    def symbolic(g, motion, keep, cover_min, channels_last, *buffers):
        from denoiser.nn.warp import MOTION_LIMIT, OUTSIDE
        from denoiser.nonfinite import POSINF

        keep_f = g.op("Cast", keep, to_i=1)  # float32: 1 keep, 0 discard
        outs = graph_node(g, "WarpHistory", motion, keep_f, *buffers, like=motion, outputs=len(buffers) + 1,
                          motion_limit=float(MOTION_LIMIT), posinf=float(POSINF), outside=float(OUTSIDE),
                          cover_min=float(cover_min), channels_last=[int(bool(c)) for c in channels_last])
        sizes = motion.type().varyingSizes()  # [B, C_i, H, W] (None where not known)
        for out, like, last in zip(outs, [*buffers, None], [*channels_last, False]):
            channels = like.type().varyingSizes()[1] if like is not None and like.type().varyingSizes() else 1
            if sizes is not None and len(sizes) == 4:
                shape = [sizes[0], sizes[2], sizes[3], channels] if last else [sizes[0], channels, sizes[2], sizes[3]]
                out.setType(motion.type().with_sizes(shape))
            else:
                out.setType(motion.type())
        return outs


__all__ = ["DOMAIN", "OPERATIONS", "ClampBlendOp", "ColorFeatureOp", "EmbedNetOp", "FactoredHeadOp", "GuideFeaturesOp", "GuideGateOp", "KernelApplyOp", "Log1pOp", "Operation", "PyramidFilterHeadOp", "PyramidFilterOp", "WarpHistoryOp",
           "fused_kernels", "graph_node", "heads_as_matmul", "in_graph", "kernels_as_op", "matmul_heads", "unfused",
           "untraced"]
