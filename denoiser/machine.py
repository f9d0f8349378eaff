"""The machine a measurement ran on: the CPU's model, signature and vector ISA (:data:`ISA_FLAGS`,
whether bfloat16 is native) and its practical matmul peak (:func:`matmul_peak`), what every timing
report names and divides by.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import torch

from denoiser.measure import Clock, summarize

#: the CPU flags the benchmark tables record (what the vector units and bf16 paths can use)
ISA_FLAGS = ("avx2", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16", "amx_fp16")


#: environment variables that cap the instruction set a library's kernels use below what the CPU
#: has, and who reads each: a run under them times another CPU's code paths on this one (to see an
#: AVX2 CPU's profile on an AVX-512 machine); OIDN (pyoidn) reads none of them
ISA_CAPS = {"ONEDNN_MAX_CPU_ISA": "oneDNN: OpenVINO's CPU plugin and torch's convolutions",
            "DNNL_MAX_CPU_ISA": "oneDNN (its older name)",
            "MKL_ENABLE_INSTRUCTIONS": "MKL: torch's matrix products",
            "DENOISER_OVEXT_MARCH": "the project's OpenVINO extension, built for that -march"}


def isa_caps(environ=None) -> dict[str, str]:
    """``{variable: value}`` of the :data:`ISA_CAPS` set (non-empty) in ``environ`` (default
    ``os.environ``)."""
    import os

    environ = os.environ if environ is None else environ
    return {k: environ[k].strip() for k in ISA_CAPS if environ.get(k, "").strip()}


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo``, else :func:`platform.processor` or the machine
    type: what every timing report names its machine by."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_signature(cpuinfo: str | None = None) -> str:
    """``<vendor> family <f> model <m>`` from ``/proc/cpuinfo`` (``unknown`` when unreadable): tells
    apart CPUs that a virtual machine names alike (``Intel(R) Xeon(R) Processor``)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return "unknown"
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    if "vendor_id" not in fields:
        return "unknown"
    return f"{fields['vendor_id']} family {fields.get('cpu family', '?')} model {fields.get('model', '?')}"


def cpu_isa(cpuinfo: str | None = None) -> dict[str, bool]:
    """``{flag: present}`` for :data:`ISA_FLAGS` from ``/proc/cpuinfo`` (all False when unreadable)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            cpuinfo = ""
    flags: set[str] = set()
    for line in cpuinfo.splitlines():
        if line.startswith("flags"):
            flags.update(line.split(":", 1)[1].split())
            break
    return {f: f in flags for f in ISA_FLAGS}


def has_bf16(isa: dict[str, bool] | None = None) -> bool:
    """Whether the CPU computes bfloat16 natively (AVX512-BF16 or AMX-BF16; :func:`cpu_isa`):
    elsewhere a bf16 product runs on a slow reference path (minutes for a 2048 matmul)."""
    isa = cpu_isa() if isa is None else isa
    return bool(isa.get("avx512_bf16") or isa.get("amx_bf16"))


def product_rate(run: Callable[[], object], size: int, repeats: int = 5, warmup: int = 2) -> float:
    """GFLOP/s of ``run()``, one ``size`` x ``size`` by ``size`` x ``size`` matrix product
    (``2 size^3`` operations): the fastest of ``repeats`` calls after ``warmup`` untimed ones."""
    for _ in range(warmup):
        run()
    runs = []
    for _ in range(repeats):
        with Clock() as clock:
            run()
        runs.append(clock.wall)
    return 2 * size**3 / summarize(runs)["min"] / 1e9


def matmul_peak(size: int = 2048, repeats: int = 5, dtype: torch.dtype = torch.float32, warmup: int = 2) -> float:
    """GFLOP/s of a ``size`` x ``size`` matrix product ``torch.mm`` on the CPU in ``dtype``
    (:func:`product_rate`): torch's practical peak (with OpenVINO's beside it, the graphs' peak is
    :func:`denoiser.inference.peak.engines_matmul_peak`). The defaults (2048, two warm-up
    products, best of 5) are what every benchmark uses; a 1024 product, once warmed up only once,
    read 163-199 GFLOP/s on the same idle 2 cores."""
    a, b = torch.randn(size, size).to(dtype), torch.randn(size, size).to(dtype)
    return product_rate(lambda: torch.mm(a, b), size, repeats, warmup)
