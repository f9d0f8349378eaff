"""``denoiser-bench``: what accuracy costs in time, networks and OIDN timed on the same frames.

::

    denoiser-bench 'ckpt={teacher: t.ckpt, student: s.ckpt}' eval_csv=eval/metrics.csv data=demo
    denoiser-bench ckpt=[s.ckpt] sizes=[[256,256]] repeats=5 use_backends=[eager,onnxruntime]

For every method (OIDN fast/balanced/high from ``baselines``, denoiser-eval's list in
``conf/baselines/default.yaml`` whose noisy input ``conf/bench.yaml`` sets to null, as it costs
nothing to time; each checkpoint of ``ckpt`` and each untrained config variant of
``variants``), every size of ``sizes`` ``[H, W]`` and, for networks, every backend of
``use_backends`` (Hydra ``_target_`` entries of ``backends``: PyTorch eager fp32, channels_last,
bfloat16 autocast, ``torch.compile``, ONNX Runtime, OpenVINO f32 and bf16; and CUDA backends that run only where a GPU
is present), the benchmark measures:

* the **median ms per frame** of ``repeats`` recurrent steps after ``warmup`` steps (state
  carried, as in real use), with one thread count for everyone (``threads``; torch, OIDN's
  ``numThreads`` and ONNX Runtime's intra-op threads);
* **GFLOP** per frame (convolutions and matrix products, ``torch.utils.flop_counter``) and
  the achieved GFLOP/s as a fraction of this machine's fp32 matmul peak, measured before and
  after the methods (the larger counts);
* **parameters** and **peak memory**: the peak resident set size during the warm-up and timed
  steps above the level after preparing the method (weights loaded, graph exported or
  compiled), sampled every 2 ms (CPU); ``torch.cuda.max_memory_allocated`` (CUDA). Memory the
  allocator kept from an earlier run is not counted again, so read it as "at least".

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
:mod:`denoiser.metrics` through :class:`denoiser.evaluation.Evaluation`); ``quality_frames``
(first N frames of each sequence) and ``max_sequences`` keep it cheap. That is the ``psnr``
column, the same for every size of a (method, backend) pair (``psnr_from``: ``backend``). A
bf16 speed-up thus comes with the PSNR of bf16. ``denoiser-eval``'s eager fp32 PSNR
(``eval_csv``, the ``mean`` rows, joined by method name) is kept beside it as ``psnr_eval``;
the baselines (OIDN) and, with ``quality: false``, the networks take their ``psnr`` from it
(``psnr_from``: ``eval``). Untrained ``variants`` are not scored.

Outputs in ``out_dir``: ``bench.csv`` (one row per method, backend, device and size),
``report.md`` (machine, the table, the student vs OIDN-fast ratio at every size: the student's
fastest backend whose own PSNR is known, and eager fp32) and ``accuracy_vs_time.png`` (PSNR
against ms per frame at ``plot_size`` on a log axis; see :mod:`denoiser.plot_tradeoff`).
"""

from __future__ import annotations

import contextlib
import math
import os
import platform
from collections import OrderedDict
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm.auto import tqdm

from denoiser.atomic import atomic_write_text
from denoiser.backends import Stepper
from denoiser.buffers import FRAME_INPUTS
from denoiser.errors import ConfigError
from denoiser.evaluation import eval_means
from denoiser.frames import resize_frame
from denoiser.measure import (
    PeakRss,
    count_flops,
    markdown_table,
    matmul_peak,
    summarize,
    time_steps,
    write_csv,
)

# ----------------------------------------------------------------------------- frames


def load_frames(data_cfg: DictConfig, split: str, sequence: str | None, count: int,
                samples: bool = False) -> tuple[str, list[dict]]:
    """``count`` consecutive frames ``{buffer: [1, C, H, W]}`` of one test sequence (cycled if short);
    with ``samples`` also ``samples [1, S, 3, H, W]`` where the sequence has them (for ONND)."""
    from denoiser.data.evalset import open_test_split, read_frame

    _, sources, dataset = open_test_split(data_cfg, split, [sequence] if sequence else None, samples=samples)
    source = sources[0]
    frames = [read_frame(dataset, source, i % source.frames)[0] for i in range(count)]
    return source.name, [{k: f[k] for k in (*FRAME_INPUTS, "samples") if k in f} for f in frames]


