"""What the flicker measure (:mod:`denoiser.report.flicker`) says: per stream a row and a Markdown
table (:func:`summary_rows`, :func:`summary_table`), a plot over frames (:func:`plot_flicker`),
``denoiser-denoise``'s record of a run (:func:`denoise_report`: ``report.json``, ``report.md``,
``flicker.png``), and the check that the warp error orders methods as tPSNR does, from
``denoiser-eval``'s per-sequence rows (:func:`ordering_agreement`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence

import numpy as np

from denoiser.report.flicker import FlickerMeter, WarpError

# ----------------------------------------------------------------------------- agreement with tPSNR


def ordering_agreement(rows: Sequence[Mapping], methods: Sequence[str], resamples: int = 2000, seed: int = 0,
                       confidence: float = 0.95) -> dict:
    """Does the warp error order methods as tPSNR does? From ``denoiser-eval``'s per-sequence rows
    (``metrics.csv``: ``method``, ``sequence``, ``warp``, ``tpsnr``; ``sequence=mean`` rows skipped).

    Per sequence holding every one of ``methods`` with both values: the methods' order by warp
    error (ascending) against their order by tPSNR (descending); ``agreement`` is the share of
    those sequences whose two orders are the same. ``spearman`` is the rank correlation over all
    (method, sequence) pairs between ``-warp`` and ``tpsnr`` (so +1 is full agreement) with its
    percentile bootstrap interval over sequences (``resamples`` draws, ``seed``). Returns
    ``{"sequences", "agreement", "spearman", "lo", "hi", "per_sequence": {seq: bool}}``.
    """
    table: dict[str, dict[str, tuple[float, float]]] = {}
    for r in rows:
        if str(r["sequence"]) == "mean" or str(r["method"]) not in methods:
            continue
        w, t = _cell(r.get("warp")), _cell(r.get("tpsnr"))
        if w is not None and t is not None:
            table.setdefault(str(r["sequence"]), {})[str(r["method"])] = (w, t)
    seqs = [s for s, per in table.items() if all(m in per for m in methods)]
    if not seqs:
        raise ValueError(f"ordering agreement: no sequence has warp and tpsnr for every one of {list(methods)}")
    same = {}
    for s in seqs:
        by_warp = sorted(methods, key=lambda m: table[s][m][0])
        by_tpsnr = sorted(methods, key=lambda m: -table[s][m][1])
        same[s] = by_warp == by_tpsnr

    def rho(chosen) -> float:
        x = [-table[s][m][0] for s in chosen for m in methods]
        y = [table[s][m][1] for s in chosen for m in methods]
        return _spearman(x, y)

    rng = np.random.default_rng(seed)
    draws = [rho([seqs[i] for i in rng.integers(0, len(seqs), len(seqs))]) for _ in range(resamples)]
    draws = [d for d in draws if not math.isnan(d)]
    alpha = (1.0 - confidence) / 2.0
    lo, hi = (float(np.quantile(draws, alpha)), float(np.quantile(draws, 1.0 - alpha))) if draws else (math.nan,) * 2
    return {"sequences": len(seqs), "agreement": sum(same.values()) / len(seqs), "spearman": rho(seqs),
            "lo": lo, "hi": hi, "per_sequence": same}


def agreement_lines(per_sequence: Mapping[str, Mapping[str, Mapping[str, float]]], methods: Sequence[str],
                    goal: float = 0.8) -> list[str]:
    """Markdown lines of :func:`ordering_agreement` for a summary: ``per_sequence`` is
    ``{method or seed group: {column: {sequence: value}}}`` (a seed group's value is the mean over its
    seeds, :func:`denoiser.report.seed_groups.group_sequences`); ``goal`` the share of sequences whose
    orders must agree. A method without warp and tPSNR values is named in one line instead."""
    missing = [m for m in methods if not per_sequence.get(m, {}).get("warp") or not per_sequence[m].get("tpsnr")]
    head = ["## The warp error against tPSNR", ""]
    if missing:
        return [*head, f"No check: no per-sequence warp error and tPSNR for {', '.join(missing)}.", ""]
    rows = [{"method": m, "sequence": seq, "warp": w, "tpsnr": per_sequence[m]["tpsnr"].get(seq)}
            for m in methods for seq, w in per_sequence[m]["warp"].items()]
    res = ordering_agreement(rows, methods)
    verdict = "meets" if res["agreement"] >= goal else "misses"
    return [*head,
            (f"Per test sequence, the order of {', '.join(methods)} by warp error (no reference; lower is "
             f"steadier) against their order by tPSNR (against the references): the same in "
             f"**{res['agreement']:.0%}** of {res['sequences']} sequences ({verdict} the {goal:.0%} goal). "
             f"Spearman's rank correlation of -warp error and tPSNR over every (method, sequence) pair: "
             f"**{res['spearman']:+.3f}** (95% bootstrap interval over sequences {res['lo']:+.3f} to {res['hi']:+.3f})."),
            "", "Sequences whose two orders differ: "
            + (", ".join(f"`{s}`" for s, same in res["per_sequence"].items() if not same) or "none") + ".", ""]


def _cell(value) -> float | None:
    if value in (None, ""):
        return None
    value = float(value)
    return None if math.isnan(value) else value


def _ranks(x: Sequence[float]) -> np.ndarray:
    """Average ranks (ties share their mean rank), 1-based."""
    x = np.asarray(x, dtype=np.float64)
    order = np.argsort(x, kind="mergesort")
    ranks = np.empty(len(x))
    ranks[order] = np.arange(1, len(x) + 1)
    for v in np.unique(x):
        tied = x == v
        ranks[tied] = ranks[tied].mean()
    return ranks


def _spearman(x: Sequence[float], y: Sequence[float]) -> float:
    """Spearman's rank correlation (Pearson's of the average ranks); NaN when a side is constant."""
    rx, ry = _ranks(x), _ranks(y)
    rx, ry = rx - rx.mean(), ry - ry.mean()
    denom = math.sqrt(float((rx * rx).sum() * (ry * ry).sum()))
    return float((rx * ry).sum() / denom) if denom > 0 else math.nan


# ----------------------------------------------------------------------------- table, plot, record


def summary_rows(results: Mapping[str, WarpError]) -> list[dict]:
    """One row per stream: ``name``, ``mean`` (×1e3), ``kept`` (mean share of pixels), ``frames``
    measured, ``mask``; a stream without a defined value is a ValueError naming it."""
    rows = []
    for name, r in results.items():
        try:
            mean = r.mean
        except ValueError as err:
            raise ValueError(f"{name}: {err}") from None
        rows.append({"name": name, "mean": mean, "kept": r.mean_kept,
                     "frames": sum(not math.isnan(v) for v in r.per_frame), "mask": r.mask})
    return rows


#: the columns of :func:`summary_table`: format and header
TABLE_FORMATS = {"mean": ".3f", "kept": ".1%"}
TABLE_HEADERS = {"name": "frames of", "mean": "warp err ×1e3 ↓", "kept": "pixels kept", "frames": "frames measured",
                 "mask": "visibility test"}


def summary_table(results: Mapping[str, WarpError], align: bool = True) -> str:
    """Markdown table of :func:`summary_rows` (one row per stream, the mean warp error first)."""
    from denoiser.tables import markdown_table

    return markdown_table(summary_rows(results), ["name", "mean", "kept", "frames", "mask"], TABLE_FORMATS,
                          TABLE_HEADERS, align=align)


def plot_flicker(path, results: Mapping[str, WarpError], title: str, frame_numbers: Sequence[int] | None = None):
    """PNG of the warp error over frames, one line per stream (frames counted from 1, or
    ``frame_numbers``), its mean in the legend; written atomically. Returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from denoiser.atomic import atomic_save_figure

    fig, ax = plt.subplots(figsize=(8, 4), dpi=120)
    for name, r in results.items():
        xs = list(frame_numbers) if frame_numbers is not None else list(range(1, len(r.per_frame) + 1))
        ax.plot(xs, r.per_frame, "o-", ms=3, lw=1.5, label=f"{name} (mean {r.mean:.3f})")
    ax.set_xlabel("frame")
    ax.set_ylabel("warp error ×1e3 (lower is steadier)")
    ax.set_title(title, fontsize=10)
    ax.set_ylim(bottom=0)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return atomic_save_figure(fig, path)


