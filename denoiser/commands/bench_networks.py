"""CPU benchmark of the denoiser networks: ``python -m denoiser.commands.bench_networks``.

For the student and the teacher (``conf/net/{student,teacher}.yaml`` with their kernel sizes) at
256x256, 1280x720 and 1920x1080 it prints, per variant: parameters, FLOPs per frame
(``FlopCounterMode`` on fake tensors), median milliseconds per frame (one ``step`` with history,
``torch.inference_mode``, after warm-up), peak memory (the process's peak RSS during the steps above
its RSS before them, with the peak mark reset through ``/proc/self/clear_refs``; every
configuration runs in its own subprocess), achieved GFLOP/s and that as a fraction of the fp32 matmul peak measured in the
same run (best of several 2048x2048 ``torch.mm``). Then the kernel application (fast shifted-view
accumulation against ``F.unfold``) at 1080p, and the student before and after the CPU
optimisations.

Variants (how a network is prepared and run; ``VARIANTS``):

* ``eager``: float32, NCHW, as trained (the baseline);
* ``channels_last``: float32, weights and inputs in channels-last (NHWC) memory format;
* ``channels_last_bf16``: channels-last and ``torch.autocast("cpu", bfloat16)`` for the U-Net
  (uses AMX/AVX512-BF16 through oneDNN where the CPU has it); inputs, softmax and filtering stay
  float32 (see ``denoiser/nn``), so the output keeps its HDR range;
* ``channels_last_bf16_weights``: channels-last with the network's weights converted to
  bfloat16 (no autocast: no per-call weight casts); the Denoiser feeds the U-Net in its weights'
  dtype and still filters in float32;
* ``channels_last_bf16_weights_compiled``: the same with ``torch.compile(net.step)`` (inductor
  fuses the elementwise work); compiling takes minutes on 2 cores, so it is not in the default
  ``--variants`` and its warm-up (3 steps, compiling both the first-frame and the recurrent
  graph) is reported separately as ``warm-up s``.

Denormal floats are flushed (``torch.set_flush_denormal(True)``) in every variant.

Options: ``--nets student,teacher`` ``--sizes 256x256,1280x720,1920x1080``
``--variants eager,channels_last,...`` ``--repeats N`` (student; the teacher
always runs 1 warm-up + 1 timed step, it takes many seconds per frame on 2 cores) ``--no-kernels``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import time
from contextlib import nullcontext

SIZES = {"256x256": (256, 256), "1280x720": (720, 1280), "1920x1080": (1080, 1920)}
NETS = {"student": ["net=student", "kernel=student"], "teacher": ["net=teacher", "kernel=teacher"]}


def _eager(net, frame):
    return net, frame, nullcontext


def _channels_last(net, frame):
    import torch

    net = net.to(memory_format=torch.channels_last)
    frame = {k: v.contiguous(memory_format=torch.channels_last) if v.dim() == 4 else v
             for k, v in frame.items()}
    return net, frame, nullcontext


def _channels_last_bf16(net, frame):
    import torch

    net, frame, _ = _channels_last(net, frame)
    return net, frame, lambda: torch.autocast("cpu", dtype=torch.bfloat16)


def _channels_last_bf16_weights(net, frame):
    import torch

    net, frame, _ = _channels_last(net, frame)
    return net.to(torch.bfloat16), frame, nullcontext


def _channels_last_bf16_weights_compiled(net, frame):
    import types

    import torch

    net, frame, context = _channels_last_bf16_weights(net, frame)
    return types.SimpleNamespace(step=torch.compile(net.step, dynamic=False)), frame, context


#: variant name -> prepare(net, frame) -> (net, frame, context factory)
VARIANTS = {"eager": _eager, "channels_last": _channels_last, "channels_last_bf16": _channels_last_bf16,
            "channels_last_bf16_weights": _channels_last_bf16_weights,
            "channels_last_bf16_weights_compiled": _channels_last_bf16_weights_compiled}
#: warm-up steps per variant (default 1): a compiled step compiles one graph for the first
#: frame (no state) and one for later frames
WARMUP = {"channels_last_bf16_weights_compiled": 3}
#: variants run by default (compiling takes minutes on 2 cores: ask for it with --variants)
DEFAULT_VARIANTS = ["eager", "channels_last", "channels_last_bf16", "channels_last_bf16_weights"]


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    raise KeyError(key)


def start_peak() -> float:
    """Reset the process's peak-RSS mark (Linux ``/proc/self/clear_refs``); returns the RSS in MB.

    Without procfs, falls back to ``ru_maxrss`` (which cannot be reset: peaks of earlier
    allocations may then hide smaller ones).
    """
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return _status_mb("VmRSS")
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def peak_mb() -> float:
    """Peak RSS in MB since :func:`start_peak`."""
    try:
        return _status_mb("VmHWM")
    except OSError:
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def matmul_peak(n: int = 2048, repeats: int = 5, dtype_name: str = "float32") -> float:
    """Best GFLOP/s of ``torch.mm`` on two ``n x n`` matrices."""
    import torch

    dtype = getattr(torch, dtype_name)
    a, b = torch.randn(n, n).to(dtype), torch.randn(n, n).to(dtype)
    for _ in range(2):
        torch.mm(a, b)
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        torch.mm(a, b)
        best = min(best, time.perf_counter() - t)
    return 2 * n**3 / best / 1e9


def run_net(job: dict) -> dict:
    """Worker: time ``step`` of one net/size/variant; returns ms per run and the RSS growth."""
    import torch

    from denoiser.commands.netstats import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.runner import RecurrentRunner

    torch.set_flush_denormal(True)
    net = build_net(compose_net_config(NETS[job["net"]])).eval()
    frame = random_frame(1, job["height"], job["width"])
    net, frame, context = VARIANTS[job["variant"]](net, frame)
    base = start_peak()
    times, cpu = [], []
    runner = RecurrentRunner(net.step)
    with torch.inference_mode(), context():
        started = time.perf_counter()
        for _ in runner.run((frame, i == 0) for i in range(job["warmup"])):
            pass
        warmup_s = time.perf_counter() - started
        t, c = time.perf_counter(), time.process_time()
        for _ in runner.run((frame, False) for _ in range(job["repeats"])):
            times.append(time.perf_counter() - t)
            cpu.append(time.process_time() - c)
            t, c = time.perf_counter(), time.process_time()
    return {"ms": [x * 1e3 for x in times], "cpu_ms": [x * 1e3 for x in cpu], "peak_mb": peak_mb() - base,
            "warmup_s": warmup_s}


def run_kernel(job: dict) -> dict:
    """Worker: time one kernel application (fast or unfold) on a ``[1, C, H, W]`` image."""
    import torch

    from denoiser.nn.kernels import apply_kernels, apply_kernels_unfold

    torch.set_flush_denormal(True)
    impl = {"fast": apply_kernels, "unfold": apply_kernels_unfold}[job["impl"]]
    k, h, w = job["k"], job["height"], job["width"]
    x = torch.rand(1, job["channels"], h, w)
    logits = torch.randn(1, k * k, h, w)
    base = start_peak()
    times = []
    with torch.inference_mode():
        impl(x, logits)
        for _ in range(job["repeats"]):
            t = time.perf_counter()
            impl(x, logits)
            times.append(time.perf_counter() - t)
    return {"ms": [x * 1e3 for x in times], "peak_mb": peak_mb() - base}


WORKERS = {"net": run_net, "kernel": run_kernel}


def in_subprocess(job: dict) -> dict:
    """Run one job in a fresh interpreter (clean peak-RSS accounting)."""
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.bench_networks", "--worker", json.dumps(job)],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["(no output)"]
        return {"error": tail[0]}
    return json.loads(proc.stdout.strip().splitlines()[-1])


def fmt_row(cells, widths):
    return "| " + " | ".join(str(c).rjust(w) if i else str(c).ljust(w)
                             for i, (c, w) in enumerate(zip(cells, widths))) + " |"


def print_table(header, rows):
    widths = [max(len(str(r[i])) for r in [header, *rows]) for i in range(len(header))]
    print(fmt_row(header, widths))
    print("|" + "|".join("-" * (w + 2) for w in widths) + "|")
    for r in rows:
        print(fmt_row(r, widths))
    print()


def net_rows(args, peak, flops, params):
    from tqdm import tqdm

    jobs = []
    for name in args.nets:
        variants = args.variants if name == "student" else ["eager"]
        for size in args.sizes:
            for variant in variants:
                h, w = SIZES[size]
                teacher = name == "teacher"
                jobs.append({"kind": "net", "net": name, "height": h, "width": w, "variant": variant,
                             "warmup": WARMUP.get(variant, 1), "repeats": 1 if teacher else args.repeats, "size": size})
    results = []
    for job in tqdm(jobs, desc="networks", file=sys.stderr):
        res = in_subprocess(job)
        results.append((job, res))
        if "error" in res:
            print(f"  {job['net']} {job['size']} {job['variant']}: {res['error']}", file=sys.stderr)
    rows = []
    for job, res in results:
        f = flops[(job["net"], job["size"])]
        if "error" in res:
            rows.append([job["net"], job["variant"], job["size"], f"{params[job['net']]:,}", f"{f / 1e9:.1f}",
                         "error", "", "", "", "", "", ""])
            continue
        ms = statistics.median(res["ms"])
        gflops = f / (ms / 1e3) / 1e9
        rows.append([job["net"], job["variant"], job["size"], f"{params[job['net']]:,}", f"{f / 1e9:.1f}",
                     f"{ms:.0f}", f"{statistics.median(res['cpu_ms']):.0f}", f"{len(res['ms'])}",
                     f"{res['peak_mb']:.0f}", f"{gflops:.1f}",
                     f"{100 * gflops / peak:.1f}%", f"{res['warmup_s']:.0f}"])
    return results, rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m denoiser.commands.bench_networks", description=__doc__.splitlines()[0])
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--nets", default="student,teacher")
    parser.add_argument("--sizes", default=",".join(SIZES))
    parser.add_argument("--variants", default=",".join(DEFAULT_VARIANTS),
                        help=f"student variants, from {list(VARIANTS)}")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-kernels", action="store_true")
    args = parser.parse_args(argv)
    if args.worker:
        job = json.loads(args.worker)
        print(json.dumps(WORKERS[job["kind"]](job)))
        return
    args.nets, args.sizes, args.variants = (s.split(",") for s in (args.nets, args.sizes, args.variants))
    for group, names, known in (("--nets", args.nets, NETS), ("--sizes", args.sizes, SIZES),
                                ("--variants", args.variants, VARIANTS)):
        unknown = [n for n in names if n not in known]
        if unknown:
            parser.error(f"{group}: unknown {unknown}, choose from {list(known)}")

    import torch

    from denoiser.commands.netstats import build_net, compose_net_config, count_flops

    started = time.time()
    peak = matmul_peak()
    peak_bf16 = matmul_peak(dtype_name="bfloat16")
    print(f"# nn_bench: torch {torch.__version__}, {torch.get_num_threads()} threads, "
          f"{platform.processor() or platform.machine()}, load average {os.getloadavg()[0]:.1f}")
    print(f"# matmul peak (2048x2048 torch.mm, best of 5): fp32 {peak:.1f} GFLOP/s, bf16 {peak_bf16:.1f} GFLOP/s\n")

    flops, params = {}, {}
    for name in args.nets:
        net = build_net(compose_net_config(NETS[name]))
        params[name] = net.num_parameters()
        for size in args.sizes:
            flops[(name, size)] = count_flops(net, *SIZES[size])
        del net

    results, rows = net_rows(args, peak, flops, params)
    print("## Networks (one step with history, batch 1, CPU, inference mode)\n")
    print("ms/frame: median wall clock; CPU ms: process CPU time of the same step (both threads; on an\n"
          "idle machine about threads x wall, lower when other processes compete for the cores)\n")
    print_table(["net", "variant", "size", "params", "GFLOP/frame", "ms/frame", "CPU ms", "runs", "peak MB",
                 "GFLOP/s", "of fp32 mm peak", "warm-up s"], rows)
    if "student" in params and "teacher" in params:
        ratios = ", ".join(f"{s} {flops[('teacher', s)] / flops[('student', s)]:.1f}x" for s in args.sizes)
        print(f"teacher/student FLOPs: {ratios}; parameters {params['teacher'] / params['student']:.1f}x\n")

    by = {(j["net"], j["size"], j["variant"]): r for j, r in results if "error" not in r}
    if "student" in params and len(args.variants) > 1 and "eager" in args.variants:
        print("## Student: before (eager fp32) and after (best variant)\n")
        out = []
        for size in args.sizes:
            base = by.get(("student", size, "eager"))
            cands = {v: statistics.median(by[("student", size, v)]["ms"]) for v in args.variants
                     if ("student", size, v) in by}
            if base is None or not cands:
                continue
            best = min(cands, key=cands.get)
            b_ms = statistics.median(base["ms"])
            f = flops[("student", size)]
            out.append([size, f"{b_ms:.0f}", best, f"{cands[best]:.0f}", f"{b_ms / cands[best]:.2f}x",
                        f"{100 * f / (cands[best] / 1e3) / 1e9 / peak:.1f}%"])
        print_table(["size", "before ms", "best variant", "after ms", "speed-up", "after, of fp32 mm peak"], out)

    if not args.no_kernels:
        from tqdm import tqdm

        print("## Kernel application at 1920x1080, 4 channels (color + the pyramid's constant channel)\n")
        krows = []
        jobs = [{"kind": "kernel", "impl": impl, "k": k, "channels": 4, "height": 1080, "width": 1920,
                 "repeats": 3} for k in (5, 9) for impl in ("fast", "unfold")]
        for job in tqdm(jobs, desc="kernels", file=sys.stderr):
            res = in_subprocess(job)
            if "error" in res:
                krows.append([job["impl"], job["k"], "error", res["error"][:40]])
                continue
            krows.append([job["impl"], job["k"], f"{statistics.median(res['ms']):.0f}", f"{res['peak_mb']:.0f}"])
        print_table(["implementation", "k", "ms", "peak MB"], krows)
    print(f"# total benchmark time {time.time() - started:.0f} s, load average now {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
