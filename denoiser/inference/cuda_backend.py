"""CUDA inference backends (``conf/bench.yaml``: ``cuda``, ``cuda_compiled``; ``denoiser-denoise
backend=cuda|cuda_compiled``), and the CUDA-event timer that times them.

:class:`CudaBackend` (eager): the network's weights cast once to ``precision`` (``fp16``,
``bf16`` or ``fp32``; no autocast, so no per-step weight casts; the Denoiser feeds its U-Net in
the weights' dtype and filters in float32, :mod:`denoiser.nn.denoiser`), weights in channels-last
memory format, and the pyramid filter run by the Triton kernels of :mod:`denoiser.inference.triton_filter`
where Triton and CUDA are present (``triton_filter: auto``). The recurrent state stays on the
device from frame to frame (the runner carries the step's own state tensors) and a step never
waits for the device: frames already on the device are used in place, the output is not copied
back.

:class:`CudaGraphBackend` (compiled): the same network, optionally ``torch.compile``-d (inductor,
no CUDA graphs of its own), stepped through static buffers, one set per frame size
(:class:`StaticStep`): the frame is copied into static input buffers, the recurrent state lives
in static state buffers that the step overwrites with its new state, and a reset is a static
flag (``reset=True`` makes the network ignore the state buffers: ``Denoiser.step`` with a reset
reads nothing from them, the same numbers as ``state=None``). So every step of a frame size runs
the same kernels on the same addresses, and on CUDA the whole step is captured once into a
``torch.cuda.CUDAGraph`` (after ``warmup`` untimed runs on a side stream, which also compile) and
replayed: one launch per frame. The output is returned as a copy (the graph's own output buffer is
overwritten by the next replay). On the CPU (``device=cpu``, ``graph=False``) the same static
buffers and copy-in run without a graph, which is how the tests check the semantics.

:func:`cuda_event_times` times steps with CUDA events (device time between the step's first and
last kernel, no host round trip inside); :func:`device_report` names the GPU, driver, torch and
CUDA versions. (They live here rather than in :mod:`denoiser.measure` while that module is being
reworked; they use its :class:`~denoiser.recurrent.RecurrentRunner` contract and :func:`~denoiser.measure.summarize`.)
"""

from __future__ import annotations

import copy
from collections.abc import Mapping

import torch

from denoiser.errors import ConfigError
from denoiser.recurrent import RecurrentRunner, Stepper

#: ``precision=`` -> weight dtype
PRECISIONS = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
TRITON_FILTER = ("auto", True, False)


