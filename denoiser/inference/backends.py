"""Inference backends: how a network is prepared and stepped (PyTorch eager, channels-last,
autocast, ``torch.compile``, ONNX Runtime, OpenVINO f32/bf16; CUDA variants where a GPU is present).

A backend's ``prepare(net, example, threads)`` returns a :class:`~denoiser.recurrent.Stepper`, whose
``step(frame, state, reset) -> (output, state)`` the recurrent runner
(:mod:`denoiser.recurrent`) drives over a sequence. ``available()`` says why a backend cannot
run here (None when it can); ``dtype`` is the precision of its convolutions (``fp32``,
``bf16``, ``fp16``) for the tables.

Backends are chosen by name from the config group ``conf/backends/`` (one YAML per backend:
``_target_`` and its options): :func:`load_backend` composes ``conf/backends/<name>.yaml`` and
instantiates it, :func:`backend_names` lists the group. ``denoiser-bench`` (``use_backends``),
``denoiser-pareto`` and ``denoiser-denoise`` (``backend``, with :func:`resolve_backend` mapping
``precision`` in one place) and ``denoiser-train``'s time objective (``objectives.time.backend``)
all select from it. A new backend: a class here (or anywhere importable) with ``label``,
``device``, ``dtype``, ``available()`` and ``prepare()``, plus ``conf/backends/<name>.yaml``.
Directories given with ``hydra.searchpath`` on a command line (or in :data:`SEARCHPATH`) add
options to the group.
The CUDA backends with cast weights, the Triton filter and CUDA graphs are in :mod:`denoiser.inference.cuda_backend`.
"""

from __future__ import annotations

import contextlib
import copy
import statistics
import sys
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import torch

from denoiser.errors import ConfigError, first_line
from denoiser.recurrent import Stepper

#: the config group of the backends: ``conf/backends/<name>.yaml``
GROUP = "backends"
#: extra config search path entries (``file:///dir`` or ``pkg://pkg``; each may hold ``backends/<name>.yaml``),
#: searched beside a running Hydra app's own ``hydra.searchpath``
SEARCHPATH: list[str] = []
#: the precisions of ``precision=`` (denoise)
PRECISIONS = ("f32", "bf16", "fp16")
#: ``backend=`` + ``precision=`` shorthands (denoise, pareto) -> the group's option: the one place they map
PRECISION_OPTIONS = {"eager": {"f32": "eager", "bf16": "bf16"},
                     "openvino": {"f32": "openvino_f32", "bf16": "openvino_bf16"}}
#: options whose class takes ``precision`` (fp32, bf16, fp16) as an argument: the CUDA backends
PRECISION_ARGUMENT = ("cuda", "cuda_compiled")


def searchpath() -> list[str]:
    """Where the group's options are looked up besides ``conf/``: :data:`SEARCHPATH`, then the running
    Hydra app's ``hydra.searchpath``."""
    from hydra.core.hydra_config import HydraConfig

    app = list(HydraConfig.get().searchpath) if HydraConfig.initialized() else []
    return [*SEARCHPATH, *(p for p in app if p not in SEARCHPATH)]


def _searchpath_override() -> list[str]:
    path = searchpath()
    return [f"hydra.searchpath=[{','.join(path)}]"] if path else []


def backend_names() -> list[str]:
    """The options of the group ``conf/backends/`` (and of the search path's ``backend/`` directories), sorted."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from denoiser.conf import CONF_DIR

    def options():
        return GlobalHydra.instance().config_loader().get_group_options(GROUP, overrides=_searchpath_override())

    if GlobalHydra.instance().is_initialized():
        return sorted(options())
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return sorted(options())


def backend_config(name: str, key: str = "backend") -> dict:
    """The resolved ``conf/backends/<name>.yaml`` (a plain dict with ``_target_``); an unknown name is a
    one-line ConfigError naming ``key`` and the group's options."""
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from denoiser.configs import compose_config

    names = backend_names()
    if name not in names:
        raise ConfigError(f"{key}: {name!r} is not one of {', '.join(names)}")
    try:
        cfg = compose_config([f"+{GROUP}={name}", *_searchpath_override()])
        return OmegaConf.to_container(cfg[GROUP], resolve=True)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"{key}: {GROUP}/{name}.yaml: {first_line(exc)}") from None


def load_backend(name: str, key: str = "backend", **overrides):
    """The backend ``conf/backends/<name>.yaml`` instantiated, with ``overrides`` of its arguments
    (e.g. ``profile=True``). Mistakes are one-line ConfigErrors naming ``key``: an unknown name
    (with the group's options), a bad argument."""
    from denoiser.configs import instantiate_config

    return instantiate_config({**backend_config(name, key), **overrides}, f"{key}={name}")


