"""The measurement kit every benchmark uses: FLOPs, the matmul peak, peak memory, timings and
their medians, and tables (Markdown and CSV).

* FLOPs: :func:`count_flops` (one recurrent step with history, shapes only);
* the machine's matmul peak: :func:`matmul_peak`;
* peak memory: :class:`PeakRss` (of a block in this process: sampled, or the kernel's
  high-water mark; see there which applies when) and :func:`run_process` (of a whole child
  process);
* timings: :class:`Clock` (wall and CPU seconds of a block), :func:`clock_steps` /
  :func:`time_steps` (recurrent steps through the runner), :func:`round_robin` (several
  methods' steps interleaved: each repeat times every method once, in a rotated order),
  :func:`summarize` (median, min, max), :func:`median_interval` (the median of repeated ratios
  with a distribution-free confidence interval) and :func:`fastest`;
* tables: :func:`markdown_table`, :func:`write_csv` / :func:`read_csv`.

Used by ``denoiser-bench``, ``denoiser-eval`` and the tools ``netstats``, ``bench_networks``,
``bench_data``, ``bench_longseq`` and ``bench_render`` (:mod:`denoiser.commands`).
"""

from __future__ import annotations

import contextlib
import csv
import io
import math
import os
import statistics
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path

import torch

from denoiser.atomic import atomic_write_text
from denoiser.errors import UserError
from denoiser.runner import RecurrentRunner, Stepper

# ----------------------------------------------------------------------------- memory

_PAGE_KIB = (os.sysconf("SC_PAGE_SIZE") if hasattr(os, "sysconf") else 4096) // 1024


def _proc_kib(what: str) -> int | None:
    """This process's resident set size in KiB from procfs, None where there is none.

    ``what``: ``"rss"`` (now; ``/proc/self/statm``, cheap enough to sample every few ms) or
    ``"hwm"`` (the peak since the process started or since :func:`reset_peak_rss`; ``VmHWM`` of
    ``/proc/self/status``).
    """
    try:
        if what == "rss":
            with open("/proc/self/statm") as fh:
                return int(fh.read().split()[1]) * _PAGE_KIB
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _max_rss_kib() -> int:
    """Peak RSS of the process's whole life in KiB (``ru_maxrss``; cannot be reset)."""
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (``VmHWM``) of this process to its current RSS through
    ``/proc/self/clear_refs`` (Linux); False where that is not possible."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


class PeakRss:
    """Peak resident set size of this process during a ``with`` block above its level at entry:
    ``megabytes`` (MiB).

    Two ways to find the peak (``method``):

    * ``"sample"`` (default): a thread reads the RSS every ``interval`` seconds. It touches
      nothing process-wide, so it suits a process that measures many things in turn
      (``denoiser-bench``); a spike shorter than ``interval`` can be missed.
    * ``"hwm"``: the kernel's own high-water mark, reset at entry (:func:`reset_peak_rss`) and
      read at exit: exact, spikes included, but there is one mark per process, so use it in a
      process of its own that measures one thing (``bench_networks`` runs every configuration
      in a fresh subprocess). Where the mark cannot be reset, it samples instead.

    Without procfs (not Linux) both read ``ru_maxrss``, which cannot be reset: the growth is
    then only seen when the block sets a new peak for the whole process.
    """

    def __init__(self, interval: float = 0.002, method: str = "sample"):
        if method not in ("sample", "hwm"):
            raise ValueError(f"PeakRss method: 'sample' or 'hwm', got {method!r}")
        self.interval = interval
        self.method = method
        self.base = self.peak = 0  # KiB
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @staticmethod
    def _rss() -> int:
        rss = _proc_kib("rss")
        return _max_rss_kib() if rss is None else rss

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self._rss())
            time.sleep(self.interval)

    def __enter__(self):
        hwm = self.method == "hwm" and reset_peak_rss()
        self.base = self.peak = self._rss()
        if not hwm:
            self._thread = threading.Thread(target=self._run, daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc):
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
            self.peak = max(self.peak, self._rss())
        else:
            hwm = _proc_kib("hwm")
            self.peak = max(self.peak, self._rss() if hwm is None else hwm)

    @property
    def megabytes(self) -> float:
        return (self.peak - self.base) / 1024