class CudaBackend:
    """Eager ``Denoiser.step`` with cast weights on a CUDA device (module docstring).

    Args:
        label: backend name in tables.
        precision: ``fp16``, ``bf16`` or ``fp32``: the weights' dtype (cast once in ``prepare``).
        device: ``cuda`` (default), ``cuda:N``, or ``cpu`` (tests: the same logic without a GPU).
        channels_last: weights (so the convolutions' outputs) in NHWC memory format.
        triton_filter: ``auto`` (the Triton pyramid filter when it can run on ``device``),
            true (required), false (the torch filter).
        cudnn_benchmark: let cuDNN pick the fastest convolution algorithms per shape
            (``torch.backends.cudnn.benchmark``, process-wide; the first step of a size tries them).
    """

    def __init__(self, label: str = "cuda fp16", precision: str = "fp16", device: str = "cuda",
                 channels_last: bool = True, triton_filter: str | bool = "auto", cudnn_benchmark: bool = True):
        if precision not in PRECISIONS:
            raise ConfigError(f"precision: {precision!r} is not one of {', '.join(PRECISIONS)}")
        if triton_filter not in TRITON_FILTER:
            raise ConfigError(f"triton_filter: {triton_filter!r} is not auto, true or false")
        self.label = label
        self.precision = precision
        self.dtype = precision  # for the tables
        self.device = str(device)
        self.channels_last = bool(channels_last)
        self.triton_filter = triton_filter
        self.cudnn_benchmark = bool(cudnn_benchmark)

    def _cuda(self) -> bool:
        return torch.device(self.device).type == "cuda"

    def available(self) -> str | None:
        """None when usable here, else the reason it is skipped."""
        if self._cuda():
            if not torch.cuda.is_available():
                return "no CUDA device"
            if self.precision == "bf16" and not torch.cuda.is_bf16_supported():
                return "this GPU has no bf16"
        if self.triton_filter is True:
            from denoiser.inference.triton_filter import unavailable_reason

            return unavailable_reason(self.device)
        return None

    def uses_triton(self) -> bool:
        """Whether ``prepare`` puts the Triton pyramid filter in (``triton_filter``)."""
        if self.triton_filter is False:
            return False
        from denoiser.inference.triton_filter import unavailable_reason

        # auto: on CUDA only (the CPU interpreter is for tests, far too slow to time)
        return unavailable_reason(self.device) is None and (self.triton_filter is True or self._cuda())

    def prepare_net(self, net: torch.nn.Module) -> torch.nn.Module:
        """A copy of ``net`` (the caller's is untouched) in eval mode on ``device`` with weights
        in ``precision`` and, when set, channels-last and the Triton filter."""
        net = copy.deepcopy(net).eval().to(device=self.device, dtype=PRECISIONS[self.precision])
        if self.channels_last:
            net = net.to(memory_format=torch.channels_last)
        if self.uses_triton():
            from denoiser.inference.triton_filter import use_triton_filter

            use_triton_filter(net)
        if self._cuda() and self.cudnn_benchmark:
            torch.backends.cudnn.benchmark = True
        return net

    def _sync(self):
        return (lambda: torch.cuda.synchronize(self.device)) if self._cuda() else (lambda: None)

    def prepare(self, net: torch.nn.Module, example: Mapping[str, torch.Tensor] | None, threads: int) -> Stepper:
        """A :class:`~denoiser.recurrent.Stepper` of ``net``: ``step(frame {buffer: [B, C, H, W]},
        state) -> (output [B, 3, H, W] float32 on the device, state)``."""
        net = self.prepare_net(net)

        def step(frame, state):
            with torch.inference_mode():
                inputs = {k: v.to(self.device, non_blocking=True) for k, v in frame.items()}
                out, new_state, _ = net.step(inputs, state)
            return out, new_state

        return Stepper(step, self._sync(), engine="torch")


class StaticStep:
    """``step(frame, state) -> (output, state)`` over static buffers, one set per frame size
    (``slots``; module docstring).

    Args:
        net: the prepared :class:`~denoiser.nn.denoiser.Denoiser`.
        fn: the callable run on the buffers, ``fn(frame, state, reset) -> (output, state, extras)``
            (``net.step`` or its ``torch.compile``).
        device: where the buffers live.
        graph: capture each frame size's step into a CUDA graph and replay it (CUDA only).
        warmup: untimed runs before the capture (compilation, cuDNN's algorithm search).
    """

    def __init__(self, net: torch.nn.Module, fn, device: str, graph: bool, warmup: int = 3):
        self.net = net
        self.fn = fn
        self.device = torch.device(device)
        self.graph = bool(graph)
        self.warmup = int(warmup)
        #: ``{frame signature: _Slot}``: one set of buffers (and graph) per frame size
        self.slots: dict[tuple, _Slot] = {}

    def step(self, frame: Mapping[str, torch.Tensor], state: dict | None):
        """frame ``{buffer: [B, C, H, W]}`` (any device; copied in) and the previous step's
        state or None (reset) -> ``(output [B, 3, H, W] float32, a copy, on the device; state)``;
        the returned state is the slot's own state buffers (pass it back unchanged)."""
        with torch.inference_mode():
            key = tuple(sorted((k, tuple(v.shape)) for k, v in frame.items()))
            slot = self.slots.get(key)
            if slot is None:
                slot = self.slots[key] = _Slot(self, frame)
            return slot.step(frame, state).clone(), slot.state


