"""CPU benchmark of the denoiser networks: ``python -m denoiser.commands.tools.bench_networks``.

::

    python -m denoiser.commands.tools.bench_networks
    python -m denoiser.commands.tools.bench_networks nets=[student] sizes=[1920x1080] repeats=2 kernels=false

A Hydra app over ``conf/bench_networks.yaml``. For the networks of ``nets`` (default student and
teacher: ``conf/net/<name>.yaml`` with their own kernel sizes) at every size of ``sizes``
(default 256x256, 1280x720 and 1920x1080) it prints, per variant: parameters, FLOPs per frame
(:func:`denoiser.measure.count_flops`), median milliseconds per frame (one recurrent step with
history, ``torch.inference_mode``, after warm-up), peak memory (the kernel's peak-RSS mark of
the process during the steps above its RSS before them: :class:`denoiser.measure.PeakRss`
``method="hwm"``; every configuration runs in its own subprocess for that), achieved GFLOP/s
and that as a fraction of the fp32 matmul peak measured in the same run (best of several
2048x2048 ``torch.mm``). Then the kernel application (fast shifted-view accumulation against
``F.unfold``) at 1080p (``kernels``), and the student before and after the CPU optimisations.
The tables are Markdown, padded for the console.

Variants (how a network is prepared and run; ``VARIANTS``). These are backends of the config
group ``conf/backends/`` of the same name (:func:`~denoiser.inference.backends.load_backend`, as
``denoiser-bench`` runs them; any other option of the group is a variant too, e.g. ``compile``):

* ``eager``: float32, NCHW, as trained (the baseline);
* ``channels_last``: float32, weights and inputs in channels-last (NHWC) memory format;
* ``channels_last_bf16``: channels-last and ``torch.autocast("cpu", bfloat16)`` for the U-Net
  (uses AMX/AVX512-BF16 through oneDNN where the CPU has it); inputs, softmax and filtering stay
  float32 (see ``denoiser/nn``), so the output keeps its HDR range;
* ``openvino_f32``, ``openvino_bf16``: the exported step graph compiled by OpenVINO
  (:class:`~denoiser.inference.backends.OpenVinoBackend`, fused or plain graph; export and compilation
  happen before and in the warm-up steps; bf16 needs AVX512-BF16/AMX).

These two are not backends but weight-format experiments (they convert the network's weights):

* ``channels_last_bf16_weights``: channels-last with the network's weights converted to
  bfloat16 (no autocast: no per-call weight casts); the Denoiser feeds the U-Net in its weights'
  dtype and still filters in float32;
* ``channels_last_bf16_weights_compiled``: the same with ``torch.compile(net.step)`` (inductor
  fuses the elementwise work); compiling takes minutes on 2 cores, so it is not in the default
  ``variants`` and its warm-up (3 steps, compiling both the first-frame and the recurrent
  graph) is reported separately as ``warm-up s``.

Denormal floats are flushed (``torch.set_flush_denormal(True)``) in every variant. ``repeats``
applies to the student; the teacher always runs 1 warm-up + 1 timed step, it takes many seconds
per frame on 2 cores. Each measurement is a job ``{kind: net|kernel, ...}`` that the parent
passes to a fresh ``python -m denoiser.commands.tools.bench_networks job={...}``, which prints its
result as one JSON line.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from contextlib import nullcontext

from omegaconf import DictConfig, OmegaConf

from denoiser.errors import ConfigError, first_line
from denoiser.measure import Clock, PeakRss, clock_steps, summarize
from denoiser.tables import markdown_table


def _backend(name):
    """A variant that is the backend ``conf/backends/<name>.yaml`` (:func:`~denoiser.inference.backends.load_backend`)."""
    def prepare(net, frame):
        import types

        import torch

        from denoiser.inference.backends import load_backend

        backend = load_backend(name, "variants")
        reason = backend.available()
        if reason:
            raise RuntimeError(reason)
        stepper = backend.prepare(net, frame, torch.get_num_threads())  # as many threads as torch
        return types.SimpleNamespace(step=stepper.step), frame, nullcontext

    return prepare


def _channels_last_bf16_weights(net, frame):
    """Not a backend: a weight-format experiment (the weights stored as bfloat16, no autocast), channels-last."""
    import torch

    net = net.to(memory_format=torch.channels_last).to(torch.bfloat16)
    frame = {k: v.contiguous(memory_format=torch.channels_last) if v.dim() == 4 else v
             for k, v in frame.items()}
    return net, frame, nullcontext


def _channels_last_bf16_weights_compiled(net, frame):
    """Not a backend: the weight-format experiment above under ``torch.compile(net.step)``."""
    import types

    import torch

    net, frame, context = _channels_last_bf16_weights(net, frame)
    return types.SimpleNamespace(step=torch.compile(net.step, dynamic=False)), frame, context


#: the variants that are backends of the group ``conf/backends/`` (the same name there)
BACKEND_VARIANTS = ("eager", "channels_last", "channels_last_bf16", "openvino_f32", "openvino_bf16")
#: variant name -> prepare(net, frame) -> (net, frame, context factory); the two weight-format
#: experiments are not backends (they change the network's weights, not how it is run)
VARIANTS = {**{name: _backend(name) for name in BACKEND_VARIANTS},
            "channels_last_bf16_weights": _channels_last_bf16_weights,
            "channels_last_bf16_weights_compiled": _channels_last_bf16_weights_compiled}
def variant(name: str):
    """The prepare function of a variant: :data:`VARIANTS`, else any other backend of ``conf/backends/``."""
    return VARIANTS.get(name) or _backend(name)


#: warm-up steps per variant (default 1): a compiled step compiles one graph for the first
#: frame (no state) and one for later frames; OpenVINO compiles in the first step
WARMUP = {"channels_last_bf16_weights_compiled": 3, "openvino_f32": 2, "openvino_bf16": 2}
#: the network that runs eager only, 1 warm-up + 1 timed step
SLOW_NET = "teacher"
#: matmul peak: matrix size, warm-up products, timed products (the best counts)


# ----------------------------------------------------------------------------- workers (one per process)


def run_net(job: dict) -> dict:
    """Worker: time ``step`` of one net/size/variant; returns ms per run and the RSS growth."""
    import torch

    from denoiser.configs import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.recurrent import Stepper

    torch.set_flush_denormal(True)
    net = build_net(compose_net_config(job["net"])).eval()
    frame = random_frame(1, job["height"], job["width"])
    from denoiser.inference import backends

    backends.SEARCHPATH[:] = job.get("searchpath", [])
    net, frame, context = variant(job["variant"])(net, frame)
    with PeakRss(method="hwm") as mem, torch.inference_mode(), context():
        warm, timed = clock_steps(Stepper(net.step), [frame], job["warmup"], job["repeats"])
    return {"ms": [c.wall * 1e3 for c in timed], "cpu_ms": [c.cpu * 1e3 for c in timed], "peak_mb": mem.megabytes,
            "warmup_s": sum(c.wall for c in warm)}


def run_kernel(job: dict) -> dict:
    """Worker: time one kernel application (fast or unfold) on a ``[1, C, H, W]`` image."""
    import torch

    from denoiser.nn.kernels import apply_kernels, apply_kernels_unfold

    torch.set_flush_denormal(True)
    impl = {"fast": apply_kernels, "unfold": apply_kernels_unfold}[job["impl"]]
    k, h, w = job["k"], job["height"], job["width"]
    x = torch.rand(1, job["channels"], h, w)
    logits = torch.randn(1, k * k, h, w)
    times = []
    with PeakRss(method="hwm") as mem, torch.inference_mode():
        impl(x, logits)
        for _ in range(job["repeats"]):
            with Clock() as clock:
                impl(x, logits)
            times.append(clock.wall)
    return {"ms": [t * 1e3 for t in times], "peak_mb": mem.megabytes}


WORKERS = {"net": run_net, "kernel": run_kernel}


def run_job(job: dict) -> dict:
    """Run one job in this process and print its result as the last line of stdout (JSON)."""
    try:
        result = WORKERS[job["kind"]](job)
    except Exception as exc:  # noqa: BLE001 - reported in the parent's table, not fatal
        result = {"error": f"{type(exc).__name__}: {first_line(exc)}"}
    print(json.dumps(result))
    return result


def in_subprocess(job: dict) -> dict:
    """Run one job in a fresh interpreter (clean peak-RSS accounting)."""
    override = "job={" + ",".join(f"{k}:{v}" for k, v in job.items()) + "}"
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.tools.bench_networks", override],
                          capture_output=True, text=True, check=False)
    lines = proc.stdout.strip().splitlines()
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or [f"exit status {proc.returncode}"]
        return {"error": tail[0]}
    return json.loads(lines[-1])


# ----------------------------------------------------------------------------- parent


def parse_size(name: str) -> tuple[int, int]:
    """``"WxH"`` -> ``(H, W)``."""
    try:
        w, h = (int(v) for v in str(name).lower().split("x"))
    except ValueError:
        raise ConfigError(f"sizes: {name!r} is not WxH (e.g. 1280x720)") from None
    return h, w


def net_jobs(cfg: DictConfig) -> list[dict]:
    from denoiser.inference.backends import searchpath

    jobs = []
    for name in cfg.nets:
        slow = name == SLOW_NET
        for size in cfg.sizes:
            h, w = parse_size(size)
            for variant in (["eager"] if slow else cfg.variants):
                jobs.append({"kind": "net", "net": name, "height": h, "width": w, "variant": variant,
                             "warmup": WARMUP.get(variant, 1), "repeats": 1 if slow else int(cfg.repeats),
                             "searchpath": searchpath()})  # the worker finds the same backend group
    return jobs


def size_name(job: dict) -> str:
    return f"{job['width']}x{job['height']}"


def net_rows(results: list[tuple[dict, dict]], peak: float, flops: dict, params: dict) -> list[dict]:
    rows = []
    for job, res in results:
        f = flops[(job["net"], size_name(job))]
        row = {"net": job["net"], "variant": job["variant"], "size": size_name(job), "params": f"{params[job['net']]:,}",
               "gflop": f / 1e9}
        if "error" in res:
            row["ms"] = "error"
        else:
            ms = summarize(res["ms"])["median"]
            row.update(ms=ms, cpu_ms=summarize(res["cpu_ms"])["median"], runs=len(res["ms"]), peak_mb=res["peak_mb"],
                       gflops=f / (ms / 1e3) / 1e9, warmup_s=res["warmup_s"])
            row["of_peak"] = row["gflops"] / peak
        rows.append(row)
    return rows


NET_COLUMNS = ["net", "variant", "size", "params", "gflop", "ms", "cpu_ms", "runs", "peak_mb", "gflops", "of_peak",
               "warmup_s"]
FORMATS = {"gflop": ".1f", "ms": ".0f", "cpu_ms": ".0f", "peak_mb": ".0f", "gflops": ".1f", "of_peak": ".1%",
           "warmup_s": ".0f", "before_ms": ".0f", "after_ms": ".0f", "speedup": ".2f"}
HEADERS = {"gflop": "GFLOP/frame", "ms": "ms/frame", "cpu_ms": "CPU ms", "peak_mb": "peak MB", "gflops": "GFLOP/s",
           "of_peak": "of fp32 mm peak", "warmup_s": "warm-up s", "before_ms": "before ms", "after_ms": "after ms",
           "speedup": "speed-up (x)", "impl": "implementation"}


def before_after(rows: list[dict], sizes: list[str], variants: list[str]) -> list[dict]:
    """The student at each size: eager fp32 against its fastest variant."""
    by = {(r["net"], r["size"], r["variant"]): r for r in rows if r["ms"] != "error"}
    out = []
    for size in sizes:
        base = by.get(("student", size, "eager"))
        cands = [by[("student", size, v)] for v in variants if ("student", size, v) in by]
        if base is None or not cands:
            continue
        best = min(cands, key=lambda r: r["ms"])
        out.append({"size": size, "before_ms": base["ms"], "variant": best["variant"], "after_ms": best["ms"],
                    "speedup": base["ms"] / best["ms"], "of_peak": best["of_peak"]})
    return out


def kernel_rows() -> list[dict]:
    from tqdm import tqdm

    rows = []
    jobs = [{"kind": "kernel", "impl": impl, "k": k, "channels": 4, "height": 1080, "width": 1920, "repeats": 3}
            for k in (5, 9) for impl in ("fast", "unfold")]
    for job in tqdm(jobs, desc="kernels", file=sys.stderr):
        res = in_subprocess(job)
        row = {"impl": job["impl"], "k": job["k"]}
        row.update({"ms": "error", "peak_mb": res["error"][:40]} if "error" in res else
                   {"ms": summarize(res["ms"])["median"], "peak_mb": res["peak_mb"]})
        rows.append(row)
    return rows


def run(cfg: DictConfig) -> list[dict]:
    """The ``bench_networks`` task (or, with ``job``, one measurement); returns the network rows."""
    if cfg.get("job") is not None:
        return [run_job(OmegaConf.to_container(cfg.job))]
    import torch
    from tqdm import tqdm

    from denoiser.configs import build_net, compose_net_config
    from denoiser.inference.backends import backend_names
    from denoiser.machine import has_bf16, matmul_peak
    from denoiser.measure import count_flops

    names = [*backend_names(), *(v for v in VARIANTS if v not in BACKEND_VARIANTS)]
    unknown = [v for v in cfg.variants if v not in names]
    if unknown:
        raise ConfigError(f"variants: unknown {unknown}, choose from {names}")
    sizes = {str(s): parse_size(s) for s in cfg.sizes}
    flops, params = {}, {}
    for name in cfg.nets:
        net = build_net(compose_net_config(name), f"nets: {name}")
        params[name] = net.num_parameters()
        for size, (h, w) in sizes.items():
            flops[(name, size)] = count_flops(net, h, w)
        del net

    started = time.time()
    peak = matmul_peak()
    # a CPU without native bf16 runs the bf16 product on a reference path: minutes, and no peak
    bf16 = f"bf16 {matmul_peak(dtype=torch.bfloat16):.1f} GFLOP/s" if has_bf16() else \
        "bf16 not measured (the CPU has no AVX512-BF16 or AMX-BF16)"
    print(f"# bench_networks: torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}, load average {os.getloadavg()[0]:.1f}")
    print(f"# matmul peak (2048x2048 torch.mm, best of 5): fp32 {peak:.1f} GFLOP/s, {bf16}\n")

    results = []
    for job in tqdm(net_jobs(cfg), desc="networks", file=sys.stderr):
        res = in_subprocess(job)
        results.append((job, res))
        if "error" in res:
            print(f"  {job['net']} {size_name(job)} {job['variant']}: {res['error']}", file=sys.stderr)
    rows = net_rows(results, peak, flops, params)
    print("## Networks (one step with history, batch 1, CPU, inference mode)\n")
    print("ms/frame: median wall clock; CPU ms: process CPU time of the same step (both threads; on an\n"
          "idle machine about threads x wall, lower when other processes compete for the cores)\n")
    print(markdown_table(rows, NET_COLUMNS, FORMATS, HEADERS, align=True))
    if "student" in params and SLOW_NET in params:
        ratios = ", ".join(f"{s} {flops[(SLOW_NET, s)] / flops[('student', s)]:.1f}x" for s in sizes)
        print(f"teacher/student FLOPs: {ratios}; parameters {params[SLOW_NET] / params['student']:.1f}x\n")

    if "student" in params and len(cfg.variants) > 1 and "eager" in cfg.variants:
        print("## Student: before (eager fp32) and after (best variant)\n")
        print(markdown_table(before_after(rows, list(sizes), list(cfg.variants)),
                             ["size", "before_ms", "variant", "after_ms", "speedup", "of_peak"], FORMATS,
                             {**HEADERS, "variant": "best variant", "of_peak": "after, of fp32 mm peak"}, align=True))

    if cfg.kernels:
        print("## Kernel application at 1920x1080, 4 channels (color + the pyramid's constant channel)\n")
        print(markdown_table(kernel_rows(), ["impl", "k", "ms", "peak_mb"], FORMATS, HEADERS, align=True))
    print(f"# total benchmark time {time.time() - started:.0f} s, load average now {os.getloadavg()[0]:.1f}")
    return rows


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "bench_networks")()


if __name__ == "__main__":
    main()
