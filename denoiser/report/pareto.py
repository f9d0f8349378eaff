"""Pareto fronts of trained variants: accuracy (PSNR, higher is better) against time (ms per
frame, lower is better), and the timing of one network as both ``denoiser-train``'s optional
time objective and ``denoiser-pareto``'s sequential timing pass use it (docs/pareto.md).

* :func:`front_indices`: the non-dominated points, O(n log n) (tests check it against a plain loop);
* :func:`time_network`: median ms per recurrent step of a network on a backend of
  :mod:`denoiser.inference.backends` (``denoiser-bench``'s measurement: :func:`denoiser.measure.time_steps`);
* :func:`job_dirs`, :func:`read_job`: the jobs of a finished Hydra multirun directory;
* :func:`group_seeds`: jobs that differ only by ``seed=`` (a variant retrained with more seeds);
* :func:`dominates`: whether one ``(psnr, ms)`` point beats another on both axes.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Mapping, Sequence
from pathlib import Path

#: a job's final metrics and objectives, written by denoiser-train into its run directory
METRICS_FILE = "metrics.json"
#: written by denoiser-train when a run finished (not interrupted)
DONE_FILE = "DONE"


def front_indices(points: Sequence[tuple[float, float]]) -> list[int]:
    """Indices of the points ``(psnr, ms)`` that no other point dominates, fastest first.

    ``b`` dominates ``a`` when ``b`` is at least as good and at least as fast, and strictly
    better in one. Points with a NaN are never on the front; equal points are all kept.
    """
    valid = [i for i, (q, t) in enumerate(points) if not (math.isnan(q) or math.isnan(t))]
    order = sorted(valid, key=lambda i: (points[i][1], -points[i][0]))  # fastest first, best first among ties
    front, best_q, best_at = [], -math.inf, None
    for i in order:
        q, t = points[i]
        if q > best_q:
            front.append(i)
            best_q, best_at = q, (q, t)
        elif (q, t) == best_at:  # an exact duplicate of a front point is not dominated either
            front.append(i)
    return front


def dominates(a: tuple[float, float], b: tuple[float, float]) -> bool:
    """Whether ``a = (psnr, ms)`` dominates ``b``: at least as good and as fast, strictly better in
    one; False when either has a NaN."""
    if any(math.isnan(v) for v in (*a, *b)):
        return False
    return a[0] >= b[0] and a[1] <= b[1] and (a[0] > b[0] or a[1] < b[1])


def timing_frames(height: int, width: int, count: int = 2) -> list[dict]:
    """``count`` random frames ``{buffer: [1, C, H, W]}`` (:func:`denoiser.frames.random_frame`,
    seeds 0..count-1): network inputs for timing only (a step's time does not depend on the values)."""
    from denoiser.frames import random_frame

    return [random_frame(1, height, width, seed=i) for i in range(count)]


def time_network(net, backend, size: Sequence[int], threads: int | None = None, warmup: int = 1,
                 repeats: int = 3) -> dict:
    """Median and fastest ms per recurrent step of ``net`` on ``backend`` (an instance from
    :mod:`denoiser.inference.backends`) for frames of ``size`` ``(H, W)``: ``{"ms_median", "ms_min",
    "backend", "threads", "height", "width"}``; ``ms_median`` is NaN with a ``status`` when the
    backend is not available here."""
    import torch

    from denoiser.measure import summarize, time_steps

    if threads:
        torch.set_num_threads(int(threads))
    threads = torch.get_num_threads()
    height, width = (int(v) for v in size)
    row = {"backend": backend.label, "threads": threads, "height": height, "width": width}
    reason = backend.available()
    if reason:
        return {**row, "ms_median": float("nan"), "ms_min": float("nan"), "status": f"skipped: {reason}"}
    frames = timing_frames(height, width)
    stepper = backend.prepare(net.eval(), frames[0], threads)
    stats = summarize(time_steps(stepper, frames, int(warmup), int(repeats)))
    return {**row, "ms_median": 1000 * stats["median"], "ms_min": 1000 * stats["min"], "status": "ok"}


def read_json(path: str | os.PathLike) -> dict:
    path = Path(path)
    return json.loads(path.read_text()) if path.is_file() else {}


def job_dirs(sweep_dir: str | os.PathLike) -> list[Path]:
    """Job directories of a multirun (those with ``.hydra/overrides.yaml``), in job-number order."""
    dirs = [p.parent.parent for p in Path(sweep_dir).glob("*/.hydra/overrides.yaml")]

    def key(p: Path):
        head = p.name.split("_", 1)[0]
        return (0, int(head), p.name) if head.isdigit() else (1, 0, p.name)

    return sorted(dirs, key=key)


def read_job(job_dir: str | os.PathLike) -> dict:
    """One job of a multirun: ``{"dir", "overrides" (list), "metrics" (dict), "done", "ckpt"}``;
    ``ckpt`` is ``checkpoints/last.ckpt`` (the final weights, as validated), else ``best.ckpt``, else None;
    an override naming a moved option names its place now (:func:`denoiser.configs.current_overrides`)."""
    from omegaconf import OmegaConf

    from denoiser.configs import current_overrides

    job_dir = Path(job_dir)
    overrides = current_overrides(OmegaConf.load(job_dir / ".hydra" / "overrides.yaml"))
    ckpts = [job_dir / "checkpoints" / name for name in ("last.ckpt", "best.ckpt")]
    return {"dir": job_dir, "overrides": overrides, "metrics": read_json(job_dir / METRICS_FILE),
            "done": (job_dir / DONE_FILE).is_file(), "ckpt": next((c for c in ckpts if c.is_file()), None)}


def varying_overrides(override_lists: Sequence[Sequence[str]]) -> list[list[str]]:
    """Per job, the overrides whose value differs between jobs (what tells the variants apart)."""
    def split(o: str) -> tuple[str, str]:
        key, _, value = o.partition("=")
        return key, value

    values: dict[str, set] = {}
    for overrides in override_lists:
        for key, value in map(split, overrides):
            values.setdefault(key, set()).add(value)
    counts = {k: sum(any(split(o)[0] == k for o in ol) for ol in override_lists) for k in values}
    varying = {k for k, v in values.items() if len(v) > 1 or counts[k] < len(override_lists)}
    return [[o for o in ol if split(o)[0] in varying] for ol in override_lists]


def seed_of(overrides: Sequence[str]) -> int | None:
    """The ``seed=`` of a job's overrides (None when it keeps the config's)."""
    for o in overrides:
        key, _, value = o.partition("=")
        if key.lstrip("+") == "seed":
            return int(value)
    return None


def group_seeds(jobs: Sequence[Mapping]) -> list[list[Mapping]]:
    """Jobs (:func:`read_job` dicts) grouped by their overrides without ``seed=``: one group per
    variant, in order of first appearance, its jobs in seed order (a job without ``seed=`` is the
    config's seed and comes first)."""
    groups: dict[tuple[str, ...], list[Mapping]] = {}
    for job in jobs:
        key = tuple(sorted(o for o in job["overrides"] if o.partition("=")[0].lstrip("+") != "seed"))
        groups.setdefault(key, []).append(job)
    return [sorted(g, key=lambda j: (seed_of(j["overrides"]) is not None, seed_of(j["overrides"]) or 0))
            for g in groups.values()]


def cache_key(path: str | os.PathLike, **what) -> str:
    """A key naming a checkpoint file's version (path, size, mtime) and what was measured of it."""
    import hashlib

    st = Path(path).stat()
    text = json.dumps({"path": str(Path(path).resolve()), "size": st.st_size, "mtime": st.st_mtime_ns, **what},
                      sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:20]


def front_seed_jobs(csv_path: str | os.PathLike, seeds: Sequence[int]) -> list[dict]:
    """The jobs that retrain the front's variants with more ``seeds`` (``denoiser-pipeline
    pipeline=pareto``, ``jobs_from``): one per network on the front of ``pareto.csv`` that was
    trained with one seed, its overrides and ``seed=<a>,<b>`` for a multirun whose job folders are
    ``<job>_s<seed>``. None when ``seeds`` is empty or the table does not exist yet."""
    import csv

    if not seeds or not Path(csv_path).is_file():
        return []
    with open(csv_path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return [{"name": f"front_seeds_{r['job']}",
             "args": [*r["overrides"].split(), "seed=" + ",".join(str(s) for s in seeds),
                      f"hydra.sweep.subdir={r['job']}_s${{seed}}"]}
            for r in rows if r["front"] == "True" and r["kind"] == "network" and r["seeds"] in ("cfg", "0")]


def finished_runs(sweep_dirs: Sequence[str | os.PathLike]) -> list[dict]:
    """Every finished job of the multiruns ``sweep_dirs`` (``DONE`` and ``checkpoints/last.ckpt``),
    as ``{name: job<folder>, run_dir, ckpt}`` for an evaluation of them all (``jobs_from``)."""
    runs = []
    for sweep in sweep_dirs:
        for job in job_dirs(sweep) if Path(sweep).is_dir() else []:
            last = job / "checkpoints" / "last.ckpt"
            if (job / DONE_FILE).is_file() and last.is_file():
                runs.append({"name": f"job{job.name}", "run_dir": str(job), "ckpt": str(last)})
    return runs
