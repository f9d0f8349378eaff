"""A denoiser's recurrent step as an ONNX graph (opset 17), and that graph run by ONNX Runtime.

Used by ``denoiser-export`` (:mod:`denoiser.commands.export`), by the ONNX Runtime and OpenVINO
backends of the benchmark (:mod:`denoiser.inference.backends`) and by ``denoiser-denoise``
(:class:`OnnxStep`, :class:`OpenVinoStep`). The graph is one :meth:`Denoiser.step <denoiser.nn.denoiser.Denoiser.step>` with the recurrent
state as explicit inputs and outputs (see ``docs/export.md``):

=================================  ======================  =====================================
inputs                             shape                   meaning
=================================  ======================  =====================================
``color``                          ``[B, 3, H, W]`` f32    noisy linear HDR radiance
``albedo``, ``normal``             ``[B, 3, H, W]`` f32    first-hit albedo, camera-space normal
``depth``                          ``[B, 1, H, W]`` f32    planar depth
``motion``                         ``[B, 2, H, W]`` f32    backward motion in pixels (x right, y down)
``reset``                          ``[B]`` bool            True: discard the history (first frame, cut)
``state_<k>``                      ``[B, C_k, H, W]`` f32  previous step's ``next_state_<k>``
=================================  ======================  =====================================

outputs: ``output [B, 3, H, W]`` (denoised linear HDR) and ``next_state_<k>`` for every state
key ``k`` (``output``, ``color``, ``features``, ``guide`` for the temporal recurrence). On the
first frame pass zeros as state and ``reset = True``. Networks without temporal recurrence have
neither ``reset`` nor state. ``H`` and ``W`` are dynamic (any size; ``B`` is fixed at export).

How: the TorchScript-based exporter traces the step at a deliberately odd size
(``trace_size``, not a multiple of the U-Net's 2^levels), so the internal padding to a multiple
is recorded as shape arithmetic and the graph stays valid at every size. (The
``torch.export``-based exporter rejected the padding's shape guards and a ``clamp`` at opset 17
with torch 2.13.) The result is checked by ONNX Runtime against PyTorch at ``check_size``, a
different resolution, over two recurrent steps (reset, then with the returned state); the
largest absolute error of every output is printed and must stay below
``tolerance * max(1, max |value|)`` (HDR values reach hundreds: float32 rounding in a
different operator order scales with them).
"""

from __future__ import annotations

import os
import sys
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from torch import nn

from denoiser.atomic import atomic_path
from denoiser.buffers import CHANNELS, FRAME_INPUTS
from denoiser.errors import UserError
from denoiser.frames import random_frame
from denoiser.inference import sigstack
from denoiser.nn.graph_mode import heads_as_matmul, kernels_as_op
from denoiser.recurrent import Network, RecurrentRunner


def state_keys(net: Network) -> list[str]:
    """State keys of a denoiser's recurrence, in graph order (empty without recurrence)."""
    return list(state_channels(net))


def state_channels(net: Network) -> dict[str, int]:
    """``{state key: channels}`` of a denoiser's recurrence (empty without recurrence)."""
    temporal = getattr(net, "temporal", None)
    return {} if temporal is None else dict(temporal.state_channels())


class StepGraph(nn.Module):
    """``Denoiser.step`` with positional tensors: the module that is traced to ONNX.

    ``forward(color, albedo, normal, depth, motion[, reset, *state]) -> (output, *next_state)``
    with the shapes of the module docstring; ``state`` in :func:`state_keys` order.
    """

    def __init__(self, net: nn.Module):
        super().__init__()
        self.net = net
        self.keys = state_keys(net)

    def input_names(self) -> list[str]:
        extra = ["reset", *[f"state_{k}" for k in self.keys]] if self.keys else []
        return [*FRAME_INPUTS, *extra]

    def output_names(self) -> list[str]:
        return ["output", *[f"next_state_{k}" for k in self.keys]]

    def forward(self, color, albedo, normal, depth, motion, reset=None, *state):
        frame = {"color": color, "albedo": albedo, "normal": normal, "depth": depth, "motion": motion}
        previous = dict(zip(self.keys, state)) if self.keys else None
        output, new_state, _ = self.net.step(frame, previous, reset)
        return (output, *[new_state[k] for k in self.keys])


