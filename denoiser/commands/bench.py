"""``denoiser-bench``: what accuracy costs in time, networks and OIDN timed on the same frames.

::

    denoiser-bench 'ckpt={teacher: t.ckpt, student: s.ckpt}' eval_csv=eval/metrics.csv data=demo
    denoiser-bench ckpt=[s.ckpt] sizes=[[256,256]] repeats=9 use_backends=[eager,onnxruntime]

For every method (OIDN fast/balanced/high from ``baselines``, denoiser-eval's list in
``conf/baselines/default.yaml`` whose noisy input ``conf/bench.yaml`` sets to null, as it costs
nothing to time; each checkpoint of ``ckpt`` and each untrained config variant of
``variants``), every size of ``sizes`` ``[H, W]`` and, for networks, every backend of
``use_backends`` (names of the config group ``conf/backends/``, one YAML each, loaded by
:func:`denoiser.inference.backends.load_backend`: PyTorch eager fp32, channels_last, bfloat16 autocast,
``torch.compile``, ONNX Runtime, OpenVINO f32 and bf16, whose labels say ``(fused)`` or ``(plain)`` graph;
and CUDA backends that run only where a GPU is present), the benchmark measures:

* **ms per frame** (median, min and max) of ``repeats`` recurrent steps after ``warmup`` steps
  (state carried, as in real use), with one thread count asked of everyone (``threads``; torch,
  OIDN's ``numThreads``, ONNX Runtime's intra-op threads, OpenVINO's ``INFERENCE_NUM_THREADS``);
  the ``threads`` column is what each engine reports it uses, read back from it. The timed
  steps are **interleaved**: per size every method is prepared and warmed up first, then each of
  the ``repeats`` rounds times every method once, in an order rotated by the round
  (:func:`~denoiser.measure.round_robin`), so a slow phase of a shared machine falls on every
  method alike. Every process-wide setting is the same for every method (none is changed by a
  backend);
* the **speed-up** vs ``compare.baseline`` (OIDN-fast) of every CPU row, paired per round: the
  median over rounds of ``baseline time / method time`` in the same round, with a
  distribution-free interval of that median from the order statistics of the per-round ratios
  (:func:`~denoiser.measure.median_interval`: at least 95%; with the default 7 rounds the min-max
  over rounds, 98.4%). A network's fp32 rows sit beside its bf16 rows; the report's student vs
  OIDN table labels each row with both precisions (OIDN's CPU device computes in fp32, in fp16
  only with AMX-FP16), so the like-with-like figure is the fp32 row's;
* the **harness check** (``check_oidn``): pyoidn's ``filter.execute()`` alone on the same frames,
  bound once to its arrays (no copies in the timed call), timed in the same rounds as the
  benchmark's OIDN-fast path; ``report.md`` says what the harness adds (median of the paired
  rounds). The benchmark hands OIDN its frames in OIDN's interleaved ``[H, W, 3]`` layout before
  the clock starts, as a renderer would;
* **GFLOP** per frame (convolutions and matrix products, ``torch.utils.flop_counter``) and
  the achieved GFLOP/s as a fraction of this machine's fp32 matmul peak, measured before and
  after the methods (the larger counts);
* **parameters** and **peak memory**: the peak resident set size during the method's warm-up
  steps above the level before them (all methods of the size prepared: weights loaded, graph
  exported or compiled), sampled every 2 ms (CPU); ``torch.cuda.max_memory_allocated`` (CUDA).
  Memory the allocator kept from an earlier run is not counted again, so read it as "at least";
  the process holds every method of a size at once;
* the **versions** of torch, ONNX Runtime, OpenVINO and OIDN (and pyoidn), the CPU's model and ISA
  flags (``avx2``, ``avx512f``, ``avx512_bf16``, ``amx_bf16``, ``amx_fp16`` ...): the report's
  machine line, ``bench.json``'s ``machine``, and each row's ``engine`` column.

Frames: ``frames`` consecutive frames of one test sequence (``sequence``, default the
first), resampled to each size (bilinear; normals re-normalised, motion scaled): the cost of
these networks and of OIDN does not depend on the content, and every method sees the same
frames. Sizes can be skipped per method (``skip``), since a teacher at 1080p on 2 cores takes
minutes, and a method's backends restricted (``method_backends``).

Quality is measured through the same backend and precision as the time (``quality: true``,
the default): for every checkpoint and backend that ran, a fresh prepared network (the same
``backend.prepare``) steps through the recurrent runner over the evaluation sequences of
``split`` at their native size, as ``denoiser-eval`` does (state reset at the first frame and
at cuts, the first ``quality_warmup`` frames after each reset excluded, PSNR of
:mod:`denoiser.metrics` through :class:`denoiser.report.evaluation.Evaluation`); ``quality_frames``
(first N frames of each sequence) and ``max_sequences`` keep it cheap. That is the ``psnr``
column, the same for every size of a (method, backend) pair (``psnr_from``: ``backend``). A
bf16 speed-up thus comes with the PSNR of bf16. ``denoiser-eval``'s eager fp32 PSNR
(``eval_csv``, the ``mean`` rows, joined by method name) is kept beside it as ``psnr_eval``;
the baselines (OIDN) and, with ``quality: false``, the networks take their ``psnr`` from it
(``psnr_from``: ``eval``). Untrained ``variants`` are not scored.

Outputs in ``out_dir``: ``bench.csv`` (one row per method, backend, device and size),
``bench.json`` (the machine, versions and ISA flags, every row with its per-round times
``times_ms``, the speed-ups and the harness checks), ``report.md`` (machine, harness check, the
student vs OIDN-fast table at every size: each of the student's CPU rows, fp32 first, with the
paired speed-up and its interval) and ``accuracy_vs_time.png`` (PSNR against ms per frame at
``plot_size`` on a log axis; see :mod:`denoiser.report.plot_tradeoff`).
"""

