"""The operations of the OpenVINO extension (:mod:`denoiser.inference.ovext`), said once: their
schema and the helper that records one as a node of an exported graph.

* :data:`OPERATIONS`: the extension's operations (ONNX domain :data:`DOMAIN`): inputs and
  attributes. The export stubs (``torch.autograd.Function`` subclasses, each beside the code it
  records: :class:`~denoiser.nn.kernels.KernelApplyOp`, :class:`~denoiser.nn.pyramid.PyramidFilterOp`
  and :class:`~denoiser.nn.pyramid.PyramidFilterHeadOp`, :class:`~denoiser.nn.embed.EmbedNetOp`,
  :class:`~denoiser.nn.inputs.Log1pOp`, :class:`~denoiser.nn.inputs.ColorFeatureOp`,
  :class:`~denoiser.nn.inputs.GuideFeaturesOp`, :class:`~denoiser.nn.unet.FactoredHeadOp`,
  :class:`~denoiser.nn.temporal.ClampBlendOp`, :class:`~denoiser.nn.temporal.GuideGateOp`,
  :class:`~denoiser.nn.warp.WarpHistoryOp`) record their nodes through :func:`graph_node`, which
  checks them against it; ``tests/inference/test_ovext_schema.py`` checks the C++ source
  (``denoiser/inference/ovext/<name>.hpp``, the operation's name in snake case, and
  ``extension.cpp``) against it.
* When a graph holds these operations: :func:`denoiser.nn.graph_mode.kernels_as_op`.

Imports nothing of the package (the stubs' modules import it).
"""

from __future__ import annotations

from typing import NamedTuple

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


def scale_attributes(scale: float | None) -> dict:
    """A kernel filter's logit normalisation as attributes: ``scale`` (1 when off) and ``has_scale``."""
    return {"scale": 1.0 if scale is None else float(scale), "has_scale": int(scale is not None)}


__all__ = ["DOMAIN", "OPERATIONS", "Operation", "graph_node", "scale_attributes"]
