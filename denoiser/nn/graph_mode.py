"""Whether and how a graph of a network is being recorded: the switches the ``nn`` modules read
to choose a recorded graph's form (eager training and inference never take these paths).
Imports torch only, so every ``nn`` module may import it.

* :func:`in_graph`: ``net.step`` is being traced or exported (``torch.jit`` / ``torch.onnx``);
  the modules then record graph-friendly forms (slices instead of in-place loops, inputs split
  into parts instead of concatenated).
* :func:`kernels_as_op` / :func:`fused_kernels`: within the block, a recorded graph holds the
  kernel filters, the input transforms' ``log1p`` and (with matmul heads) the level-0 head's
  upsampled sum as single operations of the extension :mod:`denoiser.inference.ovext` (their
  schema: :mod:`denoiser.nn.graph_ops`; each stub that records one stands beside the code it
  records); :func:`unfused` computes a fused node's value, :func:`untraced` with the tracer off.
* :func:`heads_as_matmul` / :func:`matmul_heads`: within the block, the traced U-Net heads are
  matrix products (:func:`denoiser.nn.parts.pointwise_of_parts`) instead of 1x1 convolutions:
  faster in OpenVINO f32, slower in OpenVINO bf16 (there the convolution's bfloat16 output is
  reordered fast, and the ``MatMul`` runs in float32).
"""

from __future__ import annotations

import contextlib
import contextvars
from collections.abc import Iterator

import torch


def in_graph() -> bool:
    """Whether a graph is being recorded: traced (``torch.jit``) or exported (``torch.onnx``)."""
    return torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()


_KERNEL_OP = contextvars.ContextVar("kernel_op", default=False)
_MATMUL_HEADS = contextvars.ContextVar("matmul_heads", default=False)


@contextlib.contextmanager
def _switched(var: contextvars.ContextVar, value: bool) -> Iterator[None]:
    """``var`` set to ``value`` within the block, its earlier value back after it."""
    token = var.set(value)
    try:
        yield
    finally:
        var.reset(token)


@contextlib.contextmanager
def kernels_as_op(enabled: bool = True) -> Iterator[None]:
    """Within the block, a recorded graph holds the extension's operations (:data:`denoiser.nn.graph_ops.OPERATIONS`):
    :func:`denoiser.nn.kernels.apply_kernels_graph` as one ``denoiser::KernelApply`` node instead
    of slices, a softmax and k*k multiply-adds, a :class:`~denoiser.nn.pyramid.PyramidFilter` as
    one ``denoiser::PyramidFilter``, :func:`denoiser.nn.inputs.log1p` as one ``denoiser::Log1p``
    and, with :func:`heads_as_matmul`, the level-0 head from its factors as one
    ``denoiser::PyramidFilterHead`` (the filter's channels) and ``denoiser::FactoredHead`` (the
    others), and the f32 graph's input transforms and embedding as their operations."""
    with _switched(_KERNEL_OP, bool(enabled)):
        yield


def fused_kernels() -> bool:
    """Whether a graph being recorded holds the extension's operations (:func:`kernels_as_op`)."""
    return _KERNEL_OP.get() and in_graph()


def unfused(fn, *args):
    """``fn(*args)`` with :func:`kernels_as_op` off (the plain computation of a fused node)."""
    with _switched(_KERNEL_OP, False):
        return fn(*args)


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
    with _switched(_MATMUL_HEADS, bool(enabled)):
        yield


def matmul_heads() -> bool:
    """Whether a graph being traced runs the U-Net's heads as :func:`denoiser.nn.parts.pointwise_of_parts`."""
    return _MATMUL_HEADS.get()