from __future__ import annotations

import math
from pathlib import Path

import torch
from omegaconf import DictConfig

from denoiser.configs import plain
from denoiser.inference.peak import engines_matmul_peak
from denoiser.machine import cpu_isa
from denoiser.report.bench_report import (
    COLUMNS,
    FORMATS,
    HEADERS,
    check_lines,
    engine_versions,
    machine_description,
    machine_info,
    profile_rows,
    write_json,
    write_report,
)
from denoiser.report.bench_timing import baselines_use_samples, load_frames, run_benchmark
from denoiser.report.evaluation import eval_means
from denoiser.report.speedup import default_student, network_labels, ratio_rows
from denoiser.tables import markdown_table, write_csv


def run(cfg: DictConfig) -> list[dict]:
    """The ``denoiser-bench`` task; returns the table rows."""
    threads = int(cfg.threads) if cfg.get("threads") else torch.get_num_threads()
    torch.set_num_threads(threads)
    out_dir = Path(cfg.out_dir)
    quality = eval_means(cfg.get("eval_csv"))
    seq_name, frames = load_frames(cfg.data, cfg.split, cfg.get("sequence"), int(cfg.warmup) + int(cfg.repeats),
                                   samples=baselines_use_samples(cfg.get("baselines")))
    # the peak before and after the methods, the larger one counts (a share of the peak must
    # not look better because the machine was briefly slower when the peak was taken)
    peak_before = engines_matmul_peak()
    versions, isa = engine_versions(), cpu_isa()
    rows, checks = run_benchmark(cfg, frames, threads, versions, isa)
    peak = max(peak_before, engines_matmul_peak())
    for r in rows:
        if r.get("device") == "cpu" and "gflops_per_s" in r:
            r["peak_fraction"] = r["gflops_per_s"] / peak
    for r in rows:
        q = quality.get(r["method"])
        r["psnr_eval"] = float(q["psnr"]) if q and "psnr" in q else float("nan")
        if "psnr" not in r:  # baselines, and networks when quality is false: denoiser-eval's (eager fp32)
            r["psnr"] = r["psnr_eval"]
            r["psnr_from"] = "eval" if not math.isnan(r["psnr"]) else ""
        r.setdefault("status", "ok")
    write_csv(out_dir / "bench.csv", rows, COLUMNS)
    if any("profile" in r for r in rows):
        write_csv(out_dir / "profile.csv", profile_rows(rows), ["method", "backend", "height", "width", "op_type", "ms",
                                                                "share"])
    plot_path = None
    if any(not math.isnan(r["psnr"]) for r in rows):
        from denoiser.report.plot_tradeoff import plot_accuracy_vs_time

        plot_size = tuple(int(v) for v in (cfg.get("plot_size") or cfg.sizes[-1]))
        noisy = quality.get(cfg.get("noisy_label", "noisy input"))
        plot_path = plot_accuracy_vs_time(out_dir / "accuracy_vs_time.png", rows, plot_size,
                                          curves=plain(cfg.get("curves")) or {},
                                          noisy_psnr=float(noisy["psnr"]) if noisy else None,
                                          title=f"{seq_name} frames at {plot_size[1]}x{plot_size[0]}, {threads} CPU thread(s)")
    student = cfg.compare.student or default_student(network_labels(rows))
    ratios = ratio_rows(rows, student, cfg.compare.baseline, cfg.sizes) if student else []
    info = machine_info(threads, peak, versions, isa)
    machine = machine_description(info)
    write_report(out_dir, rows, ratios, machine, cfg, plot_path, checks, caps=info["isa_caps"])
    write_json(out_dir / "bench.json", {"machine": info, "warmup": int(cfg.warmup), "repeats": int(cfg.repeats),
                                        "interleaved": True, "rows": rows, "speedups": ratios, "harness_checks": checks})
    print(machine)
    print(markdown_table(rows, ["method", "backend", "dtype", "device", "height", "width", "ms_median", "ms_min", "ms_max",
                                "speedup_text", "gflop", "peak_mb", "peak_fraction", "psnr", "threads", "status"],
                         FORMATS, HEADERS))
    if ratios:
        print(markdown_table(ratios, ["size", "compare", "student", "student_ms", "baseline", "baseline_ms", "speedup_text",
                                      "student_psnr", "baseline_psnr", "psnr_gain"], FORMATS,
                             {"speedup_text": "speed-up x (interval)"}))
    for line in check_lines(checks):
        print(line)
    print(f"wrote {out_dir / 'bench.csv'}, {out_dir / 'bench.json'}, {out_dir / 'report.md'}"
          + (f" and {plot_path}" if plot_path else ""))
    return rows



def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "bench")()
