"""``denoiser-export``: a trained denoiser's recurrent step as an ONNX graph (opset 17).

::

    denoiser-export ckpt=runs/student.ckpt out=student.onnx
    denoiser-export ckpt=s.ckpt out=s.onnx check_size=[720,1280]     # check at 720p

The graph is one :meth:`Denoiser.step <denoiser.nn.denoiser.Denoiser.step>` with the recurrent
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
import time
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from torch import nn

from denoiser.errors import ConfigError, UserError

FRAME_INPUTS = ("color", "albedo", "normal", "depth", "motion")
FRAME_CHANNELS = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2}


def state_keys(net: nn.Module) -> list[str]:
    """State keys of a denoiser's recurrence, in graph order (empty without recurrence)."""
    temporal = getattr(net, "temporal", None)
    return [] if temporal is None else list(temporal.state_channels())


def state_channels(net: nn.Module) -> dict[str, int]:
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


def example_frame(batch: int, height: int, width: int, seed: int = 0) -> dict[str, torch.Tensor]:
    """A plausible random frame ``{buffer: [B, C, H, W]}``: HDR color with fireflies, unit
    normals, depth with sky (1e10), motion up to a quarter of the frame size."""
    g = torch.Generator().manual_seed(seed)
    color = torch.rand(batch, 3, height, width, generator=g) ** 2 * 4
    color = torch.where(torch.rand(batch, 1, height, width, generator=g) < 0.01, color * 50, color)
    depth = torch.rand(batch, 1, height, width, generator=g) * 20 + 0.5
    depth = torch.where(torch.rand(batch, 1, height, width, generator=g) < 0.1, torch.full_like(depth, 1e10), depth)
    return {
        "color": color,
        "albedo": torch.rand(batch, 3, height, width, generator=g),
        "normal": nn.functional.normalize(torch.randn(batch, 3, height, width, generator=g), dim=1),
        "depth": depth,
        "motion": torch.randn(batch, 2, height, width, generator=g) * 0.25 * max(height, width),
    }


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
                metadata: dict | None = None) -> Path:
    """Trace ``net.step`` at ``trace_size`` ``(H, W)`` and write an ONNX model to ``path`` (atomic)."""
    import onnx

    from denoiser.report import atomic_path

    graph = StepGraph(net.eval()).eval()
    h, w = (int(v) for v in trace_size)
    frame = example_frame(batch, h, w)
    args = graph_inputs(graph, frame, None, reset=False)
    dynamic = {n: {2: "height", 3: "width"} for n in graph.input_names() + graph.output_names() if n != "reset"}
    path = Path(path)
    with atomic_path(path, ".onnx") as tmp, warnings.catch_warnings(), torch.no_grad():
        # no_grad: the inference path of every op (no custom autograd.Function in the graph);
        # tracer warnings about Python ints are expected (see the module docstring)
        warnings.simplefilter("ignore")
        torch.onnx.export(graph, args, str(tmp), opset_version=int(opset), input_names=graph.input_names(),
                          output_names=graph.output_names(), dynamic_axes=dynamic, dynamo=False,
                          do_constant_folding=True)
        model = onnx.load(str(tmp))
        onnx.checker.check_model(model)
        meta = {"state_keys": ",".join(graph.keys), "multiple": str(getattr(net, "multiple", 1)),
                **{k: str(v) for k, v in (metadata or {}).items()}}
        for k, v in meta.items():
            entry = model.metadata_props.add()
            entry.key, entry.value = k, v
        onnx.save(model, str(tmp))
    return path


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

    def step(self, frame: dict, state: dict | None, reset: bool) -> tuple[np.ndarray, dict]:
        """``frame``: ``{buffer: [B, C, H, W]}`` tensors or arrays -> ``(output array, state)``."""
        feed = {k: np.ascontiguousarray(_numpy(frame[k]), dtype=np.float32) for k in FRAME_INPUTS}
        b, _, h, w = feed["color"].shape
        if self.keys:
            if state is None:
                state = {k: np.zeros((b, c, h, w), np.float32) for k, c in self.channels.items()}
                reset = True
            feed["reset"] = np.full((b,), bool(reset))
            feed.update({f"state_{k}": state[k] for k in self.keys})
        results = self.session.run(None, feed)
        named = dict(zip(self.outputs, results))
        return named["output"], {k: named[f"next_state_{k}"] for k in self.keys}


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@torch.no_grad()
def check_export(net: nn.Module, path: str | os.PathLike, size=(72, 104), batch: int = 1, steps: int = 2,
                 threads: int | None = None) -> OrderedDict[str, tuple[float, float]]:
    """Largest absolute error of ONNX Runtime vs PyTorch per output over ``steps`` recurrent steps.

    Frames are random (:func:`example_frame`) at ``size`` ``(H, W)``; the first step resets.
    Returns ``{"output": (err, scale), "next_state_<k>": (err, scale), ...}``: the largest
    absolute error and the largest magnitude of the PyTorch value (max over steps).
    """
    runner = OnnxStep(path, threads)
    h, w = (int(v) for v in size)
    errors: OrderedDict[str, tuple[float, float]] = OrderedDict()
    torch_state, onnx_state = None, None
    for t in range(steps):
        frame = example_frame(batch, h, w, seed=100 + t)
        expected, torch_state, _ = net.step(frame, torch_state, torch.full((batch,), t == 0))
        got, onnx_state = runner.step(frame, onnx_state, reset=t == 0)
        pairs = [("output", expected, got)] + [(f"next_state_{k}", torch_state[k], onnx_state[k]) for k in runner.keys]
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
    channels = {**FRAME_CHANNELS, **{f"state_{k}": c for k, c in state_channels(net).items()}}

    def shapes(h: int, w: int) -> str:
        return ",".join(f"{n}:{batch}x{c}x{h}x{w}" for n, c in channels.items())

    (h0, w0), (h1, w1), (h2, w2) = sizes
    engine = Path(path).with_suffix(".fp16.plan")
    return (f"trtexec --onnx={path} --fp16 --saveEngine={engine} \\\n  --minShapes={shapes(h0, w0)} \\\n"
            f"  --optShapes={shapes(h1, w1)} \\\n  --maxShapes={shapes(h2, w2)}")