@dataclass
class ProcessRun:
    """A finished child process: exit ``returncode``, its ``stderr`` text, ``wall`` seconds and
    ``peak_mb``, its peak resident set size in MiB (``ru_maxrss``)."""

    returncode: int
    stderr: str
    wall: float
    peak_mb: float


def run_process(argv: Sequence[str]) -> ProcessRun:
    """Run ``argv`` to its end (stdout discarded) and read its peak RSS from the kernel
    (``os.wait4``): the third way to find a peak, for a whole command (interpreter, imports,
    every read and write), e.g. ``bench_longseq``'s runs of ``denoiser-denoise``."""
    import subprocess

    with Clock() as clock:
        proc = subprocess.Popen(list(argv), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        stderr = proc.stderr.read()  # drained while it runs (progress bars), so the pipe never blocks
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    proc.stderr.close()
    return ProcessRun(proc.returncode, stderr.decode(errors="replace"), clock.wall, usage.ru_maxrss / 1024.0)


# ----------------------------------------------------------------------------- time


class Clock:
    """Wall and CPU seconds (``wall``, ``cpu``: all threads of this process) between ``start()``
    and ``stop()``, or of a ``with`` block."""

    wall: float = 0.0
    cpu: float = 0.0

    def start(self) -> Clock:
        self._wall, self._cpu = time.perf_counter(), time.process_time()
        return self

    def stop(self) -> Clock:
        self.wall, self.cpu = time.perf_counter() - self._wall, time.process_time() - self._cpu
        return self

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


def clock_steps(stepper: Stepper, frames: list[dict], warmup: int, repeats: int) -> tuple[list[Clock], list[Clock]]:
    """Clocks of ``warmup`` then ``repeats`` recurrent steps of ``stepper`` over ``frames``
    (``{buffer: [B, C, H, W]}`` each, cycled; state carried by the runner, reset on the first
    frame; ``stepper.sync()`` ends each step).

    Returns ``(warm-up clocks, timed clocks)``; each step's clock starts where the previous
    one stopped.
    """
    runner = RecurrentRunner(stepper.step)
    sequence = ((frames[i % len(frames)], i == 0) for i in range(warmup + repeats))
    clocks = []
    clock = Clock().start()
    for _ in runner.run(sequence):
        stepper.sync()
        clocks.append(clock.stop())
        clock = Clock().start()
    return clocks[:warmup], clocks[warmup:]


def time_steps(stepper: Stepper, frames: list[dict], warmup: int, repeats: int) -> list[float]:
    """Wall seconds of each of ``repeats`` recurrent steps after ``warmup`` steps (:func:`clock_steps`)."""
    return [c.wall for c in clock_steps(stepper, frames, warmup, repeats)[1]]


def summarize(times: Sequence[float]) -> dict[str, float]:
    """``{"median", "min", "max", "runs"}`` of repeated timings (any unit; an even count's median
    is the mean of the middle two). What every benchmark reports of its repeats."""
    return {"median": statistics.median(times), "min": min(times), "max": max(times), "runs": len(times)}


def median_interval(values: Sequence[float], level: float = 0.95) -> dict[str, float]:
    """The median of ``values`` (e.g. per-repeat ratios of paired timings) and a distribution-free
    confidence interval for it from order statistics (the sign test's interval).

    With ``n`` sorted values ``x_1 <= ... <= x_n``, ``[x_k, x_(n+1-k)]`` holds the true median with
    probability ``1 - 2 P(Binomial(n, 1/2) <= k - 1)`` whatever the distribution; ``k`` is the
    largest whose coverage reaches ``level``. For 7 or 8 values that is the min-max (98.4%,
    99.2%), for 9 to 11 the second smallest and second largest. Fewer than 6 values never reach
    95%: the min-max is returned with its lower coverage (5 values: 93.8%).

    Returns ``{"median", "lo", "hi", "coverage", "runs"}``.
    """
    x = sorted(float(v) for v in values)
    n = len(x)
    if n == 0:
        raise ValueError("median_interval needs at least one value")
    below = 0.0  # P(Binomial(n, 1/2) <= k - 1), accumulated as k grows
    k, coverage = 1, 1.0 - 2.0 * 0.5**n
    for j in range(1, (n + 1) // 2):  # try k = j + 1
        below += math.comb(n, j - 1) * 0.5**n
        cover = 1.0 - 2.0 * (below + math.comb(n, j) * 0.5**n)
        if cover < level:
            break
        k, coverage = j + 1, cover
    return {"median": statistics.median(x), "lo": x[k - 1], "hi": x[n - k], "coverage": max(coverage, 0.0),
            "runs": n}


#: an entry of :func:`round_robin`: called untimed with the step's index, it returns the
#: zero-argument call to time (set-up that must not be timed, e.g. staging the inputs, is done
#: before returning it)
StagedStep = Callable[[int], Callable[[], object]]


def recurrent_steps(stepper: Stepper, frames: Sequence[dict]) -> StagedStep:
    """A :func:`round_robin` entry stepping ``stepper`` through the recurrent runner over
    ``frames`` (``{buffer: [B, C, H, W]}`` each, cycled; state carried, reset at step 0);
    ``stepper.sync()`` ends each timed call."""
    runner = RecurrentRunner(stepper.step)

    def stage(k: int) -> Callable[[], object]:
        frame = frames[k % len(frames)]

        def call():
            out = runner(frame, reset=k == 0)
            stepper.sync()
            return out

        return call

    return stage


def round_robin(entries: Mapping[str, StagedStep], warmup: int, repeats: int,
                warmup_context: Callable[[str], AbstractContextManager] | None = None,
                clock: Callable[[], float] = time.perf_counter) -> tuple[dict[str, list[float]], dict[str, BaseException]]:
    """Time several methods' steps interleaved, so a slow phase of a loaded machine falls on
    every method alike and paired per-repeat comparisons cancel it.

    First each entry (:data:`StagedStep`, in ``entries`` order) runs its ``warmup`` steps
    (untimed, inside ``warmup_context(name)`` when given, e.g. a :class:`PeakRss`); then
    ``repeats`` rounds, round ``r`` timing one step of every entry in the order rotated by ``r``
    (``names[r % n:] + names[:r % n]``), so every entry takes every position equally often over
    ``n`` rounds. Entry ``name``'s ``k``-th step (warm-up steps counted) is ``entries[name](k)``.

    Returns ``(seconds, errors)``: ``seconds[name]`` the wall time of each round's step
    (``clock`` seconds, ``repeats`` values, index = round), ``errors[name]`` the exception of an
    entry that raised (it leaves the rotation; its ``seconds`` holds the rounds before).
    """
    names = list(entries)
    seconds: dict[str, list[float]] = {n: [] for n in names}
    errors: dict[str, BaseException] = {}
    for name in names:
        try:
            with warmup_context(name) if warmup_context else contextlib.nullcontext():
                for k in range(warmup):
                    entries[name](k)()
        except Exception as exc:  # noqa: BLE001 - reported per entry, the others go on
            errors[name] = exc
    for r in range(repeats if names else 0):
        for name in names[r % len(names):] + names[:r % len(names)]:
            if name in errors:
                continue
            try:
                call = entries[name](warmup + r)
                start = clock()
                call()
                seconds[name].append(clock() - start)
            except Exception as exc:  # noqa: BLE001
                errors[name] = exc
    return seconds, errors


def fastest(clocks: Sequence[Clock]) -> Clock:
    """The run with the least wall time (its CPU time belongs to the same run)."""
    return min(clocks, key=lambda c: c.wall)


# ----------------------------------------------------------------------------- compute


#: the CPU flags the benchmark tables record (what the vector units and bf16 paths can use)
ISA_FLAGS = ("avx2", "avx512f", "avx512_bf16", "avx512_fp16", "amx_tile", "amx_bf16", "amx_fp16")


def cpu_model() -> str:
    """The CPU's model name from ``/proc/cpuinfo``, else :func:`platform.processor` or the machine
    type: what every timing report names its machine by."""
    import platform

    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def cpu_signature(cpuinfo: str | None = None) -> str:
    """``<vendor> family <f> model <m>`` from ``/proc/cpuinfo`` (``unknown`` when unreadable): tells
    apart CPUs that a virtual machine names alike (``Intel(R) Xeon(R) Processor``)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:
            return "unknown"
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        fields.setdefault(key.strip(), value.strip())
    if "vendor_id" not in fields:
        return "unknown"
    return f"{fields['vendor_id']} family {fields.get('cpu family', '?')} model {fields.get('model', '?')}"


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


def has_bf16(isa: dict[str, bool] | None = None) -> bool:
    """Whether the CPU computes bfloat16 natively (AVX512-BF16 or AMX-BF16; :func:`cpu_isa`):
    elsewhere a bf16 product runs on a slow reference path (minutes for a 2048 matmul)."""
    isa = cpu_isa() if isa is None else isa
    return bool(isa.get("avx512_bf16") or isa.get("amx_bf16"))


def matmul_peak(size: int = 2048, repeats: int = 5, dtype: torch.dtype = torch.float32, warmup: int = 2) -> float:
    """GFLOP/s of a ``size`` x ``size`` matrix product ``torch.mm`` on the CPU in ``dtype``
    (fastest of ``repeats`` after ``warmup`` untimed products): the machine's practical peak.
    The defaults (2048, two warm-up products, best of 5) are what every benchmark uses; a
    1024 product, once warmed up only once, read 163-199 GFLOP/s on the same idle 2 cores."""
    a, b = torch.randn(size, size).to(dtype), torch.randn(size, size).to(dtype)
    for _ in range(warmup):
        torch.mm(a, b)
    runs = []
    for _ in range(repeats):
        with Clock() as clock:
            torch.mm(a, b)
        runs.append(clock.wall)
    return 2 * size**3 / summarize(runs)["min"] / 1e9


def count_flops(net: torch.nn.Module, height: int, width: int, batch: int = 1) -> int:
    """FLOPs (convolutions and matrix products) of one recurrent step with history of ``net`` on
    a ``batch x C x height x width`` frame.

    Steps through :class:`~denoiser.runner.RecurrentRunner` (a reset step, then the counted
    one) under ``FakeTensorMode``: shapes only, no arithmetic and no memory for activations,
    so even 1080p counts in about a second; the count depends only on the shapes.
    """
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils.flop_counter import FlopCounterMode

    from denoiser.buffers import CHANNELS, FRAME_INPUTS

    device = next(net.parameters()).device
    runner = RecurrentRunner(net.step)
    with FakeTensorMode(allow_non_fake_inputs=True), torch.inference_mode():
        frame = {k: torch.empty(batch, CHANNELS[k], height, width, device=device) for k in FRAME_INPUTS}
        runner(frame, reset=True)
        with FlopCounterMode(display=False) as counter:
            runner(frame)
    return counter.get_total_flops()


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
                   headers: Mapping[str, str] | None = None, align: bool = False) -> str:
    """A Markdown table of ``rows`` (dicts) with ``columns``: the first column left-aligned, the
    others right-aligned. ``formats``: column -> format spec for floats (:func:`format_value`;
    strings are written as they are); ``headers``: column -> title; ``align``: pad every column
    to its widest cell, so the table also reads well as plain text (console output)."""
    formats = dict(formats or {})
    headers = dict(headers or {})
    lines = [[headers.get(c, c) for c in columns]]
    lines += [[format_value(r.get(c), formats.get(c)) for c in columns] for r in rows]
    widths = [max(3, *(len(line[i]) for line in lines)) if align else 0 for i in range(len(columns))]
    rule = ["-" * max(3, w + 2) if i == 0 else "-" * max(3, w + 1) + ":" for i, w in enumerate(widths)]
    cells = [[c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(line, widths))] for line in lines]
    text = ["| " + " | ".join(cells[0]) + " |", "|" + "|".join(rule) + "|"]
    text += ["| " + " | ".join(line) + " |" for line in cells[1:]]
    return "\n".join(text) + "\n"
