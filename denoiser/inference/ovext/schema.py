"""The operations of the OpenVINO extension as the exported graphs use them: ONNX domain
``denoiser``, each operation's inputs and attributes (name -> ONNX attribute type). Said once
here; ``tests/test_ovext_schema.py`` checks it against what :mod:`denoiser.nn` exports (the
``symbolic`` of its autograd stubs, read off exported graphs) and against the C++ source (each
header's ``OPENVINO_OP`` and ``visit_attributes``, ``extension.cpp``'s ONNX conversions).
"""

from __future__ import annotations

from typing import NamedTuple

#: the ONNX domain (and OpenVINO opset name) of every operation
DOMAIN = "denoiser"


class Operation(NamedTuple):
    """One operation: ``inputs`` (the count; None: variadic), ``attributes`` ``{name: type}`` with
    the ONNX attribute types ``FLOAT``, ``INT``, ``INTS``, ``STRING``, and ``header`` (its C++ file)."""

    inputs: int | None
    attributes: dict[str, str]
    header: str


OPERATIONS: dict[str, Operation] = {
    # x [B, C, H, W], logits [B, k*k, H, W] -> [B, C, H, W] (denoiser.nn.kernels.apply_kernels_graph)
    "KernelApply": Operation(2, {"scale": "FLOAT", "has_scale": "INT"}, "kernel_apply.hpp"),
    # x [B, 3, H, W], head_0 .. head_{L-1} -> [B, 3, H, W] (denoiser.nn.pyramid.PyramidFilter)
    "PyramidFilter": Operation(None, {"kernel_sizes": "INTS", "scale": "FLOAT", "has_scale": "INT"},
                               "pyramid_filter.hpp"),
    # x -> log1p(x) (denoiser.nn.inputs.log1p)
    "Log1p": Operation(1, {}, "log1p.hpp"),
    # a [B, C, H, W], z [B, C, h, w] -> a + interpolate(z, (H, W), mode) (denoiser.nn.unet.UNet)
    "AddUpsampled": Operation(2, {"mode": "STRING"}, "add_upsampled.hpp"),
}