def baselines_use_samples(nodes) -> bool:
    """Whether a baseline's class reads per-sample radiance (``uses_samples``, ONND), from the config alone."""
    from hydra.utils import get_class

    return any(node is not None and getattr(get_class(node._target_), "uses_samples", False)
               for node in (nodes or {}).values())


# ----------------------------------------------------------------------------- backends


# ----------------------------------------------------------------------------- measuring


# ----------------------------------------------------------------------------- methods


def network_methods(cfg: DictConfig) -> OrderedDict[str, dict]:
    """``{label: {"net": module, "kind": "checkpoint"|"variant"}}`` from ``ckpt`` and ``variants``."""
    from denoiser.checkpoint import checkpoint_paths, load_denoiser
    from denoiser.configs import build_net, compose_net_config

    out: OrderedDict[str, dict] = OrderedDict()
    for name, path in checkpoint_paths(cfg.get("ckpt")).items():
        out[name] = {"net": load_denoiser(path, trust=bool(cfg.get("trust_checkpoint"))), "kind": "checkpoint"}
    for name, spec in (cfg.get("variants") or {}).items():
        if name in out:
            raise ConfigError(f"variants.{name}: the name is already used by a checkpoint")
        net_cfg = compose_net_config(spec.get("net", "student"), spec.get("kernel"), list(spec.get("overrides") or []))
        torch.manual_seed(0)
        out[str(name)] = {"net": build_net(net_cfg, f"variants.{name}").eval(), "kind": "variant (untrained)"}
    return out




def backend_quality(cfg: DictConfig, nets, backends, pairs, threads: int) -> dict[tuple[str, str], dict]:
    """``{(method, backend label): {"psnr": dB} | {"error": why}}``: each checkpoint of ``pairs``
    ``(method, backend key)`` prepared afresh by its backend and run over the evaluation
    sequences like ``denoiser-eval`` (one :class:`~denoiser.evaluation.Evaluation` per pair, so a
    failing backend fails alone)."""
    from denoiser.baselines import StepperMethod
    from denoiser.data.evalset import open_test_split, read_frame
    from denoiser.evaluation import Evaluation

    if not pairs:
        return {}
    _, sources, dataset = open_test_split(cfg.data, cfg.split)
    if cfg.get("max_sequences"):
        sources = sources[:int(cfg.max_sequences)]
    limit = cfg.get("quality_frames")
    lengths = [min(s.frames, int(limit)) if limit else s.frames for s in sources]
    warmup = int(cfg.get("quality_warmup", 2))
    example = read_frame(dataset, sources[0], 0)[0]
    out = {}
    with tqdm(total=len(pairs) * sum(lengths), desc="quality", unit="frame") as progress:
        for label, key in pairs:
            backend = backends[key]
            name = f"{label} | {backend.label}"
            try:
                method = StepperMethod(backend.prepare(nets[label]["net"], example, threads), name)
                ev = Evaluation({name: method}, ["psnr"], warmup)
                for source, frames in zip(sources, lengths):
                    ev.run_sequence(dataset, source, frames, None, None, None, progress)
                out[(label, backend.label)] = {"psnr": float(ev.acc[name].compute()["psnr"])}
            except Exception as exc:  # noqa: BLE001 - reported in the row's status, not fatal
                out[(label, backend.label)] = {"error": f"{type(exc).__name__}: {str(exc)[:120]}"}
    return out


def skipped(skip_cfg, label: str, size: tuple[int, int]) -> bool:
    """True when ``skip[label]`` lists ``[H, W]`` = ``size``."""
    entries = (skip_cfg or {}).get(label) or []
    return any(tuple(int(v) for v in e) == size for e in entries)


