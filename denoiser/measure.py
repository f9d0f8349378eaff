"""The measurement kit every benchmark uses: FLOPs, the matmul peak, peak memory, timing
medians, and tables (Markdown and CSV).
"""

from __future__ import annotations

import csv
import io
import math
import os
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import torch

from denoiser.atomic import atomic_write_text
from denoiser.errors import UserError
from denoiser.runner import RecurrentRunner

if TYPE_CHECKING:
    from denoiser.backends import Stepper


class PeakRss:
    """Peak resident set size above the starting level, sampled every ``interval`` seconds."""

    def __init__(self, interval: float = 0.002):
        self.interval = interval
        self.page = os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096
        self.peak = 0
        self._stop = threading.Event()

    def _rss(self) -> int:
        try:
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * self.page
        except OSError:  # not Linux: resource's max RSS is the best we have
            import resource

            return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(self.interval)

    def __enter__(self):
        self.base = self._rss()
        self.peak = self.base
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, self._rss())

    @property
    def megabytes(self) -> float:
        return (self.peak - self.base) / 2**20


def time_steps(stepper: Stepper, frames: list[dict], warmup: int, repeats: int) -> list[float]:
    """Seconds of each of ``repeats`` recurrent steps after ``warmup`` steps (state carried by
    the runner, reset on the first frame; ``frames`` are cycled)."""
    runner = RecurrentRunner(stepper.step)
    sequence = ((frames[i % len(frames)], i == 0) for i in range(warmup + repeats))
    times = []
    start = time.perf_counter()
    for i, _ in enumerate(runner.run(sequence)):
        stepper.sync()
        if i >= warmup:
            times.append(time.perf_counter() - start)
        start = time.perf_counter()
    return times


def measure_matmul_peak(threads: int, size: int = 1024, repeats: int = 5) -> float:
    """fp32 GFLOP/s of a ``size`` x ``size`` matrix product on the CPU (best of ``repeats``)."""
    a, b = torch.randn(size, size), torch.randn(size, size)
    torch.mm(a, b)
    best = min(_timed(lambda: torch.mm(a, b)) for _ in range(repeats))
    return 2 * size**3 / best / 1e9


def _timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def count_gflop(net: torch.nn.Module, frame: Mapping[str, torch.Tensor]) -> float:
    """GFLOP of one recurrent step (with history) of ``net`` on ``frame`` (conv and matmul)."""
    from torch.utils.flop_counter import FlopCounterMode

    net = net.to("cpu").float().to(memory_format=torch.contiguous_format)
    runner = RecurrentRunner(net.step)
    with torch.inference_mode():
        runner(dict(frame), reset=True)
        with FlopCounterMode(display=False) as counter:
            runner(dict(frame))
    return counter.get_total_flops() / 1e9


# ----------------------------------------------------------------------------- tables


def _cell(value) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return "" if value is None else str(value)


def write_csv(path: str | os.PathLike, rows: Sequence[Mapping], columns: Sequence[str] | None = None) -> Path:
    """Write ``rows`` (dicts) as CSV with ``columns`` (default: keys in first-seen order); NaN -> empty."""
    if columns is None:
        columns = []
        for r in rows:
            columns.extend(k for k in r if k not in columns)
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(columns)
    for r in rows:
        writer.writerow([_cell(r.get(c)) for c in columns])
    return atomic_write_text(path, buf.getvalue())


def _parse(value: str):
    if value == "":
        return float("nan")
    try:
        return int(value)
    except ValueError:
        pass
    try:
        return float(value)
    except ValueError:
        return value


def read_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a CSV written by :func:`write_csv` (numbers parsed, empty cells -> NaN)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: CSV file does not exist")
    with open(path, newline="") as fh:
        return [{k: _parse(v) for k, v in row.items()} for row in csv.DictReader(fh)]


def format_value(value, fmt: str | None = None) -> str:
    """One table cell: floats with ``fmt`` (default 4 significant digits), NaN as an en dash."""
    if isinstance(value, float):
        if math.isnan(value):
            return "–"
        return format(value, fmt or ".4g")
    return "" if value is None else str(value)


def markdown_table(rows: Sequence[Mapping], columns: Sequence[str], formats: Mapping[str, str] | None = None,
                   headers: Mapping[str, str] | None = None) -> str:
    """A Markdown table of ``rows`` with ``columns``; ``formats``: column -> format spec."""
    formats = dict(formats or {})
    headers = dict(headers or {})
    lines = ["| " + " | ".join(headers.get(c, c) for c in columns) + " |",
             "|" + "|".join("---" if i == 0 else "---:" for i, _ in enumerate(columns)) + "|"]
    for r in rows:
        lines.append("| " + " | ".join(format_value(r.get(c), formats.get(c)) for c in columns) + " |")
    return "\n".join(lines) + "\n"
