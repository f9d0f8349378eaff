"""Inference backends: how a network is prepared and stepped (PyTorch eager, channels-last,
autocast, ``torch.compile``, ONNX Runtime, OpenVINO f32/bf16; CUDA variants where a GPU is present).

A backend's ``prepare(net, example, threads)`` returns a :class:`~denoiser.runner.Stepper`, whose
``step(frame, state, reset) -> (output, state)`` the recurrent runner
(:mod:`denoiser.runner`) drives over a sequence. ``available()`` says why a backend cannot
run here (None when it can); ``dtype`` is the precision of its convolutions (``fp32``,
``bf16``, ``fp16``) for the tables. Backends are instantiated from ``conf/bench.yaml``'s ``backends``.
The CUDA backends with cast weights, the Triton filter and CUDA graphs are in :mod:`denoiser.inference.cuda_backend`.
"""

from __future__ import annotations

import contextlib
import copy
import sys
import tempfile
from collections.abc import Mapping
from pathlib import Path

import torch

from denoiser.runner import Stepper


class TorchBackend:
    """PyTorch eager ``Denoiser.step`` on ``device``.

    Args:
        label: backend name in tables.
        device: ``cpu`` or ``cuda``.
        channels_last: weights and inputs in NHWC memory format.
        autocast: None, ``bfloat16`` or ``float16`` (``torch.autocast``; filtering stays fp32).
    """

    def __init__(self, label: str = "eager fp32", device: str = "cpu", channels_last: bool = False,
                 autocast: str | None = None):
        self.label = label
        self.device = device
        self.channels_last = bool(channels_last)
        self.autocast = getattr(torch, autocast) if autocast else None
        self.dtype = {"bfloat16": "bf16", "float16": "fp16"}.get(autocast or "", "fp32")  # of the convolutions

    def available(self) -> str | None:
        """None when usable here, else the reason it is skipped."""
        if self.device.startswith("cuda") and not torch.cuda.is_available():
            return "no CUDA device"
        return None

    def _move(self, frame):
        fmt = torch.channels_last if self.channels_last else torch.contiguous_format
        return {k: v.to(self.device, non_blocking=True).contiguous(memory_format=fmt) for k, v in frame.items()}

    def _context(self):
        if self.autocast is None:
            return contextlib.nullcontext()
        return torch.autocast(device_type=torch.device(self.device).type, dtype=self.autocast)

    def prepare(self, net: torch.nn.Module, example: Mapping[str, torch.Tensor], threads: int) -> Stepper:
        net = copy.deepcopy(net).to(self.device).eval()  # .to() is in place: keep the caller's net as it is
        if self.channels_last:
            net = net.to(memory_format=torch.channels_last)
        inner = self.wrap(net)

        def step(frame, state):
            with torch.inference_mode(), self._context():
                out, new_state, _ = inner(self._move(frame), state)
            return out, new_state

        cuda = self.device.startswith("cuda")
        sync = torch.cuda.synchronize if cuda else (lambda: None)
        return Stepper(step, sync, threads=None if cuda else torch.get_num_threads, engine="torch")

    def wrap(self, net):
        """The callable ``(frame, state) -> (output, state, extras)`` to time."""
        return net.step


class CompileBackend(TorchBackend):
    """``torch.compile`` of ``Denoiser.step`` (inductor). ``mode``: e.g. ``reduce-overhead`` on
    CUDA (CUDA graphs). Compilation happens in the warm-up steps and is not timed."""

    def __init__(self, label: str = "torch.compile", device: str = "cpu", mode: str | None = None,
                 autocast: str | None = None):
        super().__init__(label, device, channels_last=False, autocast=autocast)
        self.mode = mode

    def wrap(self, net):
        return torch.compile(net.step, mode=self.mode, dynamic=False)


class _ExportedGraphBackend:
    """A backend running the exported ONNX step graph (:mod:`denoiser.inference.step_graph`): the export
    happens once per network (untimed) into a temporary directory."""

    label = "exported graph"
    dtype = "fp32"
    device = "cpu"
    matmul_heads = False  # export_onnx's choice of head operators (see there)
    fused_kernels = False  # export_onnx's operations of the OpenVINO extension (see there)

    def _export(self, net) -> str:
        from denoiser.inference.step_graph import export_onnx

        if not hasattr(self, "_exported"):
            self._exported: dict[int, tuple] = {}
            self._tmp = tempfile.TemporaryDirectory(prefix="denoiser-graph-")
        key = id(net)
        if key not in self._exported:
            path = Path(self._tmp.name) / f"net{len(self._exported)}.onnx"
            export_onnx(net, path, matmul_heads=self.matmul_heads, fused_kernels=self.fused_kernels)
            self._exported[key] = (net, str(path))  # the net is kept: its id stays unique
        return self._exported[key][1]