# ----------------------------------------------------------------------------- running


def bench_row(method: str, backend: str, device: str, size, times: list[float] | None, **extra) -> dict:
    row = {"method": method, "backend": backend, "device": device, "height": size[0], "width": size[1],
           "ms_median": float("nan"), "ms_min": float("nan"), "repeats": 0}
    if times:
        stats = summarize(times)
        row.update(ms_median=1000 * stats["median"], ms_min=1000 * stats["min"], repeats=stats["runs"])
    row.update(extra)
    return row


def run_benchmark(cfg: DictConfig, frames: list[dict], threads: int) -> list[dict]:
    """Time every method, backend and size; returns the table rows (the share of the matmul
    peak is set by :func:`run`, which measures the peak around them)."""
    from denoiser.baselines import build_baselines
    from denoiser.configs import instantiate_config

    sizes = [tuple(int(v) for v in s) for s in cfg.sizes]
    nets = network_methods(cfg)
    baselines = build_baselines(cfg.get("baselines"))
    backends = OrderedDict()
    for key in cfg.use_backends:
        if key not in cfg.backends:
            raise ConfigError(f"use_backends: {key!r} is not in backends ({', '.join(cfg.backends)})")
        backends[key] = instantiate_config(cfg.backends[key], f"backends.{key}")
    warmup, repeats = int(cfg.warmup), int(cfg.repeats)
    if repeats < 1 or warmup < 0:
        raise ConfigError(f"repeats must be >= 1 and warmup >= 0, got {repeats} and {warmup}")
    jobs = [(size, label) for size in sizes for label in [*baselines, *nets] if not skipped(cfg.get("skip"), label, size)]
    rows = []
    with tqdm(jobs, desc="bench", unit="job") as progress:
        for size, label in progress:
            progress.set_postfix_str(f"{label} {size[1]}x{size[0]}")
            sized = [resize_frame(f, *size) for f in frames]
            if label in baselines:
                method = baselines[label]
                if not getattr(method, "uses_samples", False):
                    sized = [{k: v for k, v in f.items() if k != "samples"} for f in sized]
                with PeakRss() as mem:
                    times = time_steps(Stepper(lambda f, s, m=method: (m(f, s is None), None)), sized, warmup, repeats)
                rows.append(bench_row(label, getattr(method, "backend", "OIDN (pyoidn)"), "cpu", size, times,
                                      threads=threads,
                                      peak_mb=mem.megabytes, kind="baseline"))
                continue
            sized = [{k: v for k, v in f.items() if k != "samples"} for f in sized]  # networks: as in eval
            net, kind = nets[label]["net"], nets[label]["kind"]
            gflop = count_flops(net, *size) / 1e9
            allowed = (cfg.get("method_backends") or {}).get(label)
            for key, backend in backends.items():
                if allowed is not None and key not in allowed:
                    continue
                reason = backend.available()
                base = {"threads": threads if backend.device == "cpu" else "", "gflop": gflop,
                        "dtype": getattr(backend, "dtype", ""),
                        "params": net.num_parameters(), "kind": kind}
                if reason:
                    rows.append(bench_row(label, backend.label, backend.device, size, None, status=f"skipped: {reason}",
                                          **base))
                    continue
                try:
                    if backend.device.startswith("cuda"):
                        torch.cuda.reset_peak_memory_stats()
                    stepper = backend.prepare(net, sized[0], threads)
                    with PeakRss() as mem:  # what running needs above the prepared state
                        times = time_steps(stepper, sized, warmup, repeats)
                except Exception as exc:  # noqa: BLE001 - a backend that fails here is reported, not fatal
                    rows.append(bench_row(label, backend.label, backend.device, size, None,
                                          status=f"failed: {type(exc).__name__}: {str(exc).splitlines()[0][:120]}"
                                          if str(exc) else f"failed: {type(exc).__name__}", **base))
                    continue
                peak = (torch.cuda.max_memory_allocated() / 2**20 if backend.device.startswith("cuda")
                        else mem.megabytes)
                row = bench_row(label, backend.label, backend.device, size, times, peak_mb=peak, **base)
                if stepper.profile is not None:
                    row["profile"] = stepper.profile()  # {op type: ms} of the last timed step
                row["gflops_per_s"] = gflop / (row["ms_median"] / 1000)
                rows.append(row)
    for m in baselines.values():
        close = getattr(m, "close", None)
        if close:
            close()
    if cfg.get("quality", True):
        pairs = list(OrderedDict.fromkeys(
            (r["method"], key) for r in rows if r.get("status", "ok") == "ok" and r["method"] in nets
            and nets[r["method"]]["kind"] == "checkpoint" for key, b in backends.items() if b.label == r["backend"]))
        measured = backend_quality(cfg, nets, backends, pairs, threads)
        for r in rows:
            q = measured.get((r["method"], r["backend"]))
            if q and "psnr" in q:
                r.update(psnr=q["psnr"], psnr_from="backend")
            elif r["method"] in nets:  # not measured through this backend: no PSNR, not eval's in its place
                r.update(psnr=float("nan"), psnr_from="")
                if q:
                    r["status"] = f"ok (quality failed: {q['error']})"
    return rows


