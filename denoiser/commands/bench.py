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

import contextlib
import json
import math
import os
import time
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from denoiser.atomic import atomic_write_text
from denoiser.buffers import FRAME_INPUTS
from denoiser.configs import plain
from denoiser.errors import ConfigError
from denoiser.frames import resize_frame
from denoiser.machine import cpu_isa, cpu_model, cpu_signature, matmul_peak
from denoiser.measure import (
    PeakRss,
    StagedStep,
    count_flops,
    median_interval,
    recurrent_steps,
    round_robin,
    summarize,
)
from denoiser.report.evaluation import eval_means
from denoiser.runner import Stepper
from denoiser.tables import markdown_table, write_csv

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


def load_backends(cfg: DictConfig) -> OrderedDict:
    """``{name: backend}`` of ``use_backends``: names of the group ``conf/backends/``
    (:func:`denoiser.inference.backends.load_backend`); ``profile: true`` turns on the counters of the
    backends that take ``profile``."""
    from denoiser.inference.backends import backend_config, backend_names, load_backend

    names = backend_names()
    backends = OrderedDict()
    for key in cfg.use_backends:
        if key not in names:
            raise ConfigError(f"use_backends: {key!r} is not one of {', '.join(names)} (conf/backends/)")
        extra = {"profile": True} if cfg.get("profile") and "profile" in backend_config(key) else {}
        backends[key] = load_backend(key, f"use_backends: {key}", **extra)
    return backends

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
    sequences like ``denoiser-eval`` (one :class:`~denoiser.report.evaluation.Evaluation` per pair, so a
    failing backend fails alone)."""
    from denoiser.data.evalset import open_test_split, read_frame
    from denoiser.methods.baselines import StepperMethod
    from denoiser.report.evaluation import Evaluation

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
    """True when ``skip[label]`` lists ``[H, W]`` = ``size`` (label: a method's, or a backend's key in
    ``use_backends``, which skips that backend for every network)."""
    entries = (skip_cfg or {}).get(label) or []
    return any(tuple(int(v) for v in e) == size for e in entries)


# ----------------------------------------------------------------------------- running


def bench_row(method: str, backend: str, device: str, size, times: list[float] | None, **extra) -> dict:
    """One table row; ``times``: seconds of each repeat (index = round of :func:`round_robin`)."""
    row = {"method": method, "backend": backend, "device": device, "height": size[0], "width": size[1],
           "ms_median": float("nan"), "ms_min": float("nan"), "ms_max": float("nan"), "repeats": 0, "times_ms": []}
    if times:
        stats = summarize(times)
        row.update(ms_median=1000 * stats["median"], ms_min=1000 * stats["min"], ms_max=1000 * stats["max"],
                   repeats=stats["runs"], times_ms=[1000 * t for t in times])
    row.update(extra)
    return row


def engine_versions() -> dict[str, str]:
    """``{engine: version}`` of the libraries that run the steps: ``torch``, ``onnxruntime``,
    ``openvino`` (``openvino.get_version()``, with its build), ``oidn`` (the OIDN library's
    own ``version``, and the pyoidn package's); ``not installed`` where missing."""
    from importlib.metadata import PackageNotFoundError, version

    out = {"torch": torch.__version__}
    for engine, package in (("onnxruntime", "onnxruntime"), ("openvino", "openvino"), ("oidn", "pyoidn")):
        try:
            out[engine] = version(package)
        except PackageNotFoundError:
            out[engine] = "not installed"
    if out["openvino"] != "not installed":
        with contextlib.suppress(Exception):
            import openvino

            out["openvino"] = openvino.get_version()
    if out["oidn"] != "not installed":
        with contextlib.suppress(Exception):
            from pyoidn.device import Device

            device = Device()
            v = device.get_int("version")  # major * 10000 + minor * 100 + patch
            device.release()
            out["oidn"] = f"{v // 10000}.{v // 100 % 100}.{v % 100} (pyoidn {out['oidn']})"
    return out


def oidn_dtype(isa: dict[str, bool]) -> str:
    """The precision OIDN's CPU device computes in here: fp16 with AMX-FP16 (OIDN >= 2.4), else fp32."""
    return "fp16" if isa.get("amx_fp16") else "fp32"


def oidn_harness_steps(method, frames: list[dict]) -> StagedStep:
    """The benchmark's path to an OIDN baseline: each frame's buffers are put in OIDN's ``[H, W, 3]``
    layout before the clock starts (our frames are planar ``[1, C, H, W]``; a renderer hands OIDN
    interleaved pixels), the timed call is ``method.denoise_arrays`` (the clamping copies into
    OIDN's shared images, the filter, the output copy)."""
    from denoiser.methods.baselines import _hwc

    def stage(k: int):
        frame = frames[k % len(frames)]
        arrays = [_hwc(frame[b]) for b in ("color", "albedo", "normal")]
        return lambda: method.denoise_arrays(*arrays)

    return stage


def oidn_direct_steps(quality: str, threads: int, frames: list[dict]) -> tuple[StagedStep, Callable[[], int], Callable[[], None]]:
    """OIDN called directly through pyoidn, the reference for the harness's OIDN path: one device
    (``numThreads`` = ``threads``) and one RT filter (``hdr``, ``quality``) bound once to four
    ``[H, W, 3]`` float32 arrays; staging writes frame ``k`` into them (clamped as the baseline
    clamps) untimed, the timed call is ``filter.execute()`` alone: no copies.

    Returns ``(entry, threads read back, close)``."""
    import pyoidn.filter as oidn_filter
    from pyoidn.device import Device

    from denoiser.methods.baselines import _hwc

    h, w = frames[0]["color"].shape[-2:]
    images = {n: np.zeros((h, w, 3), np.float32) for n in ("color", "albedo", "normal", "output")}
    device = Device()
    device.set_int("numThreads", int(threads))
    device.commit()
    flt = oidn_filter.Filter(device, oidn_filter.OIDN_FILTER_TYPE_RT)
    for name, arr in images.items():
        flt.set_image(name, arr, oidn_filter.OIDN_FORMAT_FLOAT3)
    flt.set_bool("hdr", True)
    flt.set_quality({"fast": oidn_filter.OIDN_QUALITY_FAST, "balanced": oidn_filter.OIDN_QUALITY_BALANCED,
                     "high": oidn_filter.OIDN_QUALITY_HIGH}[quality])
    flt.commit()
    if device.get_error():
        raise RuntimeError(f"OIDN (direct) set-up failed: {device.get_error()}")

    def stage(k: int):
        frame = frames[k % len(frames)]
        np.maximum(_hwc(frame["color"]), 0.0, out=images["color"])
        np.clip(_hwc(frame["albedo"]), 0.0, 1.0, out=images["albedo"])
        images["normal"][...] = _hwc(frame["normal"])
        return flt.execute

    def close():
        flt.release()
        device.release()

    threads_used = int(device.get_int("numThreads"))  # read back once: close() releases the device
    return stage, lambda: threads_used, close


@contextlib.contextmanager
def warmup_memory(device: str, out: dict, key):
    """Peak memory of the block (the warm-up steps) into ``out[key]`` in MiB: RSS above the level at
    entry (:class:`PeakRss`, CPU) or ``torch.cuda.max_memory_allocated`` (CUDA)."""
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    with PeakRss() as mem:
        yield
    out[key] = torch.cuda.max_memory_allocated() / 2**20 if cuda else mem.megabytes


def _failure(exc: BaseException) -> str:
    return f"failed: {type(exc).__name__}: {str(exc).splitlines()[0][:120]}" if str(exc) else f"failed: {type(exc).__name__}"


def run_benchmark(cfg: DictConfig, frames: list[dict], threads: int, versions: dict[str, str] | None = None,
                  isa: dict[str, bool] | None = None) -> tuple[list[dict], list[dict]]:
    """Time every method, backend and size; returns ``(rows, checks)``: the table rows (the share
    of the matmul peak is set by :func:`run`, which measures the peak around them) and, with
    ``check_oidn``, one harness check per size (:func:`harness_check`).

    Per size, every method (baselines, and each network on each backend) is prepared first;
    then each runs its ``warmup`` steps (untimed; its peak memory is taken over them), and the
    ``repeats`` timed steps are interleaved (:func:`~denoiser.measure.round_robin`: each round
    times every method once, in a rotated order), so a slow phase of the machine falls on every
    method alike and the speed-up vs the baseline is paired per round."""
    from denoiser.methods.baselines import OidnDenoiser, build_baselines

    versions = versions if versions is not None else engine_versions()
    isa = isa if isa is not None else cpu_isa()
    sizes = [tuple(int(v) for v in s) for s in cfg.sizes]
    nets = network_methods(cfg)
    baselines = build_baselines(cfg.get("baselines"))
    backends = load_backends(cfg)
    warmup, repeats = int(cfg.warmup), int(cfg.repeats)
    if repeats < 1 or warmup < 0:
        raise ConfigError(f"repeats must be >= 1 and warmup >= 0, got {repeats} and {warmup}")
    baseline = cfg.compare.baseline
    rows, checks = [], []
    for size in tqdm(sizes, desc="bench", unit="size"):
        sized = [resize_frame(f, *size) for f in frames]
        plain = [{k: v for k, v in f.items() if k != "samples"} for f in sized]  # networks: as in eval
        entries: OrderedDict[tuple[str, str], StagedStep] = OrderedDict()
        timed: OrderedDict[tuple[str, str], tuple[dict, Stepper | None]] = OrderedDict()  # base row, stepper
        closers = []
        for label, method in baselines.items():
            if skipped(cfg.get("skip"), label, size):
                continue
            oidn = isinstance(method, OidnDenoiser)
            backend = getattr(method, "backend", "OIDN (pyoidn)")
            key = (label, backend)
            base = {"kind": "baseline", "dtype": oidn_dtype(isa) if oidn else "fp32",
                    "engine": f"oidn {versions['oidn']}" if oidn else f"torch {versions['torch']}"}
            if oidn:
                entries[key] = oidn_harness_steps(method, plain)
                stepper = Stepper(None, threads=method.threads_in_use)
            else:
                stepper = Stepper(lambda f, s, m=method: (m(f, s is None), None), engine="torch")
                entries[key] = recurrent_steps(stepper, sized if getattr(method, "uses_samples", False) else plain)
            timed[key] = ({"method": label, "backend": backend, "device": "cpu", **base}, stepper)
            if oidn and label == baseline and cfg.get("check_oidn", True):
                check_key = (label, "direct pyoidn")
                try:
                    entries[check_key], read_threads, close = oidn_direct_steps(method.quality, method.threads, plain)
                    closers.append(close)
                    timed[check_key] = ({"method": label, "backend": "direct pyoidn (filter.execute only)",
                                         "device": "cpu", **base, "kind": "check"}, Stepper(None, threads=read_threads))
                except Exception as exc:  # noqa: BLE001 - the check is reported, not fatal
                    checks.append({"size": f"{size[1]}x{size[0]}", "baseline": label, "status": _failure(exc)})
        for label, spec in nets.items():
            if skipped(cfg.get("skip"), label, size):
                continue
            net, kind = spec["net"], spec["kind"]
            if "gflop" not in spec or spec.get("gflop_size") != size:
                spec["gflop"], spec["gflop_size"] = count_flops(net, *size) / 1e9, size
            allowed = (cfg.get("method_backends") or {}).get(label)
            for bkey, backend in backends.items():
                if (allowed is not None and bkey not in allowed) or skipped(cfg.get("skip"), bkey, size):
                    continue
                base = {"method": label, "backend": backend.label, "device": backend.device, "gflop": spec["gflop"],
                        "dtype": getattr(backend, "dtype", ""), "params": net.num_parameters(), "kind": kind}
                reason = backend.available()
                if reason:
                    rows.append(bench_row(size=size, times=None, status=f"skipped: {reason}", **base))
                    continue
                try:
                    stepper = backend.prepare(net, plain[0], threads)
                except Exception as exc:  # noqa: BLE001 - a backend that fails here is reported, not fatal
                    rows.append(bench_row(size=size, times=None, status=_failure(exc), **base))
                    continue
                base["engine"] = f"{stepper.engine} {versions.get(stepper.engine, '')}".strip()
                entries[(label, backend.label)] = recurrent_steps(stepper, plain)
                timed[(label, backend.label)] = (base, stepper)
        memory: dict = {}
        seconds, errors = round_robin(
            entries, warmup, repeats,
            warmup_context=lambda key, timed=timed, memory=memory: warmup_memory(timed[key][0]["device"], memory, key))
        for close in closers:
            close()
        size_rows = {}
        for key, (base, stepper) in timed.items():
            base = dict(base)
            method, backend = base.pop("method"), base.pop("backend")
            device = base.pop("device")
            if key in errors:
                size_rows[key] = bench_row(method, backend, device, size, None, status=_failure(errors[key]), **base)
                continue
            row = bench_row(method, backend, device, size, seconds[key],
                            peak_mb=memory.get(key, float("nan")) if warmup else float("nan"), **base)
            with contextlib.suppress(Exception):  # an engine that cannot say leaves the column empty
                row["threads"] = stepper.threads() if stepper.threads else ""
            if stepper.profile is not None:
                row["profile"] = stepper.profile()  # {op type: ms} of the last timed step
            if "gflop" in row:
                row["gflops_per_s"] = row["gflop"] / (row["ms_median"] / 1000)
            size_rows[key] = row
        check_rows = [r for r in size_rows.values() if r.get("kind") == "check"]
        kept = [r for r in size_rows.values() if r.get("kind") != "check"]
        for check in check_rows:
            harness = next((r for r in kept if r["method"] == check["method"] and r["kind"] == "baseline"), None)
            checks.append(harness_check(harness, check))
        rows.extend(kept)
    for m in baselines.values():
        close = getattr(m, "close", None)
        if close:
            close()
    rows = precision_order(rows)
    add_speedups(rows, baseline)
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
    return rows, checks


#: order of the precisions in the tables: a network's fp32 rows, then its reduced-precision rows
PRECISION_ORDER = {"fp32": 0, "bf16": 1, "fp16": 2}


def precision_order(rows: list[dict]) -> list[dict]:
    """``rows`` ordered by size (as measured), then method (first seen), then precision
    (:data:`PRECISION_ORDER`), keeping the backends' order within a precision: each network's
    fp32 rows sit beside its bf16 rows."""
    sizes = list(OrderedDict.fromkeys((r["height"], r["width"]) for r in rows))
    methods = list(OrderedDict.fromkeys(r["method"] for r in rows))
    return sorted(rows, key=lambda r: (sizes.index((r["height"], r["width"])), methods.index(r["method"]),
                                       PRECISION_ORDER.get(r.get("dtype", ""), 3)))


def paired_speedup(baseline_ms: list[float], method_ms: list[float]) -> dict[str, float]:
    """The speed-up ``baseline time / method time`` paired per round (both timed in the same
    round of :func:`~denoiser.measure.round_robin`): the median of the per-round ratios with its
    distribution-free interval (:func:`~denoiser.measure.median_interval`; for 7 or 8 rounds the
    min-max over rounds, 98.4%/99.2% coverage)."""
    ratios = [b / m for b, m in zip(baseline_ms, method_ms)]
    return median_interval(ratios)


def add_speedups(rows: list[dict], baseline: str) -> None:
    """Set ``speedup``, ``speedup_lo``, ``speedup_hi`` (:func:`paired_speedup` against the
    ``baseline`` method's row at the same size) on every timed CPU row."""
    for r in rows:
        b = next((x for x in rows if x["method"] == baseline and x.get("kind") == "baseline" and x.get("times_ms")
                  and (x["height"], x["width"]) == (r["height"], r["width"])), None)
        if b is None or not r.get("times_ms") or r["device"] != "cpu":
            continue
        s = paired_speedup(b["times_ms"], r["times_ms"])
        r.update(speedup=s["median"], speedup_lo=s["lo"], speedup_hi=s["hi"], speedup_coverage=s["coverage"])


def harness_check(harness: dict | None, direct: dict) -> dict:
    """What the harness adds to OIDN: per round, the harness's OIDN time over the direct pyoidn
    call's (same round, same frame) minus 1; the median over rounds and its interval
    (:func:`~denoiser.measure.median_interval`)."""
    size = f"{direct['width']}x{direct['height']}"
    if harness is None or not harness.get("times_ms") or not direct.get("times_ms"):
        why = direct.get("status") if not direct.get("times_ms") else "the harness's row has no times"
        return {"size": size, "baseline": direct["method"], "status": why or "no times"}
    s = median_interval([h / d - 1 for h, d in zip(harness["times_ms"], direct["times_ms"])])
    return {"size": size, "baseline": direct["method"], "status": "ok", "overhead": s["median"],
            "overhead_lo": s["lo"], "overhead_hi": s["hi"], "coverage": s["coverage"], "repeats": s["runs"],
            "harness_ms": harness["ms_median"], "direct_ms": direct["ms_median"],
            "direct_threads": direct.get("threads", "")}


# ----------------------------------------------------------------------------- report

COLUMNS = ["method", "backend", "dtype", "device", "height", "width", "ms_median", "ms_min", "ms_max", "repeats",
           "speedup", "speedup_lo", "speedup_hi", "gflop", "params", "peak_mb", "gflops_per_s", "peak_fraction", "psnr",
           "psnr_eval", "psnr_from", "kind", "engine", "threads", "status"]
FORMATS = {"ms_median": ".1f", "ms_min": ".1f", "ms_max": ".1f", "gflop": ".2f", "peak_mb": ".0f", "gflops_per_s": ".1f",
           "peak_fraction": ".1%", "psnr": ".2f", "psnr_eval": ".2f", "student_psnr": ".2f", "baseline_psnr": ".2f",
           "ratio": ".2f", "psnr_gain": "+.2f", "student_ms": ".1f", "baseline_ms": ".1f"}
HEADERS = {"ms_median": "ms/frame (median)", "ms_min": "ms min", "ms_max": "ms max", "gflop": "GFLOP", "peak_mb": "peak MB",
           "gflops_per_s": "GFLOP/s", "peak_fraction": "of matmul peak", "psnr": "PSNR dB",
           "psnr_eval": "PSNR dB (eval, eager fp32)", "psnr_from": "PSNR from", "speedup_text": "speed-up (interval)"}


def _interval_text(mid: float, lo: float, hi: float) -> str:
    return "" if any(math.isnan(v) for v in (mid, lo, hi)) else f"{mid:.2f} ({lo:.2f}-{hi:.2f})"


def ratio_rows(rows: list[dict], student: str, baseline: str, sizes) -> list[dict]:
    """Student vs ``baseline`` (e.g. OIDN-fast) at each size: one line per timed CPU row of the
    student, its fp32 rows first (like with like where OIDN computes in fp32), then its bf16 rows,
    each labelled with both precisions (``compare``). ``ratio`` is the paired per-round speed-up
    (:func:`paired_speedup`, from the rows' ``speedup`` columns), ``ratio_lo``/``ratio_hi`` its
    interval."""
    out = []
    for size in sizes:
        size = tuple(int(v) for v in size)
        b = next((r for r in rows if r["method"] == baseline and r.get("kind") == "baseline"
                  and (r["height"], r["width"]) == size and r.get("times_ms")), None)
        if b is None:
            continue
        mine = [r for r in rows if r["method"] == student and r["device"] == "cpu" and (r["height"], r["width"]) == size
                and r.get("times_ms") and "speedup" in r]
        for s in sorted(mine, key=lambda r: (PRECISION_ORDER.get(r.get("dtype", ""), 3), r["ms_median"])):
            same = s.get("dtype") == b.get("dtype")
            out.append({"size": f"{size[1]}x{size[0]}", "dtype": s.get("dtype", ""),
                        "compare": f"{s.get('dtype', '?')} vs {b.get('dtype', '?')}" + (" (like with like)" if same else ""),
                        "student": f"{student} ({s['backend']})", "student_ms": s["ms_median"],
                        "baseline": baseline, "baseline_ms": b["ms_median"], "ratio": s["speedup"],
                        "ratio_lo": s["speedup_lo"], "ratio_hi": s["speedup_hi"], "coverage": s["speedup_coverage"],
                        "repeats": s["repeats"], "speedup_text": _interval_text(s["speedup"], s["speedup_lo"], s["speedup_hi"]),
                        "student_psnr": s.get("psnr", float("nan")), "baseline_psnr": b.get("psnr", float("nan")),
                        "psnr_gain": s.get("psnr", float("nan")) - b.get("psnr", float("nan"))})
    return out


#: CPU flags that decide the fast paths of the backends (bf16 convolutions: AVX512-BF16 or AMX;
#: OIDN >= 2.4 computes in fp16 with AMX-FP16)
def machine_info(threads: int, peak_gflops: float, versions: dict[str, str], isa: dict[str, bool]) -> dict:
    """The machine and software of a run: ``cpu`` (model name), ``cpu_id`` (:func:`cpu_signature`),
    ``logical_cores``, ``isa`` (:func:`cpu_isa`), ``versions`` (:func:`engine_versions`),
    ``threads_requested``, ``matmul_peak_gflops``, ``gpu``, and the run's UTC ``date`` and code
    ``commit`` (:func:`denoiser.report.summary.git_commit`)."""
    from denoiser.report.summary import git_commit

    return {"cpu": cpu_model(), "cpu_id": cpu_signature(), "logical_cores": os.cpu_count(), "isa": dict(isa),
            "versions": dict(versions), "threads_requested": threads, "matmul_peak_gflops": peak_gflops,
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none",
            "date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": git_commit()}


def machine_description(info: dict) -> str:
    """The report's machine line of :func:`machine_info`."""
    isa = ", ".join(f"{f} {'yes' if v else 'no'}" for f, v in info["isa"].items())
    versions = ", ".join(f"{k} {v}" for k, v in info["versions"].items())
    return (f"CPU: {info['cpu']}, {info['logical_cores']} logical cores ({isa}), {info['threads_requested']} thread(s) "
            f"requested for every method (the threads column: what each engine reports it uses); "
            f"fp32 matmul peak {info['matmul_peak_gflops']:.1f} GFLOP/s (2048x2048 torch.mm, best of 5, the larger of the "
            f"measurements before and after the methods); GPU: {info['gpu']}; versions: {versions}; "
            f"OIDN computes in {oidn_dtype(info['isa'])} on this CPU")


def check_lines(checks: list[dict]) -> list[str]:
    """The report's lines of the harness checks (:func:`harness_check`)."""
    out = []
    for c in checks:
        if c["status"] != "ok":
            out.append(f"harness overhead on {c['baseline']} at {c['size']}: not measured ({c['status']})")
            continue
        out.append(f"harness overhead on {c['baseline']} at {c['size']}: {100 * c['overhead']:+.1f}% (median of "
                   f"{c['repeats']} paired repeats; {100 * c['overhead_lo']:+.1f}% to {100 * c['overhead_hi']:+.1f}%, "
                   f"{c['coverage']:.1%} interval): {c['harness_ms']:.1f} ms through the benchmark, {c['direct_ms']:.1f} "
                   f"ms for pyoidn's filter.execute() alone on the same frames ({c['direct_threads']} threads)")
    return out


def write_report(out_dir: Path, rows: list[dict], ratios: list[dict], machine: str, cfg: DictConfig,
                 plot: Path | None, checks: list[dict] | None = None) -> str:
    interval = ("speed-up: the median over the rounds of the paired ratio (baseline time / method time, both "
                "timed in the same round); in brackets a distribution-free interval of that median from the "
                "order statistics of the per-round ratios (at least 95%; for 7 or 8 rounds the min-max, 98.4% and "
                "99.2%)")
    parts = ["# Accuracy vs time\n", machine + "\n",
             f"Per size, every method runs {cfg.warmup} warm-up step(s) (peak memory is taken over them), then "
             f"{cfg.repeats} timed rounds interleave the methods (each round times every method once, in a rotated "
             "order): median, min and max ms per frame over the rounds; same frames for every method (resampled to "
             "each size). GFLOP counts convolutions and matrix products of one step. " + quality_note(cfg) + "\n",
             *[line + "\n" for line in check_lines(checks or [])]]
    if ratios:
        parts += ["## Student vs " + ratios[0]["baseline"] + " (same frames, interleaved rounds)\n",
                  f"Each precision against OIDN's own ({interval}).\n",
                  markdown_table(ratios, ["size", "compare", "student", "student_ms", "baseline_ms", "speedup_text",
                                          "student_psnr", "baseline_psnr", "psnr_gain"],
                                 FORMATS, {"student_ms": "student ms", "baseline_ms": f"{ratios[0]['baseline']} ms",
                                           "speedup_text": "speed-up x (interval)", "psnr_gain": "PSNR gain dB",
                                           "student_psnr": "student PSNR dB", "baseline_psnr": "baseline PSNR dB"}), ""]
    for r in rows:
        r["speedup_text"] = _interval_text(r.get("speedup", float("nan")), r.get("speedup_lo", float("nan")),
                                           r.get("speedup_hi", float("nan")))
    columns = [c for c in COLUMNS if c not in ("kind", "speedup", "speedup_lo", "speedup_hi")]
    columns.insert(columns.index("repeats") + 1, "speedup_text")
    parts += precision_lines(rows)
    parts += ["## All measurements\n", f"speed-up vs {cfg.compare.baseline}: {interval}.\n",
              markdown_table(rows, columns, FORMATS, {**HEADERS, "speedup_text": f"vs {cfg.compare.baseline} (interval)"})]
    profiled = profile_section(rows)
    if profiled:
        parts += ["", *profiled]
    if plot is not None:
        from denoiser.report.plot_tradeoff import pareto_front_of_rows

        size = tuple(int(v) for v in (cfg.get("plot_size") or cfg.sizes[-1]))
        front = pareto_front_of_rows(rows, size)
        parts += ["", f"Pareto front at {size[1]}x{size[0]} (fastest first): {', '.join(front)}.", "",
                  f"![accuracy vs time]({plot.name})", ""]
    text = "\n".join(parts)
    atomic_write_text(out_dir / "report.md", text)
    return text


def precision_lines(rows: list[dict]) -> list[str]:
    """report.md lines: per method and size timed in OpenVINO f32 and bf16, whether bf16 pays on
    this CPU (median against median, same run), which is what ``denoiser-denoise``'s default
    (``precision=auto``, :func:`denoiser.inference.backends.faster_precision`) measures and runs."""
    lines = []
    timed: dict[tuple, dict[str, float]] = {}
    for r in rows:
        if str(r.get("backend", "")).startswith("openvino") and r.get("status", "ok") == "ok":
            timed.setdefault((r["method"], r["height"], r["width"]), {})[r.get("dtype", "")] = r["ms_median"]
    for (method, h, w), ms in timed.items():
        if "fp32" not in ms or "bf16" not in ms:
            continue
        f32, bf16 = ms["fp32"], ms["bf16"]
        verdict = ("bf16 pays on this CPU: `denoiser-denoise`'s default (precision=auto) runs it" if bf16 < f32 else
                   "bf16 does not pay on this CPU: `denoiser-denoise`'s default (precision=auto) keeps f32")
        lines.append(f"- {method} at {w}x{h}: OpenVINO bf16 {bf16:.1f} ms, f32 {f32:.1f} ms "
                     f"({f32 / bf16:.2f}x); {verdict}.")
    return ["## bf16 or f32 (OpenVINO, same run)\n", *lines, ""] if lines else []


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
    versions, isa = engine_versions(), cpu_isa()
    rows, checks = run_benchmark(cfg, frames, threads, versions, isa)
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
    write_report(out_dir, rows, ratios, machine, cfg, plot_path, checks)
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


def write_json(path: Path, data: dict) -> Path:
    """``data`` as JSON (NaN -> null, so any JSON reader takes it)."""
    def clean(x):
        if isinstance(x, float) and math.isnan(x):
            return None
        if isinstance(x, dict):
            return {str(k): clean(v) for k, v in x.items()}
        if isinstance(x, (list, tuple)):
            return [clean(v) for v in x]
        return x

    return atomic_write_text(path, json.dumps(clean(data), indent=1) + "\n")


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