def resolve_backend(name: str, precision: str | None = None, key: str = "backend") -> tuple[str, dict]:
    """``backend=`` and ``precision=`` (denoise, pareto) -> ``(option of the group, overrides)``.

    ``eager`` and ``openvino`` are shorthands taking a precision (:data:`PRECISION_OPTIONS`:
    ``openvino`` + ``bf16`` is ``openvino_bf16``), ``cuda`` and ``cuda_compiled`` take it as an
    argument (f32 -> fp32); any other option runs its own precision only (``precision`` None: no check)."""
    if precision is not None and precision not in PRECISIONS:
        raise ConfigError(f"precision: {precision!r} is not one of {', '.join(PRECISIONS)}")
    if name in PRECISION_OPTIONS:
        options = PRECISION_OPTIONS[name]
        p = precision or "f32"
        if p not in options:
            if p == "fp16":
                raise ConfigError(f"precision=fp16 needs backend={' or backend='.join(PRECISION_ARGUMENT)}")
            raise ConfigError(f"backend={name} runs precision={' or precision='.join(options)} only")
        return options[p], {}
    if name in PRECISION_ARGUMENT and precision is not None and name in backend_names():
        p = {"f32": "fp32"}.get(precision, precision)
        return name, {"precision": p, "label": f"{name.replace('_', ' ')} {p}"}
    if precision is not None and name in backend_names():
        dtype = load_backend(name, key).dtype
        if dtype != {"f32": "fp32"}.get(precision, precision):
            if precision == "fp16":
                raise ConfigError(f"precision=fp16 needs backend={' or backend='.join(PRECISION_ARGUMENT)}")
            own = {"fp32": "f32"}.get(dtype, dtype)
            raise ConfigError(f"backend={name} runs precision={own} only")
    return name, {}


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
        fused: the kernel filter and ``log1p`` as the project's OpenVINO extension's fused
            operations (True: required, ``available()`` says why not), the plain graph (False),
            or the extension when it builds, else plain (None). ``label`` ends in ``(fused)`` or
            ``(plain)``: the graph that runs (deciding None builds the extension once).
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
    extension builds (:mod:`denoiser.inference.ovext`), else the plain graph (one line on stderr says why);
    ``fused`` forces either.
    """

    def __init__(self, label: str = "openvino f32", precision: str = "f32", device: str = "CPU",
                 profile: bool = False, fused: bool | None = None):
        from denoiser.inference.step_graph import OPENVINO_PRECISIONS

        if precision not in OPENVINO_PRECISIONS:
            raise ValueError(f"precision: {precision!r} is not one of {', '.join(OPENVINO_PRECISIONS)}")
        if fused not in (None, True, False):
            raise ConfigError(f"fused: {fused!r} is not null, true or false")
        self.base_label = label
        self.precision = precision
        self.fused = fused
        self.dtype = {"f32": "fp32"}.get(precision, precision)
        self.ov_device = device
        self.device = device.lower()
        self.profile = bool(profile)
        self.matmul_heads = precision == "f32"
        self.fused_kernels = None if fused is None else fused  # None: decided on first use (the extension builds)

    def _fused(self) -> bool:
        if self.fused_kernels is None:
            from denoiser.inference import ovext

            self.fused_kernels = ovext.kernel_extension() is not None
            if not self.fused_kernels:
                print(f"{self.base_label}: plain kernel filter graph ({ovext.unavailable_reason()})", file=sys.stderr)
        return self.fused_kernels

    @property
    def label(self) -> str:
        """``<label> (fused)`` or ``<label> (plain)``: which graph runs."""
        return f"{self.base_label} ({'fused' if self._fused() else 'plain'})"

    def available(self) -> str | None:
        try:
            import onnx  # noqa: F401 - the export needs it
            import openvino as ov
        except ImportError as exc:
            return f"{exc.name} is not installed"
        from denoiser.inference import sigstack

        with sigstack.kept():  # the CPU plugin made and freed here sets the thread's signal stack
            core = ov.Core()
            devices = core.available_devices
            bf16 = self.ov_device in devices and "BF16" in core.get_property(self.ov_device, "OPTIMIZATION_CAPABILITIES")
            del core
        if self.ov_device not in devices:
            return f"OpenVINO device {self.ov_device} not available"
        if self.precision == "bf16" and not bf16:
            return f"{self.ov_device} has no bf16 support (OpenVINO would run f32)"
        capped = self.precision == "bf16" and self.ov_device == "CPU" and bf16_capped()
        if capped:
            return capped
        if self.fused:
            from denoiser.inference import ovext

            if ovext.kernel_extension() is None:
                return f"fused=true: the OpenVINO extension is unavailable ({ovext.unavailable_reason()})"
        return None

    def prepare(self, net, example, threads: int) -> Stepper:
        from denoiser.inference.step_graph import OpenVinoStep

        self._fused()
        runner = OpenVinoStep(self._export(net), threads, precision=self.precision, device=self.ov_device,
                              profile=self.profile)
        fused = self.fused_kernels

        def kernels() -> dict:
            from denoiser.inference import ovext

            return {"openvino": runner.last_kernels, "extension": ovext.built_for() if fused else None}

        return Stepper(runner.step, profile=runner.last_profile if self.profile else None,
                       threads=runner.threads_in_use, engine="openvino",
                       extension_profile=runner.last_extension_profile if self.profile else None, kernels=kernels)


#: oneDNN's instruction-set names (``$ONEDNN_MAX_CPU_ISA``) below its native bfloat16 ones
_BELOW_BF16 = {"SSE41", "AVX", "AVX2", "AVX2_VNNI", "AVX2_VNNI_2", "AVX512_CORE", "AVX512_CORE_VNNI"}


def bf16_capped(environ=None) -> str | None:
    """Why OpenVINO's CPU bf16 cannot run under this environment's oneDNN cap
    (:data:`denoiser.machine.ISA_CAPS`), one line; None where nothing caps it. Under a cap below
    bfloat16 the CPU plugin still reports BF16 and then fails to compile a bf16 model
    (OpenVINO 2026.4: ``Object is not initialized``)."""
    from denoiser.machine import isa_caps

    caps = isa_caps(environ)
    for name in ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA"):
        if caps.get(name, "").upper() in _BELOW_BF16:
            return f"${name}={caps[name]} caps oneDNN below bfloat16 (OpenVINO would fail to compile bf16)"
    return None


@dataclass(frozen=True)
class PrecisionChoice:
    """What :func:`faster_precision` measured: ``precision`` (``f32`` or ``bf16``), the median
    ``ms`` per step of each precision timed, ``reason``, one line saying why, and ``backend``, the
    chosen precision's backend (its graph already exported: run it rather than build it again)."""

    precision: str
    ms: dict[str, float]
    reason: str
    backend: object = field(default=None, compare=False, repr=False)


