"""The accuracy-vs-time plot of ``denoiser-bench``: PSNR against ms per frame (log axis).

One point per method at one frame size, timed with its fastest CPU backend (the backend is
written next to the point): networks as circles, OIDN as squares; the untrained-variant and
checkpoint families named in ``curves`` (e.g. kernel sizes, widths) are joined by a line in
the given order; the Pareto front (no other method is both faster and better) is drawn as a
dashed staircase with its points ringed; the noisy input, which costs nothing, is a dotted
horizontal line.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

from denoiser.atomic import atomic_save_figure


def pareto_front(points: Mapping[str, tuple[float, float]]) -> list[str]:
    """Labels of the points ``{label: (ms, psnr)}`` that no other point dominates, fastest first:
    :func:`denoiser.report.pareto.front_indices` (the one front rule: another point at least as
    fast and at least as good, strictly better in one, dominates)."""
    from denoiser.report.pareto import front_indices

    labels = list(points)
    return [labels[i] for i in front_indices([(points[k][1], points[k][0]) for k in labels])]


def fastest_rows(rows: Sequence[Mapping], size: tuple[int, int], device: str = "cpu") -> dict[str, Mapping]:
    """Per method, its fastest row at ``size`` ``(H, W)`` on ``device`` with a time and a PSNR."""
    best: dict[str, Mapping] = {}
    for r in rows:
        if (int(r["height"]), int(r["width"])) != tuple(size) or r["device"] != device:
            continue
        if math.isnan(float(r["ms_median"])) or math.isnan(float(r.get("psnr", float("nan")))):
            continue
        if r["method"] not in best or r["ms_median"] < best[r["method"]]["ms_median"]:
            best[r["method"]] = r
    return best


def pareto_front_of_rows(rows: Sequence[Mapping], size: tuple[int, int]) -> list[str]:
    """The Pareto front (fastest first) of the methods' fastest CPU rows at ``size``."""
    return pareto_front({k: (float(r["ms_median"]), float(r["psnr"])) for k, r in fastest_rows(rows, size).items()})


def plot_accuracy_vs_time(path: str | os.PathLike, rows: Sequence[Mapping], size: tuple[int, int],
                          curves: Mapping[str, Sequence[str]] | None = None, noisy_psnr: float | None = None,
                          title: str = "", front_kinds: Sequence[str] | None = None) -> Path | None:
    """Write the plot for frames of ``size`` ``(H, W)``; None when no method has time and PSNR.

    ``front_kinds``: only rows of these ``kind`` values make the front (None: every row); a row
    with ``psnr_std`` (a mean over seeds) gets that error bar."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    best = fastest_rows(rows, size)
    if not best:
        return None
    points = {k: (float(r["ms_median"]), float(r["psnr"])) for k, r in best.items()}
    fig, ax = plt.subplots(figsize=(8, 5.5), dpi=120)
    cmap = plt.get_cmap("tab10")
    for i, (name, members) in enumerate((curves or {}).items()):
        pts = [points[m] for m in members if m in points]
        if len(pts) >= 2:
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "-", color=cmap(i + 2), lw=1.5, alpha=0.8,
                    label=f"{name} (curve)", zorder=1)
    offsets = [(8, 4), (8, -16), (8, 14), (8, -26)]  # alternate label positions of neighbouring points
    for rank, k in enumerate(sorted(best, key=lambda m: points[m][0])):
        r = best[k]
        baseline = r.get("kind") == "baseline"
        ax.scatter(*points[k], marker="s" if baseline else "o", s=55, zorder=3,
                   color=cmap(0) if baseline else cmap(1), edgecolor="black", linewidth=0.6)
        std = float(r.get("psnr_std", float("nan")))
        if not math.isnan(std):
            ax.errorbar(*points[k], yerr=std, color="black", lw=0.8, capsize=3, zorder=2)
        text = k if baseline else f"{k} ({r['backend']})"
        ax.annotate(text, points[k], textcoords="offset points", xytext=offsets[rank % len(offsets)], fontsize=7.5)
    front = pareto_front({k: p for k, p in points.items()
                          if front_kinds is None or best[k].get("kind") in front_kinds})
    xs, ys = [], []
    for k in front:
        t, q = points[k]
        if xs:
            xs.append(t)
            ys.append(ys[-1])
        xs.append(t)
        ys.append(q)
    ax.plot(xs, ys, "--", color="black", lw=1, zorder=2, label="Pareto front")
    ax.scatter([points[k][0] for k in front], [points[k][1] for k in front], s=170, facecolor="none",
               edgecolor="black", linewidth=1.0, zorder=2)
    ax.scatter([], [], marker="s", color=cmap(0), edgecolor="black", label="OIDN (pyoidn)")
    ax.scatter([], [], marker="o", color=cmap(1), edgecolor="black", label="our networks (fastest backend)")
    if noisy_psnr is not None and not math.isnan(noisy_psnr):
        ax.axhline(noisy_psnr, color="gray", ls=":", lw=1.2, label=f"noisy input ({noisy_psnr:.2f} dB, 0 ms)")
    ax.set_xscale("log")
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    # labelled ticks at 1, 2, 3 and 5 times powers of ten, plain numbers (ms), unlabelled minor ticks
    ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 3.0, 5.0)))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.xaxis.set_minor_locator(LogLocator(base=10, subs=(4.0, 6.0, 7.0, 8.0, 9.0)))
    ax.xaxis.set_minor_formatter(NullFormatter())
    times = [p[0] for p in points.values()]
    ax.set_xlim(min(times) / 2, max(times) * 3)
    quals = [p[1] for p in points.values()] + ([noisy_psnr] if noisy_psnr is not None else [])
    pad = max(0.5, 0.08 * (max(quals) - min(quals)))
    ax.set_ylim(min(quals) - pad, max(quals) + pad)
    ax.set_xlabel(f"time per frame at {size[1]}x{size[0]} (ms, log scale)")
    ax.set_ylabel("PSNR (dB, ACES + sRGB tonemapped), higher is better")
    ax.set_title(title or "accuracy vs time", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="best", framealpha=0.9)
    fig.tight_layout()
    return atomic_save_figure(fig, path)
