"""``denoiser-export``: a trained denoiser's recurrent step as an ONNX graph (opset 17).

::

    denoiser-export ckpt=runs/student.ckpt out=student.onnx
    denoiser-export ckpt=s.ckpt out=s.onnx check_size=[720,1280]     # check at 720p

The graph and its inputs and outputs are described in :mod:`denoiser.inference.step_graph` and
``docs/export.md``. The result is checked by ONNX Runtime against PyTorch at ``check_size``, a
different resolution from ``trace_size``, over two recurrent steps (reset, then with the
returned state); the largest absolute error of every output is printed and must stay below
``tolerance * max(1, max |value|)``. ``kernels=fused`` writes the kernel filter and the
``log1p`` transforms as operations of the project's OpenVINO extension (``denoiser::PyramidFilter``,
``denoiser::Log1p``), which only OpenVINO with that extension runs (:mod:`denoiser.inference.ovext`); that
graph is checked with OpenVINO f32 instead.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

from omegaconf import DictConfig

from denoiser.errors import ConfigError, UserError
from denoiser.inference.step_graph import check_export, export_onnx, trtexec_command


def default_output(ckpt: str | os.PathLike) -> Path:
    """The ONNX file beside the checkpoint (a run directory's: beside its best, else last, checkpoint)."""
    from denoiser.checkpoint import resolve_checkpoint

    return resolve_checkpoint(ckpt).with_suffix(".onnx")


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
    heads = str(cfg.get("heads", "conv"))
    if heads not in ("conv", "matmul"):
        raise ConfigError(f"heads: {heads!r} is not conv or matmul")
    kernels = str(cfg.get("kernels", "graph"))
    if kernels not in ("graph", "fused"):
        raise ConfigError(f"kernels: {kernels!r} is not graph or fused")
    if kernels == "fused":
        from denoiser.inference import ovext

        if ovext.kernel_extension() is None:
            raise UserError(f"kernels=fused needs the OpenVINO extension: {ovext.unavailable_reason()}")
    start = time.perf_counter()
    export_onnx(net, out, int(cfg.opset), trace, int(cfg.batch), metadata={"checkpoint": str(cfg.ckpt)},
                matmul_heads=heads == "matmul", fused_kernels=kernels == "fused")
    print(f"exported {cfg.ckpt} -> {out} (opset {cfg.opset}, traced at {trace[1]}x{trace[0]}, "
          f"{time.perf_counter() - start:.1f} s, {out.stat().st_size / 1e6:.2f} MB)")
    errors = check_export(net, out, check, int(cfg.batch), threads=cfg.get("threads"))
    engine = "OpenVINO" if kernels == "fused" else "ONNX Runtime"
    print(f"{engine} vs PyTorch at {check[1]}x{check[0]}, 2 recurrent steps, max abs error (max |value|): "
          + ", ".join(f"{k} {e:.3g} ({s:.3g})" for k, (e, s) in errors.items()))
    tol = float(cfg.tolerance)
    bad = {k: (e, s) for k, (e, s) in errors.items() if e > tol * max(1.0, s)}
    if bad:
        k, (e, s) = next(iter(bad.items()))
        raise UserError(f"{out}: {engine} differs from PyTorch in {k} by {e:.3g} > tolerance {tol} x max(1, {s:.3g})")
    print(f"max abs error {max(e for e, _ in errors.values()):.3g}: within tolerance {tol} x max(1, max |value|): ok")
    if kernels == "graph":  # TensorRT has none of the extension's operations
        print("TensorRT FP16 engine (see docs/export.md):\n" + trtexec_command(out, net, int(cfg.batch)))
    return dict(errors)


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "export")()


if __name__ == "__main__":
    main()