def faster_precision(net: torch.nn.Module, frame: Mapping[str, torch.Tensor], threads: int, name: str = "openvino",
                     warmup: int = 2, repeats: int = 3) -> PrecisionChoice:
    """The faster of ``name``'s f32 and bf16 (:data:`PRECISION_OPTIONS`) on this machine, for
    ``net`` on frames like ``frame`` (``{buffer: [B, C, H, W]}``, the size that will run):
    ``warmup`` then ``repeats`` recurrent steps of each, compared by their median. bf16 is not
    timed where it is not available (no bf16 on the CPU, OpenVINO missing it; the reason says
    so); f32 wins a tie. bf16's outputs differ from f32 by a few 1e-3 relative
    (``tests/inference/test_openvino.py``), so it is taken only when it is faster."""
    from denoiser.measure import time_steps

    ms: dict[str, float] = {}
    unavailable: dict[str, str] = {}
    backends = {}
    for precision in ("f32", "bf16"):
        backend = backends[precision] = load_backend(PRECISION_OPTIONS[name][precision])
        reason = backend.available()
        if reason:
            unavailable[precision] = reason
            continue
        stepper = backend.prepare(net, frame, threads)
        ms[precision] = 1000 * statistics.median(time_steps(stepper, [dict(frame)], warmup, repeats))
        del stepper
    if "f32" not in ms:
        raise ConfigError(f"backend={name} precision=auto: {unavailable['f32']}")
    h, w = next(iter(frame.values())).shape[-2:]
    where = f"at {w}x{h} on {threads} thread(s)"
    if "bf16" not in ms:
        return PrecisionChoice("f32", ms, f"f32: bf16 not timed ({unavailable['bf16']})", backends["f32"])
    if ms["bf16"] < ms["f32"]:
        return PrecisionChoice("bf16", ms, f"bf16: {ms['bf16']:.0f} ms a frame against f32's {ms['f32']:.0f} {where}",
                               backends["bf16"])
    return PrecisionChoice("f32", ms, f"f32: bf16 is not faster here ({ms['bf16']:.0f} ms a frame against "
                                      f"f32's {ms['f32']:.0f} {where})", backends["f32"])