def graph_inputs(graph: StepGraph, frame: dict, state: dict | None, reset: bool) -> tuple:
    """Positional inputs of :class:`StepGraph` (zero state when ``state`` is None)."""
    args = [frame[k] for k in FRAME_INPUTS]
    if graph.keys:
        like = frame["color"]
        b, _, h, w = like.shape
        if state is None:
            state = {k: like.new_zeros(b, c, h, w) for k, c in state_channels(graph.net).items()}
        args.append(torch.full((b,), bool(reset), dtype=torch.bool))
        args.extend(state[k] for k in graph.keys)
    return tuple(args)


def export_onnx(net: nn.Module, path: str | os.PathLike, opset: int = 17, trace_size=(37, 61), batch: int = 1,
                metadata: dict | None = None, matmul_heads: bool = False, fused_kernels: bool = False) -> Path:
    """Trace ``net.step`` at ``trace_size`` ``(H, W)`` and write an ONNX model to ``path`` (atomic).

    ``matmul_heads``: the U-Net's 1x1 heads as matrix products
    (:func:`denoiser.nn.parts.pointwise_of_parts`; same numbers): the graph OpenVINO runs fastest
    in f32, while 1x1 convolutions (the default) are what it runs fastest in bf16.
    ``fused_kernels``: the kernel filter, the input transforms' ``log1p`` and (with matmul heads)
    the level-0 head's upsampling as operations of the project's OpenVINO extension
    (:func:`denoiser.nn.graph_mode.kernels_as_op`, :mod:`denoiser.inference.ovext`; same numbers): faster in
    OpenVINO, and only OpenVINO with that extension can run the file.
    """
    import onnx

    bad = [name for name, p in net.named_parameters() if not bool(torch.isfinite(p).all())]
    if bad:  # the graph relies on finite weights (denoiser.nn.kernels.scale_logits)
        source = (metadata or {}).get("checkpoint", "network")
        raise UserError(f"{source}: cannot export non-finite (NaN or Inf) weights in {', '.join(bad[:3])}"
                        + (f" and {len(bad) - 3} more" if len(bad) > 3 else "") + ": a diverged checkpoint?")
    graph = StepGraph(net.eval()).eval()
    h, w = (int(v) for v in trace_size)
    frame = random_frame(batch, h, w, kind="hard")
    args = graph_inputs(graph, frame, None, reset=False)
    dynamic = {n: {2: "height", 3: "width"} for n in graph.input_names() + graph.output_names() if n != "reset"}
    path = Path(path)
    with atomic_path(path, ".onnx") as tmp, warnings.catch_warnings(), torch.no_grad():
        # no_grad: the inference path of every op (no custom autograd.Function in the graph);
        # tracer warnings about Python ints are expected (see the module docstring)
        warnings.simplefilter("ignore")
        with heads_as_matmul(matmul_heads), kernels_as_op(fused_kernels):
            torch.onnx.export(graph, args, str(tmp), opset_version=int(opset), input_names=graph.input_names(),
                              output_names=graph.output_names(), dynamic_axes=dynamic, dynamo=False,
                              do_constant_folding=True,
                              custom_opsets={"denoiser": 1} if fused_kernels else None)
        model = onnx.load(str(tmp))
        onnx.checker.check_model(model)
        meta = {"state_keys": ",".join(graph.keys), "multiple": str(getattr(net, "multiple", 1)),
                **{k: str(v) for k, v in (metadata or {}).items()}}
        for k, v in meta.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = k, v
        onnx.save(model, str(tmp))
    return path