# ----------------------------------------------------------------------------- report

COLUMNS = ["method", "backend", "dtype", "device", "height", "width", "ms_median", "ms_min", "repeats", "gflop", "params",
           "peak_mb", "gflops_per_s", "peak_fraction", "psnr", "psnr_eval", "psnr_from", "kind", "threads", "status"]
FORMATS = {"ms_median": ".1f", "ms_min": ".1f", "gflop": ".2f", "peak_mb": ".0f", "gflops_per_s": ".1f",
           "peak_fraction": ".1%", "psnr": ".2f", "psnr_eval": ".2f", "student_psnr": ".2f", "baseline_psnr": ".2f", "ratio": ".2f", "psnr_gain": "+.2f", "student_ms": ".1f",
           "baseline_ms": ".1f"}
HEADERS = {"ms_median": "ms/frame (median)", "ms_min": "ms min", "gflop": "GFLOP", "peak_mb": "peak MB",
           "gflops_per_s": "GFLOP/s", "peak_fraction": "of matmul peak", "psnr": "PSNR dB", "psnr_eval": "PSNR dB (eval, eager fp32)",
           "psnr_from": "PSNR from"}


def best_rows(rows: list[dict], size, device: str = "cpu") -> dict[str, dict]:
    """Per method, its fastest timed row at ``size`` on ``device``."""
    best: dict[str, dict] = {}
    for r in rows:
        if (r["height"], r["width"]) != tuple(size) or r["device"] != device or math.isnan(r["ms_median"]):
            continue
        if r["method"] not in best or r["ms_median"] < best[r["method"]]["ms_median"]:
            best[r["method"]] = r
    return best


def ratio_rows(rows: list[dict], student: str, baseline: str, sizes) -> list[dict]:
    """Student vs baseline (e.g. OIDN-fast) at each size: best CPU backend and eager fp32."""
    out = []
    for size in sizes:
        size = tuple(int(v) for v in size)
        b = best_rows(rows, size).get(baseline)
        s_best = best_rows([r for r in rows if not math.isnan(r.get("psnr", float("nan")))], size).get(student)
        s_best = s_best or best_rows(rows, size).get(student)  # no PSNR through any backend: the fastest
        s_eager = next((r for r in rows if r["method"] == student and r["backend"] == "eager fp32" and r["device"] == "cpu"
                        and (r["height"], r["width"]) == size and not math.isnan(r["ms_median"])), None)
        for which, s in (("fastest backend", s_best), ("eager fp32", s_eager)):
            if b is None or s is None:
                continue
            out.append({"size": f"{size[1]}x{size[0]}", "student": f"{student} ({s['backend']})", "student_ms": s["ms_median"],
                        "baseline": baseline, "baseline_ms": b["ms_median"], "ratio": b["ms_median"] / s["ms_median"],
                        "student_psnr": s.get("psnr", float("nan")), "baseline_psnr": b.get("psnr", float("nan")),
                        "psnr_gain": s.get("psnr", float("nan")) - b.get("psnr", float("nan")), "compare": which})
    return out