class _Slot:
    """The static buffers (and CUDA graph) of one frame size of a :class:`StaticStep`."""

    def __init__(self, owner: StaticStep, frame: Mapping[str, torch.Tensor]):
        self.owner = owner
        dev = owner.device
        self.inputs = {k: torch.empty(v.shape, dtype=v.dtype, device=dev) for k, v in frame.items()}
        for k, v in frame.items():
            self.inputs[k].copy_(v)
        temporal = getattr(owner.net, "temporal", None)
        self.state: dict[str, torch.Tensor] = temporal.zero_state(self.inputs["color"]) if temporal else {}
        self.reset = torch.ones(self.inputs["color"].shape[0], dtype=torch.bool, device=dev)
        self.reset_value = True
        self.graph = None
        self.output: torch.Tensor | None = None
        if owner.graph:
            side = torch.cuda.Stream(dev)
            side.wait_stream(torch.cuda.current_stream(dev))
            with torch.cuda.stream(side):
                for _ in range(owner.warmup):
                    self.run()
            torch.cuda.current_stream(dev).wait_stream(side)
            self.graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(self.graph):
                self.output = self.run()

    def run(self) -> torch.Tensor:
        """One step on the buffers: the new state is written over the state buffers after the
        network has read them (stream order); returns the output ``[B, 3, H, W]``."""
        out, new_state, _ = self.owner.fn(self.inputs, self.state, self.reset)
        for k, buf in self.state.items():
            buf.copy_(new_state[k])
        return out

    def step(self, frame: Mapping[str, torch.Tensor], state: dict | None) -> torch.Tensor:
        for k, v in frame.items():
            if v.data_ptr() != self.inputs[k].data_ptr():
                self.inputs[k].copy_(v, non_blocking=True)
        reset = state is None
        if not reset and state is not self.state:  # a state from elsewhere: take its values
            for k, buf in self.state.items():
                buf.copy_(state[k], non_blocking=True)
        if reset != self.reset_value:  # a host-side flag: no device read, no sync
            self.reset.fill_(reset)
            self.reset_value = reset
        if self.graph is not None:
            self.graph.replay()
            return self.output
        return self.run()


class CudaGraphBackend(CudaBackend):
    """:class:`CudaBackend` stepped through static buffers (:class:`StaticStep`), compiled by
    ``torch.compile`` and replayed as one CUDA graph per frame size (module docstring).

    Args (besides :class:`CudaBackend`'s):
        compile: ``torch.compile`` the step (``mode``: inductor's mode, not ``reduce-overhead``,
            whose own CUDA graphs this backend replaces).
        graph: capture and replay a CUDA graph (needs a CUDA device).
        warmup: untimed runs of a new frame size before its capture.
    """

    def __init__(self, label: str = "cuda compiled fp16", precision: str = "fp16", device: str = "cuda",
                 channels_last: bool = True, triton_filter: str | bool = "auto", cudnn_benchmark: bool = True,
                 compile: bool = True, mode: str | None = None, graph: bool = True, warmup: int = 3):
        super().__init__(label, precision, device, channels_last, triton_filter, cudnn_benchmark)
        if mode == "reduce-overhead" and graph:
            raise ConfigError("mode=reduce-overhead captures its own CUDA graphs; use graph=false with it")
        self.compile = bool(compile)
        self.mode = mode
        self.graph = bool(graph)
        self.warmup = int(warmup)

    def available(self) -> str | None:
        if self.graph and not self._cuda():
            return "CUDA graphs need a CUDA device (graph=false on the CPU)"
        return super().available()

    def prepare(self, net: torch.nn.Module, example: Mapping[str, torch.Tensor] | None, threads: int) -> Stepper:
        net = self.prepare_net(net)
        fn = torch.compile(net.step, mode=self.mode, dynamic=False) if self.compile else net.step
        static = StaticStep(net, fn, self.device, self.graph, self.warmup)
        return Stepper(static.step, self._sync(), engine="torch")


# ----------------------------------------------------------------------------- measuring on the device


def cuda_event_times(stepper: Stepper, frames: list[dict], warmup: int, repeats: int) -> list[float]:
    """Milliseconds of each of ``repeats`` recurrent steps after ``warmup`` steps, by CUDA events
    recorded on the current stream around each step (through :class:`~denoiser.recurrent.RecurrentRunner`;
    ``frames`` ``{buffer: [B, C, H, W]}``, cycled, best already on the device; reset at step 0).
    One synchronisation after the last step: the steps run back to back, as in a renderer."""
    runner = RecurrentRunner(stepper.step)
    events = []
    for i in range(warmup + repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        runner(frames[i % len(frames)], reset=i == 0)
        end.record()
        if i < warmup:
            end.synchronize()  # compilation and capture finish before the timed steps
        else:
            events.append((start, end))
    torch.cuda.synchronize()
    return [s.elapsed_time(e) for s, e in events]


def device_report(device: str = "cuda") -> dict[str, str]:
    """``{gpu, driver, torch, cuda, cudnn, triton, memory_gib, sm}`` of ``device`` (strings; the
    driver from ``nvidia-smi`` where it runs)."""
    import subprocess

    try:
        import triton

        triton_version = triton.__version__
    except ImportError:
        triton_version = "not installed"
    info = {"torch": torch.__version__, "cuda": str(torch.version.cuda), "triton": triton_version,
            "cudnn": str(torch.backends.cudnn.version())}
    if not torch.cuda.is_available():
        return {**info, "gpu": "none"}
    props = torch.cuda.get_device_properties(device)
    info.update(gpu=props.name, memory_gib=f"{props.total_memory / 2**30:.1f}", sm=f"{props.major}.{props.minor}",
                multiprocessors=str(props.multi_processor_count))
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader"],
                             check=False, capture_output=True, text=True, timeout=30)
        info["driver"] = out.stdout.strip().splitlines()[0] if out.returncode == 0 and out.stdout.strip() else "?"
    except (OSError, subprocess.SubprocessError):
        info["driver"] = "?"
    return info


