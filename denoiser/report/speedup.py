"""The speed-ups of ``denoiser-bench``: every method against the baseline (OIDN-fast) paired per
round (the median of the per-round ratios with a distribution-free interval,
:func:`denoiser.measure.median_interval`), the student-vs-baseline rows of the report, the
harness's overhead on OIDN, and the rows' order (a network's fp32 rows beside its bf16 rows).
Rows are :func:`denoiser.report.bench_timing.bench_row`'s dicts.
"""

from __future__ import annotations

import math
from collections import OrderedDict

from denoiser.measure import median_interval

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



def interval_text(mid: float, lo: float, hi: float) -> str:
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
                        "repeats": s["repeats"], "speedup_text": interval_text(s["speedup"], s["speedup_lo"], s["speedup_hi"]),
                        "student_psnr": s.get("psnr", float("nan")), "baseline_psnr": b.get("psnr", float("nan")),
                        "psnr_gain": s.get("psnr", float("nan")) - b.get("psnr", float("nan"))})
    return out



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
