"""``denoiser-bench``'s outputs: ``report.md`` (:func:`write_report`: the machine line, the harness
checks, the student vs OIDN-fast table, bf16 or f32, every measurement, where the time goes),
``bench.csv``'s columns (:data:`COLUMNS`), ``bench.json`` (:func:`write_json`) and the machine
and software of a run (:func:`machine_info`, :func:`engine_versions`).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import time
from collections import OrderedDict
from pathlib import Path

import torch
from omegaconf import DictConfig

from denoiser.atomic import atomic_write_text
from denoiser.machine import ISA_CAPS, cpu_model, cpu_signature, isa_caps
from denoiser.methods.baselines import oidn_dtype
from denoiser.report.speedup import interval_text
from denoiser.tables import markdown_table

COLUMNS = ["method", "backend", "dtype", "device", "height", "width", "ms_median", "ms_min", "ms_max", "repeats",
           "speedup", "speedup_lo", "speedup_hi", "gflop", "params", "peak_mb", "gflops_per_s", "peak_fraction", "psnr",
           "psnr_eval", "psnr_from", "kind", "engine", "threads", "status"]


FORMATS = {"ms_median": ".1f", "ms_min": ".1f", "ms_max": ".1f", "gflop": ".2f", "peak_mb": ".0f", "gflops_per_s": ".1f",
           "peak_fraction": ".1%", "psnr": ".2f", "psnr_eval": ".2f", "student_psnr": ".2f", "baseline_psnr": ".2f",
           "ratio": ".2f", "psnr_gain": "+.2f", "student_ms": ".1f", "baseline_ms": ".1f"}


HEADERS = {"ms_median": "ms/frame (median)", "ms_min": "ms min", "ms_max": "ms max", "gflop": "GFLOP", "peak_mb": "peak MB",
           "gflops_per_s": "GFLOP/s", "peak_fraction": "of matmul peak", "psnr": "PSNR dB",
           "psnr_eval": "PSNR dB (eval, eager fp32)", "psnr_from": "PSNR from", "speedup_text": "speed-up (interval)"}



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


def machine_info(threads: int, peak_gflops: float, versions: dict[str, str], isa: dict[str, bool]) -> dict:
    """The machine and software of a run: ``cpu`` (model name), ``cpu_id`` (:func:`cpu_signature`),
    ``logical_cores``, ``isa`` (:func:`cpu_isa`), ``versions`` (:func:`engine_versions`),
    ``threads_requested``, ``matmul_peak_gflops``, ``gpu``, ``isa_caps`` (:func:`denoiser.machine.isa_caps`:
    the instruction-set caps in the environment) and the run's UTC ``date`` and code ``commit``
    (:func:`denoiser.report.provenance.git_commit`)."""
    from denoiser.report.provenance import git_commit

    return {"cpu": cpu_model(), "cpu_id": cpu_signature(), "logical_cores": os.cpu_count(), "isa": dict(isa),
            "versions": dict(versions), "threads_requested": threads, "matmul_peak_gflops": peak_gflops,
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else "none",
            "isa_caps": isa_caps(), "date": time.strftime("%Y-%m-%d", time.gmtime()), "commit": git_commit()}



def machine_description(info: dict) -> str:
    """The report's machine line of :func:`machine_info`."""
    isa = ", ".join(f"{f} {'yes' if v else 'no'}" for f, v in info["isa"].items())
    versions = ", ".join(f"{k} {v}" for k, v in info["versions"].items())
    return (f"CPU: {info['cpu']}, {info['logical_cores']} logical cores ({isa}), {info['threads_requested']} thread(s) "
            f"requested for every method (the threads column: what each engine reports it uses); "
            f"fp32 matmul peak {info['matmul_peak_gflops']:.1f} GFLOP/s (2048x2048, the faster of torch.mm and OpenVINO's MatMul, best of 5, "
            f"the larger of the measurements before and after the methods); GPU: {info['gpu']}; versions: {versions}; "
            f"OIDN computes in {oidn_dtype(info['isa'])} on this CPU" + caps_sentence(info.get("isa_caps") or {}))


