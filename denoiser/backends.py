"""Inference backends: how a network is prepared and stepped (PyTorch eager, channels-last,
autocast, ``torch.compile``, ONNX Runtime; CUDA variants where a GPU is present).

A backend's ``prepare(net, example, threads)`` returns a :class:`Stepper`, whose
``step(frame, state, reset) -> (output, state)`` the recurrent runner
(:mod:`denoiser.runner`) drives over a sequence. ``available()`` says why a backend cannot
run here (None when it can). Backends are instantiated from ``conf/bench.yaml``'s ``backends``.
"""

from __future__ import annotations

import contextlib
import copy
import tempfile
from collections.abc import Callable, Mapping
from pathlib import Path

import torch


class Stepper:
    """A prepared network: ``step(frame, state) -> (output, state)`` (the runner's contract,
    :mod:`denoiser.runner`: ``state=None`` starts a sequence); ``sync()`` waits for the device."""

    def __init__(self, step: Callable, sync: Callable[[], None] = lambda: None):
        self.step = step
        self.sync = sync


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

        sync = torch.cuda.synchronize if self.device.startswith("cuda") else (lambda: None)
        return Stepper(step, sync)

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


class OnnxRuntimeBackend:
    """The exported ONNX step graph (:mod:`denoiser.step_graph`) in ONNX Runtime.

    ``provider``: an ONNX Runtime execution provider (``CPUExecutionProvider``,
    ``CUDAExecutionProvider``); the export happens once per network, untimed.
    """

    def __init__(self, label: str = "onnxruntime", provider: str = "CPUExecutionProvider"):
        self.label = label
        self.provider = provider
        self.device = "cuda" if provider.startswith("CUDA") else "cpu"
        self._exported: dict[int, str] = {}
        self._tmp = tempfile.TemporaryDirectory(prefix="denoiser-bench-onnx-")

    def available(self) -> str | None:
        try:
            import onnxruntime as ort
        except ImportError:
            return "onnxruntime is not installed"
        if self.provider not in ort.get_available_providers():
            return f"{self.provider} not available"
        return None

    def prepare(self, net, example, threads: int) -> Stepper:
        from denoiser.step_graph import OnnxStep, export_onnx

        key = id(net)
        if key not in self._exported:
            path = Path(self._tmp.name) / f"net{len(self._exported)}.onnx"
            export_onnx(net, path)
            self._exported[key] = str(path)
        runner = OnnxStep(self._exported[key], threads, providers=(self.provider,))

        return Stepper(runner.step)