def uses_extension(path: str | os.PathLike) -> bool:
    """Whether the ONNX graph at ``path`` imports the ``denoiser`` domain (its
    nodes need the OpenVINO extension :mod:`denoiser.inference.ovext`)."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    return any(entry.domain == "denoiser" for entry in model.opset_import)


class OnnxStep:
    """Runs an exported step graph with ONNX Runtime, carrying the state like ``Denoiser.step``.

    ``threads``: intra-op threads (None = ONNX Runtime's default).
    """

    def __init__(self, path: str | os.PathLike, threads: int | None = None, providers=("CPUExecutionProvider",)):
        import onnxruntime as ort

        options = ort.SessionOptions()
        if threads:
            options.intra_op_num_threads = int(threads)
            options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), options, providers=list(providers))
        self.inputs = [i.name for i in self.session.get_inputs()]
        self.outputs = [o.name for o in self.session.get_outputs()]
        self.keys = [n[len("state_"):] for n in self.inputs if n.startswith("state_")]
        self.channels = {i.name[len("state_"):]: int(i.shape[1]) for i in self.session.get_inputs()
                         if i.name.startswith("state_")}

    def step(self, frame: dict, state: dict | None, reset: bool = False) -> tuple[np.ndarray, dict]:
        """``frame``: ``{buffer: [B, C, H, W]}`` tensors or arrays -> ``(output array, state)``.

        ``state=None`` (or ``reset=True``) starts a sequence: zero state and the graph's reset
        input set (the runner's contract, :mod:`denoiser.recurrent`)."""
        feed = graph_feed(frame, state, reset, self.keys, self.channels, self.inputs)
        results = self.session.run(None, feed)
        named = dict(zip(self.outputs, results))
        return named["output"], {k: named[f"next_state_{k}"] for k in self.keys}


class _Slot:
    """An infer request of a compiled step graph that writes its outputs into arrays of its own
    (``arrays``: ``{output name: [B, C, H, W] float32}``, OpenVINO tensors sharing their memory,
    so the arrays outlive the request and a state needs no copy).

    ``fed``: the ids of the state arrays the request read at its last infer. OpenVINO keeps a
    reference to each array it was fed (``share_inputs=True``) until the request infers again,
    so an array read by ``n`` requests carries ``n`` references more than the slot's own."""

    def __init__(self, request, arrays: dict[str, np.ndarray], state_names: list[str]):
        self.request, self.arrays, self.state_names = request, arrays, state_names
        self.fed: frozenset[int] = frozenset()
        self._probe = {"unheld": np.empty(0, np.float32)}  # an array nothing else refers to

    @classmethod
    def make(cls, compiled, names: list[str], keys: list[str]) -> _Slot:
        import openvino as ov

        request = compiled.create_infer_request()
        arrays = {name: np.empty(tuple(out.get_shape()), np.float32) for name, out in zip(names, compiled.outputs)}
        for array in arrays.values():
            array.fill(0.0)  # the pages mapped now, not in the first step that writes them
        for index, name in enumerate(names):
            request.set_output_tensor(index, ov.Tensor(arrays[name], shared_memory=True))
        return cls(request, arrays, [f"next_state_{k}" for k in keys])

    def infer(self, feed: dict) -> None:
        self.request.infer(feed, share_inputs=True)
        self.fed = frozenset(id(v) for k, v in feed.items() if k.startswith("state_"))

    def held(self, slots: list[_Slot]) -> bool:
        """Whether anything but the runner refers to one of this slot's state arrays (a caller's
        state, the feed of the step about to run): more references than an array only the slot
        holds (counted by the same expression) plus one per request of ``slots`` that read it last."""
        own = sys.getrefcount(self._probe["unheld"])
        for name in self.state_names:
            readers = sum(id(self.arrays[name]) in s.fed for s in slots)
            if sys.getrefcount(self.arrays[name]) > own + readers:
                return True
        return False


#: OpenVINO ``INFERENCE_PRECISION_HINT`` per ``precision`` of :class:`OpenVinoStep`
OPENVINO_PRECISIONS = {"f32": "f32", "bf16": "bf16"}


class OpenVinoStep:
    """Runs an exported step graph with OpenVINO, carrying the state like :class:`OnnxStep`.

    The ONNX model is read once; it is reshaped to static ``[B, C, H, W]`` and compiled once
    per frame size (cached: a sequence compiles once). ``precision``: ``f32`` or ``bf16``
    (OpenVINO's ``INFERENCE_PRECISION_HINT``; bf16 runs the convolutions, and whatever
    OpenVINO decides with them, in bfloat16 where the CPU has AVX512-BF16/AMX). ``threads``:
    ``INFERENCE_NUM_THREADS`` (None = OpenVINO's default). ``device``: an OpenVINO device name.
    ``profile``: per-node performance counters on (``PERF_COUNT``), read by :meth:`last_profile`.
    """

    #: the last step's milliseconds per node, ``{(node name, node type): ms}`` (``profile=True``)
    last_nodes: dict[tuple[str, str], float]
    #: the implementations the compiled model of the last step runs, :func:`compiled_kernels` (empty before a step)
    last_kernels: dict[str, dict[str, int]]

    def __init__(self, path: str | os.PathLike, threads: int | None = None, precision: str = "f32",
                 device: str = "CPU", profile: bool = False):
        if precision not in OPENVINO_PRECISIONS:
            raise ValueError(f"precision: {precision!r} is not one of {', '.join(OPENVINO_PRECISIONS)}")
        self._compiled: dict[tuple[int, ...], tuple] = {}
        self._last = None
        self._counters: dict[tuple[int, ...], tuple[int, dict[str, float]]] = {}  # per compiled model: steps, means
        self.last_nodes = {}
        self.last_kernels = {}
        self._kernels: dict[tuple[int, ...], dict[str, dict[str, int]]] = {}  # per compiled model
        with sigstack.kept():  # OpenVINO's plugin sets the thread's signal stack (denoiser.inference.sigstack)
            self._open(path, threads, precision, device, profile)

    def _open(self, path, threads, precision, device, profile) -> None:
        import openvino as ov

        self.core = ov.Core()
        if uses_extension(path):  # export_onnx(fused_kernels=True)
            from denoiser.inference import ovext

            ovext.load_into(self.core, path)
        self.model = self.core.read_model(str(path))
        self.device = device
        self.config = {"INFERENCE_PRECISION_HINT": OPENVINO_PRECISIONS[precision], "PERFORMANCE_HINT": "LATENCY"}
        if threads:
            self.config["INFERENCE_NUM_THREADS"] = int(threads)
        if profile:
            self.config["PERF_COUNT"] = True
        self.inputs = [i.get_any_name() for i in self.model.inputs]
        self.outputs = [o.get_any_name() for o in self.model.outputs]
        self.keys = [n[len("state_"):] for n in self.inputs if n.startswith("state_")]
        self.channels = {i.get_any_name()[len("state_"):]: i.get_partial_shape()[1].get_length()
                         for i in self.model.inputs if i.get_any_name().startswith("state_")}

    def compiled(self, batch: int, height: int, width: int):
        """``(compiled model, its slots)`` for frames of ``[batch, *, height, width]`` (cached).
        A graph with state gets the two slots (:class:`_Slot`) a sequence steps on in turn with
        it, their arrays written once (so a first step's timing and memory hold them); :meth:`step`
        makes more where states are held."""
        key = (batch, height, width)
        if key not in self._compiled:
            model = self.model.clone()
            shapes = {}
            for i in model.inputs:
                shape = i.get_partial_shape()
                if len(shape) == 4:
                    shapes[i.get_any_name()] = [batch, shape[1].get_length(), height, width]
            model.reshape(shapes)
            with sigstack.kept():
                compiled = self.core.compile_model(model, self.device, self.config)
                self._compiled[key] = (compiled, [_Slot.make(compiled, self.outputs, self.keys)
                                                  for _ in range(2 if self.keys else 1)])
                self._kernels[key] = compiled_kernels(compiled)
                del compiled, model
        return self._compiled[key]

    def precision(self, batch: int = 1, height: int = 16, width: int = 16) -> str:
        """The inference precision OpenVINO chose (``f32``, ``bf16``) for that size."""
        compiled, _ = self.compiled(batch, height, width)
        return compiled.get_property("INFERENCE_PRECISION_HINT").get_type_name()

    def step(self, frame: dict, state: dict | None, reset: bool = False) -> tuple[np.ndarray, dict]:
        """Same contract as :meth:`OnnxStep.step`: arrays out, the output a copy of its own.

        The state's arrays are not copied (20 planes at 1080p, about 20 ms a step): they are the
        arrays a slot's infer request wrote (:class:`_Slot`), and a slot is written again only
        when nothing outside this runner refers to its state arrays. So a state stays as it was
        for as long as it is held (kept to step from again, two sequences stepped in turn): a
        held slot is passed over and another one made."""
        feed = graph_feed(frame, state, reset, self.keys, self.channels, self.inputs)
        b, _, h, w = feed["color"].shape
        compiled, slots = self.compiled(b, h, w)
        self.last_kernels = self._kernels[(b, h, w)]
        slot = next((s for s in slots if not s.held(slots)), None)
        if slot is None:
            slot = _Slot.make(compiled, self.outputs, self.keys)
            slots.append(slot)
        # the inputs are read in place (no copy into OpenVINO's buffers: about 20 ms of a 1080p
        # step); the infer call is synchronous and never writes them
        with sigstack.kept():
            slot.infer(feed)
        self._last = slot.request
        if "PERF_COUNT" in self.config:
            self._count_step((b, h, w), slot.request)
        return slot.arrays["output"].copy(), {k: slot.arrays[f"next_state_{k}"] for k in self.keys}

    def close(self) -> None:
        """Free the compiled models, the model and the core (OpenVINO's destructors run here, with the
        thread's signal stack kept: :mod:`denoiser.inference.sigstack`); also run when collected."""
        with sigstack.kept():
            self._last = None
            self._compiled.clear()
            self.__dict__.pop("model", None)
            self.__dict__.pop("core", None)

    def __del__(self):
        if "_compiled" in self.__dict__:
            self.close()

    def threads_in_use(self) -> int:
        """``INFERENCE_NUM_THREADS`` as the last compiled model resolved it (needs a step run first)."""
        if self._last is None:
            raise RuntimeError("threads_in_use needs a step run first (OpenVINO resolves it when compiling)")
        return int(self._last.get_compiled_model().get_property("INFERENCE_NUM_THREADS"))

    def _count_step(self, key: tuple[int, ...], request) -> None:
        """:attr:`last_nodes` from the counters after a step. The CPU plugin reports each node's
        *mean* over every infer of the compiled model so far (its infer requests share one graph
        under the ``LATENCY`` hint), the first, cold one included; so the step just run took
        ``n * mean_n - (n - 1) * mean_(n-1)``."""
        n, means = self._counters.get(key, (0, {}))
        n += 1
        now: dict[str, float] = {}
        self.last_nodes = {}
        for node in request.profiling_info:
            ms = node.real_time.total_seconds() * 1000
            now[node.node_name] = ms
            self.last_nodes[(node.node_name, node.node_type)] = n * ms - (n - 1) * means.get(node.node_name, 0.0)
        self._counters[key] = (n, now)

    def last_extension_profile(self) -> dict[str, float]:
        """Milliseconds per operation of the project's OpenVINO extension (``PyramidFilterHead``,
        ``EmbedNet``, ...: the nodes :meth:`last_profile` counts as ``Reference``) in the last
        :meth:`step` alone, largest first; empty for a graph without them; needs ``profile=True``."""
        self.last_profile()  # the same checks
        if not hasattr(self, "_extension_ops"):
            self._extension_ops = extension_node_names(self.model)
        totals: dict[str, float] = {}
        for (name, node_type), ms in self.last_nodes.items():
            if node_type == "Reference" and name in self._extension_ops:
                op = self._extension_ops[name]
                totals[op] = totals.get(op, 0.0) + ms
        return dict(sorted(totals.items(), key=lambda kv: -kv[1]))

    def last_profile(self) -> dict[str, float]:
        """Milliseconds per node type (``Convolution``, ``Reorder``, ``Subgraph`` for fused
        elementwise ops, ...) of the last :meth:`step` alone (not OpenVINO's mean over every step,
        see :meth:`_count_step`), largest first; needs ``profile=True``."""
        if self._last is None or "PERF_COUNT" not in self.config:
            raise RuntimeError("last_profile needs OpenVinoStep(profile=True) and a step run first")
        totals: dict[str, float] = {}
        for (_, node_type), ms in self.last_nodes.items():
            totals[node_type] = totals.get(node_type, 0.0) + ms
        return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


#: runtime-model node types that run no kernel of their own (their implementation is ``unknown_*``)
_NO_KERNEL = {"Input", "Output", "Const"}


def compiled_kernels(compiled) -> dict[str, dict[str, int]]:
    """The implementations an OpenVINO compiled model runs: ``{node type: {implementation:
    count}}`` from its runtime model (the ``layerType`` and ``primitiveType`` of each node, e.g.
    ``{"Convolution": {"brgconv_avx2_f32": 19}}``), node types ordered by their count, without the
    graph's inputs, outputs and constants. The name says the instruction set the CPU plugin chose
    (``avx512``, ``avx2``, ...: the widest the CPU has, or ``$ONEDNN_MAX_CPU_ISA``'s cap); the
    extension's operations are ``Reference`` nodes whatever their build (see
    :func:`denoiser.inference.ovext.built_for`)."""
    kernels: dict[str, dict[str, int]] = {}
    for node in compiled.get_runtime_model().get_ordered_ops():
        rt = node.get_rt_info()
        if "layerType" not in rt or "primitiveType" not in rt:  # a plugin that does not say
            continue
        kind, impl = rt["layerType"].astype(str), rt["primitiveType"].astype(str)
        if kind not in _NO_KERNEL:
            per = kernels.setdefault(kind, {})
            per[impl] = per.get(impl, 0) + 1
    order = sorted(kernels, key=lambda k: -sum(kernels[k].values()))
    return {k: dict(sorted(kernels[k].items(), key=lambda kv: -kv[1])) for k in order}


def extension_node_names(model) -> dict[str, str]:
    """``{node name: op type}`` of an OpenVINO model's operations of the project's extension
    (domain ``denoiser``), by every name the CPU plugin's counters may give such a node: its own,
    its outputs', and a graph output's where the op feeds that output through single-input nodes
    the plugin folds into it (``next_state_guide``: GuideFeatures through Convert nodes)."""
    def ours(node) -> bool:
        return node.get_type_info().version_id == "denoiser"

    names = {}
    for op in model.get_ops():
        if ours(op):
            for name in (op.get_friendly_name(), *(n for out in op.outputs() for n in out.get_names())):
                names[name] = op.get_type_name()
    for result in model.get_results():
        source = result.input_value(0)
        aliases = {result.get_friendly_name(), *source.get_names()}
        node = source.get_node()
        for _ in range(4):
            if ours(node) or node.get_input_size() != 1:
                break
            aliases |= {node.get_friendly_name()}
            node = node.input_value(0).get_node()
        if ours(node):
            for name in aliases:
                names.setdefault(name, node.get_type_name())
    return names


def graph_feed(frame: dict, state: dict | None, reset: bool, keys: list[str], channels: dict[str, int],
               inputs: list[str] | None = None) -> dict:
    """The step graph's inputs as float32 arrays: the frame, and with recurrence ``reset`` and
    the state (zeros and ``reset=True`` when ``state`` is None). ``inputs``: the graph's input
    names, when given only those are fed (a network without temporal recurrence has no use for
    ``motion``, and the exporter drops unused inputs)."""
    feed = {k: np.ascontiguousarray(_numpy(frame[k]), dtype=np.float32) for k in FRAME_INPUTS}
    b, _, h, w = feed["color"].shape
    if keys:
        if state is None:
            state = {k: np.zeros((b, c, h, w), np.float32) for k, c in channels.items()}
            reset = True
        feed["reset"] = np.full((b,), bool(reset))
        feed.update({f"state_{k}": np.ascontiguousarray(state[k], dtype=np.float32) for k in keys})
    if inputs is not None:
        feed = {k: v for k, v in feed.items() if k in inputs}
    return feed


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@torch.no_grad()
def check_export(net: nn.Module, path: str | os.PathLike, size=(72, 104), batch: int = 1, steps: int = 2,
                 threads: int | None = None) -> OrderedDict[str, tuple[float, float]]:
    """Largest absolute error of ONNX Runtime vs PyTorch per output over ``steps`` recurrent steps
    (OpenVINO f32 instead of ONNX Runtime for a graph that needs the extension, :func:`uses_extension`).

    Frames are random (:func:`~denoiser.frames.random_frame`, ``kind="hard"``: fireflies, sky, large
    motion) at ``size`` ``(H, W)``; the first step resets.
    Returns ``{"output": (err, scale), "next_state_<k>": (err, scale), ...}``: the largest
    absolute error and the largest magnitude of the PyTorch value (max over steps).
    """
    torch_runner = RecurrentRunner(net.step)
    engine = OpenVinoStep(path, threads) if uses_extension(path) else OnnxStep(path, threads)
    onnx_runner = RecurrentRunner(engine.step)
    h, w = (int(v) for v in size)
    errors: OrderedDict[str, tuple[float, float]] = OrderedDict()
    for t in range(steps):
        frame = random_frame(batch, h, w, seed=100 + t, kind="hard")
        expected = torch_runner(frame, reset=t == 0)
        got = onnx_runner(frame, reset=t == 0)
        pairs = [("output", expected, got)] + [(f"next_state_{k}", torch_runner.state[k], onnx_runner.state[k])
                                               for k in onnx_runner.state]
        for name, a, b in pairs:
            if tuple(a.shape) != tuple(b.shape):
                raise RuntimeError(f"ONNX output {name} has shape {tuple(b.shape)}, PyTorch {tuple(a.shape)}")
            err = float(np.abs(a.float().numpy() - b).max())
            scale = float(a.abs().max())
            old = errors.get(name, (0.0, 0.0))
            errors[name] = (max(old[0], err), max(old[1], scale))
    return errors


def trtexec_command(path: str | os.PathLike, net: nn.Module, batch: int = 1,
                    sizes=((64, 64), (1080, 1920), (2160, 3840))) -> str:
    """A ``trtexec`` command building a TensorRT FP16 engine with min/opt/max ``(H, W)`` shapes."""
    channels = {**{b: CHANNELS[b] for b in FRAME_INPUTS}, **{f"state_{k}": c for k, c in state_channels(net).items()}}

    def shapes(h: int, w: int) -> str:
        return ",".join(f"{n}:{batch}x{c}x{h}x{w}" for n, c in channels.items())

    (h0, w0), (h1, w1), (h2, w2) = sizes
    engine = Path(path).with_suffix(".fp16.plan")
    return (f"trtexec --onnx={path} --fp16 --saveEngine={engine} \\\n  --minShapes={shapes(h0, w0)} \\\n"
            f"  --optShapes={shapes(h1, w1)} \\\n  --maxShapes={shapes(h2, w2)}")
