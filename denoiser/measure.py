"""Measurement: peak memory, clocks and FLOPs, what every benchmark measures with.

* FLOPs: :func:`count_flops` (one recurrent step with history, shapes only);
* peak memory: :class:`PeakRss` (of a block in this process: sampled, or the kernel's
  high-water mark; see there which applies when) and :func:`run_process` (of a whole child
  process);
* timings: :class:`Clock` (wall and CPU seconds of a block), :func:`clock_steps` /
  :func:`time_steps` (recurrent steps through the runner), :func:`round_robin` (several
  methods' steps interleaved: each repeat times every method once, in a rotated order),
  :func:`summarize` (median, min, max), :func:`median_interval` (the median of repeated ratios
  with a distribution-free confidence interval) and :func:`fastest`.

The machine a measurement ran on (CPU model, ISA, matmul peak) is :mod:`denoiser.machine`; the
tables results are written as (Markdown, CSV) are :mod:`denoiser.tables`.
"""

from __future__ import annotations

import contextlib
import math
import os
import statistics
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass

import torch

from denoiser.recurrent import RecurrentRunner, Stepper

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
    every read and write), e.g. ``memory_longseq``'s runs of ``denoiser-denoise``."""
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


# ----------------------------------------------------------------------------- FLOPs


def count_flops(net: torch.nn.Module, height: int, width: int, batch: int = 1) -> int:
    """FLOPs (convolutions and matrix products) of one recurrent step with history of ``net`` on
    a ``batch x C x height x width`` frame.

    Steps through :class:`~denoiser.recurrent.RecurrentRunner` (a reset step, then the counted
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