def caps_sentence(caps: dict[str, str]) -> str:
    """The machine line's sentence on the instruction-set caps of a run (:func:`denoiser.machine.isa_caps`);
    ``""`` for none."""
    if not caps:
        return ""
    named = "; ".join(f"${k}={v} ({ISA_CAPS[k]})" for k, v in caps.items())
    return (f". **Instruction sets capped** below this CPU's: {named}. OIDN reads no such cap, so a ratio "
            "against OIDN here is neither this CPU's nor that of a CPU without the instructions; the "
            "kernels that ran are named under \"Which kernels ran\"")


def kernels_section(rows: list[dict]) -> list[str]:
    """report.md lines: per row whose engine named them (``kernels``: :class:`denoiser.recurrent.Stepper`),
    the implementations its last step ran, by node type (those without a kernel of their own left
    out), and what the project's extension was built for; the sizes of one method and backend that
    ran the same ones share a line."""
    sizes: dict[tuple[str, str, str], list[str]] = {}  # (method, backend, what ran) -> its sizes
    for r in rows:
        k = r.get("kernels")
        if not k:
            continue
        ran = "; ".join(f"{kind} " + ", ".join(f"{impl} x{n}" for impl, n in impls.items())
                        for kind, impls in (k.get("openvino") or {}).items()
                        if not all(impl.startswith("unknown") for impl in impls))
        if k.get("extension"):
            ran += f"; the extension's operations (`Reference`) built for {k['extension']}"
        sizes.setdefault((r["method"], r["backend"], ran), []).append(f"{r['width']}x{r['height']}")
    if not sizes:
        return []
    out = ["## Which kernels ran\n", ("OpenVINO's implementation of each node type (from the compiled model: the "
                                      "instruction set is in the name), with the node count:\n")]
    out += [f"- **{method}**, {backend} ({', '.join(at)}): {ran}" for (method, backend, ran), at in sizes.items()]
    return [*out, ""]



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
                 plot: Path | None, checks: list[dict] | None = None, caps: dict[str, str] | None = None) -> str:
    """report.md; ``caps``: the run's instruction-set caps (``machine_info``'s ``isa_caps``), which mark
    the ratio against OIDN as not like for like."""
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
                  f"Each precision against OIDN's own ({interval})."
                  + (" **Not a like-for-like ratio: this run capped the instruction sets of every engine but OIDN "
                     "(the machine line).**" if caps else "") + "\n",
                  markdown_table(ratios, ["size", "compare", "student", "student_ms", "baseline_ms", "speedup_text",
                                          "student_psnr", "baseline_psnr", "psnr_gain"],
                                 FORMATS, {"student_ms": "student ms", "baseline_ms": f"{ratios[0]['baseline']} ms",
                                           "speedup_text": "speed-up x (interval)", "psnr_gain": "PSNR gain dB",
                                           "student_psnr": "student PSNR dB", "baseline_psnr": "baseline PSNR dB"}), ""]
    for r in rows:
        r["speedup_text"] = interval_text(r.get("speedup", float("nan")), r.get("speedup_lo", float("nan")),
                                           r.get("speedup_hi", float("nan")))
    columns = [c for c in COLUMNS if c not in ("kind", "speedup", "speedup_lo", "speedup_hi")]
    columns.insert(columns.index("repeats") + 1, "speedup_text")
    parts += precision_lines(rows)
    parts += ["## All measurements\n", f"speed-up vs {cfg.compare.baseline}: {interval}.\n",
              markdown_table(rows, columns, FORMATS, {**HEADERS, "speedup_text": f"vs {cfg.compare.baseline} (interval)"})]
    profiled = profile_section(rows)
    if profiled:
        parts += ["", *profiled]
    kernels = kernels_section(rows)
    if kernels:
        parts += ["", *kernels]
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
        total = sum(p["ms"] for p in ops)
        parts += [f"**{key[0]}**, {key[1]}, {key[3]}x{key[2]}: {total:.0f} ms of node time\n",
                  markdown_table(shown, ["op_type", "ms", "share"], {"ms": ".1f", "share": ".1%"},
                                 {"op_type": "op type"}), ""]
        row = next(r for r in rows if (r["method"], r["backend"], r["height"], r["width"]) == key)
        extension = [{"op": op, "ms": ms, "share": ms / total if total else float("nan")}
                     for op, ms in (row.get("extension_profile") or {}).items()]
        if extension:
            parts += ["The extension's operations (the `Reference` nodes above), per operation:\n",
                      markdown_table(extension, ["op", "ms", "share"], {"ms": ".1f", "share": ".1%"},
                                     {"share": "share of node time"}), ""]
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