#: CPU flags that decide the fast paths of the backends (bf16 convolutions: AVX512-BF16 or AMX)
ISA_FLAGS = ("avx2", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16")


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


def machine_description(threads: int, peak_gflops: float) -> str:
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none"
    isa = ", ".join(f"{f} {'yes' if v else 'no'}" for f, v in cpu_isa().items())
    return (f"CPU: {cpu}, {os.cpu_count()} logical cores ({isa}), {threads} thread(s) for every method; "
            f"fp32 matmul peak {peak_gflops:.1f} GFLOP/s (2048x2048 torch.mm, best of 5, the larger of the "
            f"measurements before and after the methods); GPU: {gpu}; "
            f"torch {torch.__version__}")


def write_report(out_dir: Path, rows: list[dict], ratios: list[dict], machine: str, cfg: DictConfig,
                 plot: Path | None) -> str:
    parts = ["# Accuracy vs time\n", machine + "\n",
             f"Median of {cfg.repeats} recurrent steps after {cfg.warmup} warm-up step(s), same frames for every "
             "method (resampled to each size). GFLOP counts convolutions and matrix products of one step. "
             + quality_note(cfg) + "\n"]
    if ratios:
        parts += ["## Student vs " + ratios[0]["baseline"] + " (same frames, same run)\n",
                  markdown_table(ratios, ["size", "compare", "student", "student_ms", "baseline_ms", "ratio",
                                          "student_psnr", "baseline_psnr", "psnr_gain"],
                                 FORMATS, {"student_ms": "student ms", "baseline_ms": f"{ratios[0]['baseline']} ms",
                                           "ratio": "speed-up (x)", "psnr_gain": "PSNR gain dB",
                                           "student_psnr": "student PSNR dB", "baseline_psnr": "baseline PSNR dB"}), ""]
    parts += ["## All measurements\n", markdown_table(rows, [c for c in COLUMNS if c not in ("kind",)], FORMATS, HEADERS)]
    profiled = profile_section(rows)
    if profiled:
        parts += ["", *profiled]
    if plot is not None:
        from denoiser.plot_tradeoff import pareto_front_of_rows

        size = tuple(int(v) for v in (cfg.get("plot_size") or cfg.sizes[-1]))
        front = pareto_front_of_rows(rows, size)
        parts += ["", f"Pareto front at {size[1]}x{size[0]} (fastest first): {', '.join(front)}.", "",
                  f"![accuracy vs time]({plot.name})", ""]
    text = "\n".join(parts)
    atomic_write_text(out_dir / "report.md", text)
    return text


def profile_rows(rows: list[dict]) -> list[dict]:
    """One row per (method, backend, size, op type) of the rows that carry a profile
    (``profile: true``): ``ms`` of that op type in the last timed step and its ``share`` of the
    step's summed node time."""
    out = []
    for r in rows:
        total = sum((r.get("profile") or {}).values())
        for op, ms in (r.get("profile") or {}).items():
            out.append({"method": r["method"], "backend": r["backend"], "height": r["height"], "width": r["width"],
                        "op_type": op, "ms": ms, "share": ms / total if total else float("nan")})
    return out


def profile_section(rows: list[dict], top: int = 8) -> list[str]:
    """report.md lines: per profiled row, its ``top`` op types by time (the rest summed)."""
    prof = profile_rows(rows)
    if not prof:
        return []
    parts = ["## Where the time goes (OpenVINO per-node counters, last timed step)\n"]
    keys = list(OrderedDict.fromkeys((p["method"], p["backend"], p["height"], p["width"]) for p in prof))
    for key in keys:
        ops = [p for p in prof if (p["method"], p["backend"], p["height"], p["width"]) == key]
        rest = ops[top:]
        shown = ops[:top] + ([{"op_type": f"{len(rest)} other op types", "ms": sum(p["ms"] for p in rest),
                               "share": sum(p["share"] for p in rest)}] if rest else [])
        parts += [f"**{key[0]}**, {key[1]}, {key[3]}x{key[2]}: {sum(p['ms'] for p in ops):.0f} ms of node time\n",
                  markdown_table(shown, ["op_type", "ms", "share"], {"ms": ".1f", "share": ".1%"},
                                 {"op_type": "op type"}), ""]
    return parts


def quality_note(cfg: DictConfig) -> str:
    """The report's sentence saying where each PSNR (tonemapped, dB) comes from."""
    evaluated = f"denoiser-eval's metrics.csv ({cfg.eval_csv})" if cfg.get("eval_csv") else None
    if not cfg.get("quality", True):
        return f"PSNR (tonemapped, dB) from {evaluated or 'nowhere (no eval_csv, quality: false)'}."
    frames = f"the first {cfg.quality_frames} frames" if cfg.get("quality_frames") else "every frame"
    seqs = f"the first {cfg.max_sequences} sequence(s)" if cfg.get("max_sequences") else "every sequence"
    return (f"PSNR (tonemapped, dB) of the networks measured through each row's own backend and precision, "
            f"over {frames} of {seqs} of {cfg.split}, {cfg.get('quality_warmup', 2)} warm-up frame(s) excluded "
            "after each reset (psnr_from: backend); "
            + (f"psnr_eval and the baselines' PSNR from {evaluated} (eager fp32)." if evaluated
               else "no eval_csv: the baselines have no PSNR."))


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
    peak_before = matmul_peak()
    rows = run_benchmark(cfg, frames, threads)
    peak = max(peak_before, matmul_peak())
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
        from denoiser.plot_tradeoff import plot_accuracy_vs_time

        plot_size = tuple(int(v) for v in (cfg.get("plot_size") or cfg.sizes[-1]))
        noisy = quality.get(cfg.get("noisy_label", "noisy input"))
        plot_path = plot_accuracy_vs_time(out_dir / "accuracy_vs_time.png", rows, plot_size,
                                          curves=_plain(cfg.get("curves")),
                                          noisy_psnr=float(noisy["psnr"]) if noisy else None,
                                          title=f"{seq_name} frames at {plot_size[1]}x{plot_size[0]}, {threads} CPU thread(s)")
    student = cfg.compare.student or default_student(network_labels(rows))
    ratios = ratio_rows(rows, student, cfg.compare.baseline, cfg.sizes) if student else []
    machine = machine_description(threads, peak)
    write_report(out_dir, rows, ratios, machine, cfg, plot_path)
    print(machine)
    print(markdown_table(rows, ["method", "backend", "dtype", "device", "height", "width", "ms_median", "gflop", "params",
                                "peak_mb", "peak_fraction", "psnr", "psnr_eval", "status"], FORMATS, HEADERS))
    if ratios:
        print(markdown_table(ratios, ["size", "compare", "student", "student_ms", "baseline", "baseline_ms", "ratio",
                                      "student_psnr", "baseline_psnr", "psnr_gain"], FORMATS, {"ratio": "speed-up (x)"}))
    print(f"wrote {out_dir / 'bench.csv'}, {out_dir / 'report.md'}" + (f" and {plot_path}" if plot_path else ""))
    return rows


def _plain(node) -> dict:
    """A config node (or None) as a plain dict."""
    return OmegaConf.to_container(node, resolve=True) if node is not None else {}


def default_student(labels: list[str]) -> str | None:
    """The network compared with the baseline when ``compare.student`` is null: the first whose
    name contains ``student``, else the first network."""
    return next((m for m in labels if "student" in m), labels[0] if labels else None)


def network_labels(rows: list[dict]) -> list[str]:
    seen = []
    for r in rows:
        if r.get("kind") != "baseline" and r["method"] not in seen:
            seen.append(r["method"])
    return seen


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "bench")()


if __name__ == "__main__":
    main()
