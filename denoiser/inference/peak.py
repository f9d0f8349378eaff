"""The fp32 matmul peak of the engines the CPU graphs run on: the faster of ``torch.mm``
(:func:`denoiser.machine.matmul_peak`) and OpenVINO's ``MatMul``, what ``denoiser-bench``'s
"of fp32 peak" divides by. torch's MKL can take a narrower path than the CPU has (AVX2 code on
AMD CPUs with AVX-512: 138.9 GFLOP/s on 2 cores of the AMD EPYC family 26, where OpenVINO's
product reached 282.2 and the fused student graph 230.3), and a share of torch's peak then
reads above 100%.
"""

from __future__ import annotations

import numpy as np
import torch

from denoiser.inference import sigstack
from denoiser.machine import matmul_peak, product_rate


def openvino_matmul_peak(size: int = 2048, repeats: int = 5, warmup: int = 2) -> float | None:
    """GFLOP/s of a ``size`` x ``size`` f32 product as an OpenVINO ``MatMul`` compiled for the
    CPU on ``torch.get_num_threads()`` threads (:func:`denoiser.machine.product_rate`); None
    without OpenVINO. The plugin and the compiled model are made and freed inside
    :func:`denoiser.inference.sigstack.kept`."""
    try:
        import openvino as ov
        from openvino import opset8 as ops
    except ImportError:
        return None
    rng = np.random.default_rng(0)
    x = rng.standard_normal((size, size), dtype=np.float32)
    with sigstack.kept():
        a = ops.parameter([size, size], ov.Type.f32)
        model = ov.Model([ops.matmul(a, ops.constant(rng.standard_normal((size, size), dtype=np.float32)),
                                     False, False)], [a])
        compiled = ov.Core().compile_model(model, "CPU", {"INFERENCE_NUM_THREADS": torch.get_num_threads(),
                                                          "INFERENCE_PRECISION_HINT": "f32"})
        request = compiled.create_infer_request()
        rate = product_rate(lambda r=request: r.infer([x]), size, repeats, warmup)
        del request, compiled, model
    return rate


def engines_matmul_peak(size: int = 2048, repeats: int = 5, warmup: int = 2) -> float:
    """The fp32 peak, GFLOP/s: the faster of :func:`denoiser.machine.matmul_peak` and
    :func:`openvino_matmul_peak` (torch's alone without OpenVINO), each on a ``size`` x ``size``
    product, the fastest of ``repeats`` after ``warmup``."""
    return max(matmul_peak(size, repeats, torch.float32, warmup), openvino_matmul_peak(size, repeats, warmup) or 0.0)