def step_traffic(net: torch.nn.Module, height: int, width: int, precision: str = "fp16",
                 channels_last: bool = True) -> dict[str, int]:
    """Bytes one recurrent step with history moves through device memory, from the tensors'
    sizes (shapes only, under ``FakeTensorMode``, as :func:`denoiser.measure.count_flops`):

    * ``floor``: what any implementation must read and write: the weights in ``precision``, the
      frame's inputs (float32 ``[1, C, height, width]``), the state read and the state written
      (float32) and the output ``[1, 3, height, width]`` float32;
    * ``ops``: the sum over the step's operators of the bytes of their tensor arguments and
      results (views excluded): what eager execution moves when no operator is fused with
      another (an estimate: caches catch some, and in-place operators count their target twice).

    ``net`` is left as it is (a cast copy on the CPU is traced).
    """
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils._python_dispatch import TorchDispatchMode
    from torch.utils._pytree import tree_flatten

    from denoiser.buffers import CHANNELS, FRAME_INPUTS

    class Traffic(TorchDispatchMode):
        total = 0

        def __torch_dispatch__(self, func, types, args=(), kwargs=None):
            out = func(*args, **(kwargs or {}))
            if not func.is_view:
                tensors = [t for t in tree_flatten((args, kwargs, out))[0] if isinstance(t, torch.Tensor)]
                Traffic.total += sum(t.numel() * t.element_size() for t in tensors)
            return out

    prepared = CudaBackend(precision=precision, device="cpu", channels_last=channels_last,
                           triton_filter=False).prepare_net(net)
    weights = sum(p.numel() * p.element_size() for p in prepared.parameters())
    runner = RecurrentRunner(prepared.step)
    with FakeTensorMode(allow_non_fake_inputs=True), torch.inference_mode():
        frame = {k: torch.empty(1, CHANNELS[k], height, width) for k in FRAME_INPUTS}
        runner(frame, reset=True)
        state = sum(t.numel() * 4 for t in runner.state.values())
        with Traffic():
            runner(frame)
    inputs = sum(CHANNELS[k] for k in FRAME_INPUTS) * height * width * 4
    floor = weights + inputs + 2 * state + 3 * height * width * 4
    return {"floor": int(floor), "ops": int(Traffic.total), "weights": int(weights)}


def gpu_peaks(device: str = "cuda", matmul: int = 8192, copy_mib: int = 1024) -> dict[str, float]:
    """This GPU's practical peaks, measured now with CUDA events (best of 10 after 3 warm-ups):
    ``tflops_fp16`` of a ``matmul`` x ``matmul`` fp16 product, ``tflops_bf16`` the same in bf16,
    and ``gbps`` of a device-to-device copy of ``copy_mib`` MiB (bytes read plus written)."""
    def best_ms(fn) -> float:
        for _ in range(3):
            fn()
        times = []
        for _ in range(10):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end))
        return min(times)

    peaks = {}
    for name, dtype in (("tflops_fp16", torch.float16), ("tflops_bf16", torch.bfloat16)):
        a = torch.randn(matmul, matmul, device=device, dtype=dtype)
        b = torch.randn(matmul, matmul, device=device, dtype=dtype)
        peaks[name] = 2 * matmul**3 / best_ms(lambda a=a, b=b: torch.mm(a, b)) / 1e9
    src = torch.empty(copy_mib * 2**20 // 4, device=device)
    dst = torch.empty_like(src)
    peaks["gbps"] = 2 * src.numel() * 4 / best_ms(lambda: dst.copy_(src)) / 1e6
    return peaks
