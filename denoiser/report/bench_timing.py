"""``denoiser-bench``'s measurement: every method (baselines, and each network on each backend of
the config group ``conf/backends/``) timed on the same frames at every size, interleaved in
rounds (:func:`run_benchmark`), the networks' PSNR through each backend (:func:`backend_quality`),
and the frames and methods a bench config names. The command and what it measures:
:mod:`denoiser.commands.bench`; the speed-up statistics :mod:`denoiser.report.speedup`; the
report :mod:`denoiser.report.bench_report`. OIDN's timed paths are
:func:`denoiser.methods.baselines.oidn_harness_steps` and :func:`~denoiser.methods.baselines.oidn_direct_steps`.
"""

from __future__ import annotations

import contextlib
from collections import OrderedDict

import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from denoiser.buffers import FRAME_INPUTS
from denoiser.errors import ConfigError
from denoiser.frames import resize_frame
from denoiser.machine import cpu_isa
from denoiser.measure import PeakRss, StagedStep, count_flops, recurrent_steps, round_robin, summarize
from denoiser.methods.baselines import oidn_direct_steps, oidn_dtype, oidn_harness_steps
from denoiser.recurrent import Stepper
from denoiser.report.bench_report import engine_versions
from denoiser.report.speedup import add_speedups, harness_check, precision_order


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
    of the matmul peak is set by :func:`denoiser.commands.bench.run`, which measures the peak around them) and, with
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
            if stepper.extension_profile is not None:
                row["extension_profile"] = stepper.extension_profile()  # {extension op: ms}, within Reference
            if stepper.kernels is not None:
                with contextlib.suppress(Exception):  # as threads: an engine that cannot say leaves it out
                    row["kernels"] = stepper.kernels()  # the implementations the last step ran
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
