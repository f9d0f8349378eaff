"""The accuracy-vs-time Pareto front of a finished training multirun: ``denoiser-pareto``.

    denoiser-pareto sweep_dir=reports/pareto/runs
    denoiser-pareto sweep_dir=multirun/train/<date> backend=eager 'sizes=[[256,256]]'

A Hydra app over ``conf/pareto.yaml``. It reads every job directory of ``sweep_dir`` (the
multirun of ``denoiser-train -m experiment=pareto``, grid or Optuna): its overrides
(``.hydra/overrides.yaml``), its final validation metrics (``metrics.json``, written by
denoiser-train) and its checkpoint (``checkpoints/last.ckpt``, the weights those metrics
describe). Then, one network after another in this process (never two timings side by side),
it counts parameters and GFLOP and times each network on one CPU backend (``backend``; OpenVINO
by default) at each of ``sizes``, as ``denoiser-bench`` does (:func:`denoiser.pareto.time_network`).
Timings are cached in ``out_dir/cache/`` per checkpoint file version and settings, so a rerun
only times new or changed checkpoints.

Writes to ``out_dir``: ``pareto.md`` and ``pareto.csv`` (every variant: overrides, params, GFLOP,
val PSNR/tPSNR, test PSNR/tPSNR from ``eval_csv`` (denoiser-eval of the jobs' checkpoints, each
named by its job directory, ``<name>`` or ``job<name>``), ms per size, backend, threads,
on the front or not; OIDN rows from ``oidn_csv``), ``accuracy_vs_time.png`` (val PSNR against
ms at the first size, the front as a staircase) and ``front.txt`` (the front's overrides, one
line per point, the whole command line of the job: paste it after ``denoiser-train``).
"""

from __future__ import annotations

import json
import math
import shlex
from pathlib import Path

from omegaconf import DictConfig

from denoiser.atomic import atomic_write_text
from denoiser.configs import instantiate_config
from denoiser.errors import ConfigError, UserError
from denoiser.evaluation import eval_means
from denoiser.measure import count_flops, markdown_table, read_csv, write_csv
from denoiser.pareto import (
    cache_key,
    front_indices,
    job_dirs,
    read_job,
    time_network,
    varying_overrides,
)
from denoiser.plot_tradeoff import plot_accuracy_vs_time

NAN = float("nan")


def size_tag(size) -> str:
    return f"{size[1]}x{size[0]}"


def measure_job(ckpt: Path, cfg: DictConfig, backend, sizes: list[tuple[int, int]], cache_dir: Path) -> dict:
    """Params, GFLOP and ms per size of one checkpoint's network (cached per file version and settings)."""
    import torch

    from denoiser.checkpoint import load_denoiser

    threads = int(cfg.threads) if cfg.get("threads") else torch.get_num_threads()
    key = cache_key(ckpt, backend=backend.label, sizes=sizes, threads=threads, warmup=int(cfg.warmup),
                    repeats=int(cfg.repeats))
    cached = cache_dir / f"{key}.json"
    if cached.is_file():
        return json.loads(cached.read_text())
    net = load_denoiser(ckpt, trust=bool(cfg.trust_checkpoint))
    out = {"params": net.num_parameters(), "gflop": count_flops(net, *sizes[0]) / 1e9, "backend": backend.label,
           "threads": threads}
    for size in sizes:
        row = time_network(net, backend, size, threads=threads, warmup=int(cfg.warmup), repeats=int(cfg.repeats))
        out[f"ms_{size_tag(size)}"] = row["ms_median"]
        if row["status"] != "ok":
            out["status"] = row["status"]
    cache_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(cached, json.dumps(out, indent=1))
    return out




def oidn_rows(path, sizes: list[tuple[int, int]]) -> list[dict]:
    """OIDN rows of denoiser-bench's bench.csv (ms at each of ``sizes`` where it has them). Its PSNR is
    denoiser-eval's, on the test split: it goes to ``test_psnr``, and OIDN stays off the front and
    the plot, whose PSNR is the networks' validation PSNR."""
    if not path:
        return []
    by_method: dict[str, dict] = {}
    for r in read_csv(path):
        if not str(r.get("method", "")).startswith("OIDN"):
            continue
        size = (int(r["height"]), int(r["width"]))
        if size not in sizes:
            continue
        row = by_method.setdefault(r["method"], {"job": "", "variant": r["method"], "kind": "baseline",
                                                 "val_psnr": NAN, "test_psnr": float(r.get("psnr", NAN)),
                                                 "backend": r.get("backend", ""),
                                                 "threads": r.get("threads", "")})
        row[f"ms_{size_tag(size)}"] = float(r["ms_median"])
    return list(by_method.values())