def json_values(values: Sequence[float]) -> list[float | None]:
    """Per-frame values for JSON: NaN (first frame, cuts) as null."""
    return [None if math.isnan(v) else float(v) for v in values]


# ----------------------------------------------------------------------------- denoiser-denoise's report


def denoise_report(meter: FlickerMeter | None, frames: Sequence[int], info: Mapping, out_dir) -> dict:
    """``denoiser-denoise``'s record of a run, written into ``out_dir``: ``report.json``, ``report.md``
    and (with a meter) ``flicker.png``, the warp error of the input and the output over frames.

    meter: a :class:`FlickerMeter` of the streams ``input`` and ``output`` (None: the frames have no
    motion, no flicker measured); frames: the frame numbers (1-based) measured, one per meter entry;
    info: what the run was (``input``, ``frames``, ``seconds``, ``backend``, ``precision``, ``threads``,
    ``size``, ``measure_seconds``: the time the measure took). Returns the JSON record.
    """
    from pathlib import Path

    from denoiser.atomic import atomic_write_text

    out_dir = Path(out_dir)
    seconds = float(info["seconds"])
    seconds = max(seconds, 1e-9)
    record = {**info, "frames_per_second": len(frames) / seconds,
              "measure_share": float(info.get("measure_seconds", 0.0)) / seconds, "frame_numbers": list(frames),
              "stride": meter.stride if meter is not None else None}
    lines = [f"# denoiser-denoise report: {info['input']}", "",
             (f"{len(frames)} frame(s) of {info['size'][1]}x{info['size'][0]} in {seconds:.1f} s "
              f"({record['frames_per_second']:.2f} frames/s), backend {info['backend']}, precision "
              f"{info['precision']}, {info['threads']} thread(s)."), ""]
    if meter is None:
        record["flicker"] = None
        lines.append("No flicker measured: the input frames have no motion pass.")
    else:
        results = {n: meter.result(n) for n in ("input", "output")}
        defined = any(not math.isnan(v) for v in results["output"].per_frame)
        record["flicker"] = {n: {"mean": r.mean if defined else None, "kept": r.mean_kept if defined else None,
                                 "per_frame": json_values(r.per_frame), "kept_per_frame": json_values(r.kept)}
                             for n, r in results.items()}
        record["flicker"]["mask"] = meter.mask
        if defined:
            plot_flicker(out_dir / "flicker.png", results, f"{info['input']}: warp error of the noisy input and "
                         "of the denoised output", frames)
            lines += ["## Flicker (warp error, no reference needed)", "",
                      summary_table(results, align=False).rstrip(), "",
                      (f"Warp error (Lai et al. 2018; denoiser/metrics.py `warp`): per frame, the mean over the "
                       f"pixels visible in both frames (test: {meter.mask}; every {_nth(meter.stride)} pixel in x and "
                       "y) of the squared distance between the tonemapped frame and the previous one warped along "
                       "the motion vectors, ×1e3; lower is steadier. It also counts real changes of shading (moving "
                       "lights and highlights): compare the output with the input and with other denoisers' frames "
                       "of the same render (denoiser-flicker), not with 0. "
                       f"The measure took {record['measure_share']:.1%} of the run."), "",
                      "![flicker over frames](flicker.png)", "",
                      "| frame | input | output |", "|---:|---:|---:|"]
            lines += [f"| {f} | {_fmt(a)} | {_fmt(b)} |" for f, a, b in
                      zip(frames, results["input"].per_frame, results["output"].per_frame)]
        else:
            lines.append("No flicker measured: no frame has a previous one (a single frame, or cuts everywhere).")
    atomic_write_text(out_dir / "report.json", json.dumps(record, indent=1, allow_nan=False) + "\n")
    atomic_write_text(out_dir / "report.md", "\n".join(lines) + "\n")
    return record


def _nth(stride: int) -> str:
    return "" if stride == 1 else {2: "2nd", 3: "3rd"}.get(stride, f"{stride}th")


def _fmt(v: float) -> str:
    return "" if math.isnan(v) else f"{v:.3f}"