class OnnxRuntimeBackend(_ExportedGraphBackend):
    """The exported ONNX step graph (:mod:`denoiser.inference.step_graph`) in ONNX Runtime.

    ``provider``: an ONNX Runtime execution provider (``CPUExecutionProvider``,
    ``CUDAExecutionProvider``); the export happens once per network, untimed.
    """

    def __init__(self, label: str = "onnxruntime", provider: str = "CPUExecutionProvider"):
        self.label = label
        self.provider = provider
        self.device = "cuda" if provider.startswith("CUDA") else "cpu"

    def available(self) -> str | None:
        try:
            import onnx  # noqa: F401 - the export needs it
            import onnxruntime as ort
        except ImportError as exc:
            return f"{exc.name} is not installed"
        if self.provider not in ort.get_available_providers():
            return f"{self.provider} not available"
        return None

    def prepare(self, net, example, threads: int) -> Stepper:
        from denoiser.inference.step_graph import OnnxStep

        runner = OnnxStep(self._export(net), threads, providers=(self.provider,))
        options = runner.session.get_session_options()  # what the session was built with (0: ONNX Runtime's default)
        return Stepper(runner.step, threads=lambda: options.intra_op_num_threads, engine="onnxruntime")


class OpenVinoBackend(_ExportedGraphBackend):
    """The exported ONNX step graph compiled by OpenVINO (:class:`~denoiser.inference.step_graph.OpenVinoStep`).

    Args:
        label: backend name in tables.
        precision: ``f32`` or ``bf16`` (OpenVINO's ``INFERENCE_PRECISION_HINT``).
        device: OpenVINO device (``CPU``).
        profile: turn on OpenVINO's per-node performance counters, so the prepared
            :class:`Stepper` says where a step's time goes (``profile()``: ms per node type of
            the last step). The counters cost a little time: profile runs are not headline timings.

    The export happens once per network and the compilation once per frame size (in the
    warm-up step, untimed); the recurrent state is carried as graph inputs and outputs. In f32
    the U-Net's heads are exported as matrix products (``export_onnx(matmul_heads=True)``: a
    1x1 convolution's float32 output reaches a softmax over channels through a slow reference
    reorder in OpenVINO), in bf16 as 1x1 convolutions (docs/export.md). In both, the kernel
    filter is one ``denoiser::PyramidFilter`` node and the ``log1p`` transforms
    ``denoiser::Log1p`` nodes (``export_onnx(fused_kernels=True)``) when the project's OpenVINO
    extension builds (:mod:`denoiser.inference.ovext`), else the plain graph (one line on stderr says why).
    """

    def __init__(self, label: str = "openvino f32", precision: str = "f32", device: str = "CPU",
                 profile: bool = False):
        from denoiser.inference.step_graph import OPENVINO_PRECISIONS

        if precision not in OPENVINO_PRECISIONS:
            raise ValueError(f"precision: {precision!r} is not one of {', '.join(OPENVINO_PRECISIONS)}")
        self.label = label
        self.precision = precision
        self.dtype = {"f32": "fp32"}.get(precision, precision)
        self.ov_device = device
        self.device = device.lower()
        self.profile = bool(profile)
        self.matmul_heads = precision == "f32"
        self.fused_kernels = None  # decided on first use: the extension builds (denoiser.inference.ovext)

    def available(self) -> str | None:
        try:
            import onnx  # noqa: F401 - the export needs it
            import openvino as ov
        except ImportError as exc:
            return f"{exc.name} is not installed"
        core = ov.Core()
        if self.ov_device not in core.available_devices:
            return f"OpenVINO device {self.ov_device} not available"
        if self.precision == "bf16" and "BF16" not in core.get_property(self.ov_device, "OPTIMIZATION_CAPABILITIES"):
            return f"{self.ov_device} has no bf16 support (OpenVINO would run f32)"
        return None

    def prepare(self, net, example, threads: int) -> Stepper:
        from denoiser.inference import ovext
        from denoiser.inference.step_graph import OpenVinoStep

        if self.fused_kernels is None:
            self.fused_kernels = ovext.kernel_extension() is not None
            if not self.fused_kernels:
                print(f"{self.label}: plain kernel filter graph ({ovext.unavailable_reason()})", file=sys.stderr)
        runner = OpenVinoStep(self._export(net), threads, precision=self.precision, device=self.ov_device,
                              profile=self.profile)
        return Stepper(runner.step, profile=runner.last_profile if self.profile else None,
                       threads=runner.threads_in_use, engine="openvino")