def default_output(ckpt: str | os.PathLike) -> Path:
    return Path(ckpt).with_suffix(".onnx")


def run(cfg: DictConfig) -> dict:
    """The ``denoiser-export`` task; returns the check's errors."""
    from denoiser.checkpoint import load_denoiser

    if not cfg.get("ckpt"):
        raise ConfigError("ckpt: give the checkpoint to export (ckpt=<path>)")
    net = load_denoiser(cfg.ckpt, trust=bool(cfg.get("trust_checkpoint")))
    out = Path(cfg.out) if cfg.get("out") else default_output(cfg.ckpt)
    if out.suffix != ".onnx":
        raise ConfigError(f"out: {out} should end in .onnx")
    trace, check = tuple(cfg.trace_size), tuple(cfg.check_size)
    if trace == check:
        raise ConfigError("check_size must differ from trace_size (the check is about dynamic sizes)")
    start = time.perf_counter()
    export_onnx(net, out, int(cfg.opset), trace, int(cfg.batch), metadata={"checkpoint": str(cfg.ckpt)})
    print(f"exported {cfg.ckpt} -> {out} (opset {cfg.opset}, traced at {trace[1]}x{trace[0]}, "
          f"{time.perf_counter() - start:.1f} s, {out.stat().st_size / 1e6:.2f} MB)")
    errors = check_export(net, out, check, int(cfg.batch), threads=cfg.get("threads"))
    print(f"ONNX Runtime vs PyTorch at {check[1]}x{check[0]}, 2 recurrent steps, max abs error (max |value|): "
          + ", ".join(f"{k} {e:.3g} ({s:.3g})" for k, (e, s) in errors.items()))
    tol = float(cfg.tolerance)
    bad = {k: (e, s) for k, (e, s) in errors.items() if e > tol * max(1.0, s)}
    if bad:
        k, (e, s) = next(iter(bad.items()))
        raise UserError(f"{out}: ONNX Runtime differs from PyTorch in {k} by {e:.3g} > tolerance {tol} x max(1, {s:.3g})")
    print(f"max abs error {max(e for e, _ in errors.values()):.3g}: within tolerance {tol} x max(1, max |value|): ok")
    print("TensorRT FP16 engine (see docs/export.md):\n" + trtexec_command(out, net, int(cfg.batch)))
    return dict(errors)


def main() -> None:
    from denoiser.cli import hydra_command

    hydra_command(run, "export")()


if __name__ == "__main__":
    main()