def run(cfg: DictConfig) -> list[dict]:
    """The ``denoiser-pareto`` task; returns the table rows (networks, then OIDN)."""
    sweep_dir, out_dir = Path(cfg.sweep_dir), Path(cfg.out_dir)
    jobs = [read_job(d) for d in job_dirs(sweep_dir)]
    if not jobs:
        raise UserError(f"sweep_dir={sweep_dir}: no job directories (<job>/.hydra/overrides.yaml) there")
    sizes = [tuple(int(v) for v in s) for s in cfg.sizes]
    if not sizes:
        raise ConfigError("sizes: at least one [H, W]")
    if cfg.backend not in cfg.backends:
        raise ConfigError(f"backend: {cfg.backend!r} is not in backends ({', '.join(cfg.backends)})")
    backend = instantiate_config(cfg.backends[cfg.backend], f"backends.{cfg.backend}")
    reason = backend.available()
    if reason:
        raise ConfigError(f"backend={cfg.backend}: {reason}")
    labels = varying_overrides([j["overrides"] for j in jobs])
    tested = eval_means(cfg.get("eval_csv"))
    rows = []
    for i, (job, varying) in enumerate(zip(jobs, labels)):
        metrics = job["metrics"].get("metrics", {})
        test = tested.get(job["dir"].name, tested.get(f"job{job['dir'].name}", {}))
        row = {"job": job["dir"].name, "variant": " ".join(varying) or job["dir"].name, "kind": "network",
               "val_psnr": float(metrics.get("val/psnr", NAN)), "val_tpsnr": float(metrics.get("val/tpsnr", NAN)),
               "test_psnr": float(test.get("psnr", NAN)), "test_tpsnr": float(test.get("tpsnr", NAN)),
               "done": job["done"], "overrides": job["overrides"]}
        if job["ckpt"] is None:
            rows.append({**row, "status": "no checkpoint"})
            continue
        print(f"[{i + 1}/{len(jobs)}] {job['dir']}: {row['variant']}", flush=True)
        rows.append({**row, **measure_job(job["ckpt"], cfg, backend, sizes, out_dir / "cache")})
    rows += oidn_rows(cfg.get("oidn_csv"), sizes)
    ms_key = f"ms_{size_tag(sizes[0])}"
    points = [(float(r.get("val_psnr", NAN)), float(r.get(ms_key, NAN))) for r in rows]
    front = set(front_indices(points))
    for i, r in enumerate(rows):
        r["front"] = i in front
    write_report(out_dir, rows, sizes, sweep_dir)
    return rows


def write_report(out_dir: Path, rows: list[dict], sizes, sweep_dir: Path) -> None:
    ms_cols = [f"ms_{size_tag(s)}" for s in sizes]
    columns = ["job", "variant", "front", "params", "gflop", "val_psnr", "val_tpsnr", "test_psnr", "test_tpsnr",
               *ms_cols,
               "backend", "threads", "kind", "done", "overrides"]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(out_dir / "pareto.csv", [{**r, "overrides": " ".join(r.get("overrides", []))} for r in rows], columns)
    ms_key = ms_cols[0]
    ordered = sorted(rows, key=lambda r: (math.isnan(float(r.get(ms_key, NAN))), float(r.get(ms_key, NAN))))
    table = markdown_table([{**r, "front": "★" if r["front"] else ""} for r in ordered],
                           [c for c in columns if c not in ("overrides", "kind", "done")],
                           formats={"gflop": ".3g", "val_psnr": ".2f", "val_tpsnr": ".2f", "test_psnr": ".2f",
                                    "test_tpsnr": ".2f",
                                    **{c: ".3g" for c in ms_cols}},
                           headers={"gflop": f"GFLOP {size_tag(sizes[0])}", **{c: f"ms {c[3:]}" for c in ms_cols}})
    front_rows = [r for r in ordered if r["front"] and r["kind"] == "network"]
    lines = [" ".join(shlex.quote(o) for o in r["overrides"]) for r in front_rows]
    atomic_write_text(out_dir / "front.txt", "".join(f"{line}\n" for line in lines))
    plot_rows = [{"method": f"#{r['job']}" if r["kind"] == "network" else r["variant"], "backend": r.get("backend", ""),
                  "device": "cpu", "height": sizes[0][0], "width": sizes[0][1], "ms_median": float(r.get(ms_key, NAN)),
                  "psnr": float(r.get("val_psnr", NAN)), "kind": r["kind"]} for r in rows]
    plot = plot_accuracy_vs_time(out_dir / "accuracy_vs_time.png", plot_rows, sizes[0],
                                 title=f"Pareto front of {sweep_dir} (val PSNR vs ms at {size_tag(sizes[0])})")
    text = [f"# Pareto front of {sweep_dir}", "",
            (f"{sum(r['kind'] == 'network' for r in rows)} variants; val PSNR of the final weights (denoiser-train's "
             f"metrics.json), ms per frame: median of the timed steps on the backend named, one network at a time. "
             f"★: on the front (no other row both faster at {size_tag(sizes[0])} and better)."), "", table, "",
            "## The front as train overrides", "",
            "```", *(f"denoiser-train {line}" for line in lines), "```", ""]
    if plot:
        text += ["![accuracy vs time](accuracy_vs_time.png)", ""]
    atomic_write_text(out_dir / "pareto.md", "\n".join(text))
    print(table)
    print(f"wrote {out_dir}/pareto.md, pareto.csv, front.txt" + (", accuracy_vs_time.png" if plot else ""))


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "pareto")()


if __name__ == "__main__":
    main()
