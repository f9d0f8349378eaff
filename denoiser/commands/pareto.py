"""The accuracy-vs-time Pareto front of a finished training multirun: ``denoiser-pareto``.

    denoiser-pareto sweep_dir=reports/pareto/runs
    denoiser-pareto sweep_dir=multirun/train/<date> backend=eager 'sizes=[[256,256]]'

A Hydra app over ``conf/pareto.yaml``. It reads every job directory of ``sweep_dir`` (the
multirun of ``denoiser-train -m experiment=pareto``, grid or Optuna): its overrides
(``.hydra/overrides.yaml``), its final validation metrics (``metrics.json``, written by
denoiser-train) and its checkpoint (``checkpoints/last.ckpt``, the weights those metrics
describe). Then, one network after another in this process (never two timings side by side),
it counts parameters and GFLOP and times each network on one CPU backend (``backend``: a name of the
config group ``conf/backends/``; ``openvino_f32`` by default) at each of ``sizes``, as ``denoiser-bench`` does (:func:`denoiser.report.pareto.time_network`).
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

import datetime
import json
import math
import shlex
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from denoiser.atomic import atomic_write_text
from denoiser.errors import ConfigError, UserError
from denoiser.measure import count_flops
from denoiser.report.evaluation import eval_means
from denoiser.report.pareto import (
    cache_key,
    dominates,
    front_indices,
    group_seeds,
    job_dirs,
    read_job,
    seed_of,
    time_network,
    varying_overrides,
)
from denoiser.report.plot_tradeoff import plot_accuracy_vs_time
from denoiser.report.provenance import git_commit
from denoiser.tables import markdown_table, read_csv, write_csv

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


def mean_std(values: list[float]) -> tuple[float, float]:
    """Mean and sample standard deviation of the finite values (NaN when there are none; std NaN for one)."""
    vals = [v for v in values if not math.isnan(v)]
    if not vals:
        return NAN, NAN
    mean = sum(vals) / len(vals)
    if len(vals) < 2:
        return mean, NAN
    return mean, math.sqrt(sum((v - mean) ** 2 for v in vals) / (len(vals) - 1))


def read_jobs(sweep_dirs: list[Path]) -> list[dict]:
    """Every job of the sweep directories, named by its directory (names must not repeat)."""
    jobs, seen = [], {}
    for sweep_dir in sweep_dirs:
        dirs = job_dirs(sweep_dir)
        if not dirs:
            raise UserError(f"sweep_dir={sweep_dir}: no job directories (<job>/.hydra/overrides.yaml) there")
        for d in dirs:
            if d.name in seen:
                raise UserError(f"sweep_dir: job {d.name} is in both {seen[d.name]} and {sweep_dir} "
                                f"(name the jobs of each sweep apart, e.g. hydra.sweep.subdir)")
            seen[d.name] = sweep_dir
            jobs.append(read_job(d))
    return jobs


def baseline_rows(cfg: DictConfig, sizes: list[tuple[int, int]], threads: int, cache_dir: Path | None = None
                  ) -> list[dict]:
    """The baselines of ``cfg.baselines`` (OIDN) timed in this process on the networks' frames and
    threads, with their validation PSNR from ``baseline_eval_csv`` (denoiser-eval on the val split).

    With ``cache_dir`` the times are cached like the networks' (per baseline config, sizes, threads,
    warm-up and repeats), so a later report over more seeds keeps every time of one timing pass
    instead of re-timing the baselines under other conditions."""
    if not cfg.get("baselines"):
        return []
    import hashlib

    import torch

    from denoiser.measure import summarize, time_steps
    from denoiser.methods.baselines import build_baselines
    from denoiser.recurrent import Stepper
    from denoiser.report.pareto import timing_frames

    torch.set_num_threads(threads)

    evaluated = eval_means(cfg.get("baseline_eval_csv"))
    rows = []
    nodes = OmegaConf.to_container(cfg.baselines, resolve=True)
    for label, method in build_baselines(cfg.baselines).items():
        row = {"job": "", "variant": label, "kind": "baseline", "seeds": "", "backend": getattr(method, "backend",
                                                                                               "OIDN (pyoidn)"),
               "threads": threads, "val_psnr": float(evaluated.get(label, {}).get("psnr", NAN)),
               "val_tpsnr": float(evaluated.get(label, {}).get("tpsnr", NAN))}
        what = {"baseline": label, "config": nodes, "sizes": sizes, "threads": threads, "warmup": int(cfg.warmup),
                "repeats": int(cfg.repeats)}
        key = hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:20]
        cached = cache_dir / f"baseline_{key}.json" if cache_dir is not None else None
        if cached is not None and cached.is_file():
            row.update(json.loads(cached.read_text()))
        else:
            times = {}
            for size in sizes:
                print(f"[baseline] {label} at {size_tag(size)}", flush=True)
                frames = timing_frames(*size)
                stepper = Stepper(lambda f, s, m=method: (m(f, s is None), None))
                times[f"ms_{size_tag(size)}"] = 1000 * summarize(time_steps(stepper, frames, int(cfg.warmup),
                                                                            int(cfg.repeats)))["median"]
            row.update(times)
            if cached is not None:
                cache_dir.mkdir(parents=True, exist_ok=True)
                atomic_write_text(cached, json.dumps(times, indent=1))
        close = getattr(method, "close", None)
        if close:
            close()
        rows.append(row)
    return rows


def select_backend(cfg: DictConfig):
    """The backend named by ``backend`` (an option of ``conf/backends/``, or ``openvino``/``eager`` for their f32
    option: :func:`denoiser.inference.backends.resolve_backend`), instantiated; one-line ConfigError when it
    is unknown or cannot run here."""
    from denoiser.inference.backends import load_backend, resolve_backend

    name, overrides = resolve_backend(str(cfg.backend))
    backend = load_backend(name, "backend", **overrides)
    reason = backend.available()
    if reason:
        raise ConfigError(f"backend={cfg.backend}: {reason}")
    return backend


def run(cfg: DictConfig) -> list[dict]:
    """The ``denoiser-pareto`` task; returns the table rows (variants, then baselines)."""
    import torch

    sweep_dirs = [Path(d) for d in (cfg.sweep_dir if isinstance(cfg.sweep_dir, (list, ListConfig))
                                    else [cfg.sweep_dir])]
    out_dir = Path(cfg.out_dir)
    sizes = [tuple(int(v) for v in s) for s in cfg.sizes]
    if not sizes:
        raise ConfigError("sizes: at least one [H, W]")
    backend = select_backend(cfg)
    groups = group_seeds(read_jobs(sweep_dirs))
    labels = varying_overrides([[o for o in g[0]["overrides"] if o.partition("=")[0].lstrip("+") != "seed"]
                                for g in groups])
    tested = eval_means(cfg.get("eval_csv"))
    rows = []
    for i, (group, varying) in enumerate(zip(groups, labels)):
        first = group[0]
        tests = [tested.get(j["dir"].name, tested.get(f"job{j['dir'].name}", {})) for j in group]
        val = mean_std([float(j["metrics"].get("metrics", {}).get("val/psnr", NAN)) for j in group])
        val_t = mean_std([float(j["metrics"].get("metrics", {}).get("val/tpsnr", NAN)) for j in group])
        test = mean_std([float(t.get("psnr", NAN)) for t in tests])
        test_t = mean_std([float(t.get("tpsnr", NAN)) for t in tests])
        seeds = [seed_of(j["overrides"]) for j in group]
        row = {"job": first["dir"].name, "variant": " ".join(varying) or first["dir"].name, "kind": "network",
               "seeds": " ".join("cfg" if s is None else str(s) for s in seeds), "n_seeds": len(group),
               "val_psnr": val[0], "val_psnr_std": val[1], "val_tpsnr": val_t[0],
               "test_psnr": test[0], "test_psnr_std": test[1], "test_tpsnr": test_t[0],
               "done": all(j["done"] for j in group), "overrides": first["overrides"]}
        timed = next((j for j in group if j["ckpt"] is not None), None)  # one architecture: time one of its runs
        if timed is None:
            rows.append({**row, "status": "no checkpoint"})
            continue
        print(f"[{i + 1}/{len(groups)}] {timed['dir']}: {row['variant']} ({len(group)} seed(s))", flush=True)
        rows.append({**row, **measure_job(timed["ckpt"], cfg, backend, sizes, out_dir / "cache")})
    threads = int(cfg.threads) if cfg.get("threads") else torch.get_num_threads()
    rows += baseline_rows(cfg, sizes, threads, out_dir / "cache")
    rows += oidn_rows(cfg.get("oidn_csv"), sizes)
    ms_key = f"ms_{size_tag(sizes[0])}"
    nets = [i for i, r in enumerate(rows) if r["kind"] == "network"]
    front = {nets[k] for k in front_indices([(float(rows[i].get("val_psnr", NAN)), float(rows[i].get(ms_key, NAN)))
                                             for i in nets])}
    for i, r in enumerate(rows):
        r["front"] = i in front
    write_report(out_dir, rows, sizes, sweep_dirs)
    return rows


def dominance_lines(rows: list[dict], ms_key: str) -> list[str]:
    """Per baseline with a validation PSNR: the front's variants that dominate it (faster and better)."""
    lines = []
    for b in rows:
        if b["kind"] != "baseline" or math.isnan(float(b.get("val_psnr", NAN))):
            continue
        point = (float(b["val_psnr"]), float(b.get(ms_key, NAN)))
        winners = [r for r in rows if r["front"]
                   and dominates((float(r["val_psnr"]), float(r.get(ms_key, NAN))), point)]
        if winners:
            lines.append(f"- {b['variant']} (val PSNR {point[0]:.2f} dB, {point[1]:.0f} ms) is dominated by "
                         + ", ".join(f"#{r['job']} ({r['val_psnr']:.2f} dB over {r['n_seeds']} seed(s), "
                                     f"{float(r[ms_key]):.0f} ms)" for r in winners) + ".")
        else:
            faster = [r for r in rows if r["front"] and float(r.get(ms_key, NAN)) < point[1]]
            best = max(faster, key=lambda r: float(r["val_psnr"]), default=None)
            gap = (f"; the best front variant faster than it, #{best['job']}, is {best['val_psnr'] - point[0]:+.2f} dB"
                   if best else "; no front variant is faster")
            lines.append(f"- {b['variant']} (val PSNR {point[0]:.2f} dB, {point[1]:.0f} ms): no front variant "
                         f"dominates it{gap}.")
    return lines


def write_report(out_dir: Path, rows: list[dict], sizes, sweep_dirs: list[Path]) -> None:
    ms_cols = [f"ms_{size_tag(s)}" for s in sizes]
    columns = ["job", "variant", "front", "seeds", "params", "gflop", "val_psnr", "val_psnr_std", "val_tpsnr",
               "test_psnr", "test_psnr_std", "test_tpsnr", *ms_cols,
               "backend", "threads", "kind", "done", "overrides"]
    out_dir.mkdir(parents=True, exist_ok=True)
    write_csv(out_dir / "pareto.csv", [{**r, "overrides": " ".join(r.get("overrides", []))} for r in rows], columns)
    ms_key = ms_cols[0]
    ordered = sorted(rows, key=lambda r: (math.isnan(float(r.get(ms_key, NAN))), float(r.get(ms_key, NAN))))

    def pm(mean, std) -> str:
        if math.isnan(float(mean)):
            return ""
        return f"{mean:.2f}" + ("" if math.isnan(float(std)) else f" ± {std:.2f}")

    shown = [{**r, "front": "★" if r["front"] else "",
              "val_psnr": pm(r.get("val_psnr", NAN), r.get("val_psnr_std", NAN)),
              "test_psnr": pm(r.get("test_psnr", NAN), r.get("test_psnr_std", NAN))} for r in ordered]
    table = markdown_table(shown, [c for c in columns if c not in ("overrides", "kind", "done", "val_psnr_std",
                                                                   "test_psnr_std")],
                           formats={"gflop": ".3g", "val_tpsnr": ".2f", "test_tpsnr": ".2f",
                                    **{c: ".1f" for c in ms_cols}},
                           headers={"gflop": f"GFLOP {size_tag(sizes[0])}", **{c: f"ms {c[3:]}" for c in ms_cols},
                                    "val_psnr": "val PSNR dB", "test_psnr": "test PSNR dB", "val_tpsnr": "val tPSNR dB",
                                    "test_tpsnr": "test tPSNR dB"})
    front_rows = [r for r in ordered if r["front"]]
    lines = [" ".join(shlex.quote(o) for o in r["overrides"]) for r in front_rows]
    atomic_write_text(out_dir / "front.txt", "".join(f"{line}\n" for line in lines))
    plot_rows = [{"method": f"#{r['job']}" if r["kind"] == "network" else r["variant"], "backend": r.get("backend", ""),
                  "device": "cpu", "height": sizes[0][0], "width": sizes[0][1], "ms_median": float(r.get(ms_key, NAN)),
                  "psnr": float(r.get("val_psnr", NAN)), "psnr_std": float(r.get("val_psnr_std", NAN)),
                  "kind": r["kind"]} for r in rows]
    where = ", ".join(str(d) for d in sweep_dirs)
    plot = plot_accuracy_vs_time(out_dir / "accuracy_vs_time.png", plot_rows, sizes[0], front_kinds=["network"],
                                 title=f"Pareto front of {where} (val PSNR vs ms at {size_tag(sizes[0])})")
    n_nets = sum(r["kind"] == "network" for r in rows)
    one_seed = [r for r in front_rows if r["n_seeds"] < 3]
    text = [f"# Pareto front of {where}", "",
            f"- run id: {datetime.datetime.now(datetime.timezone.utc).strftime('%Y-%m-%dT%H:%M:%SZ')}",
            f"- commit: {git_commit()}", "", "<!-- pareto:begin -->",
            (f"{n_nets} variants; val PSNR of the final weights (denoiser-train's metrics.json), the mean ± std "
             f"over the seeds listed where a variant was trained with more than one; ms per frame: median of the "
             f"timed steps on the backend named, one network at a time, the baselines on the same frames and "
             f"threads. ★: on the front of the variants (no other variant both faster at {size_tag(sizes[0])} and "
             f"better)."), "", table, "",
            "## The front against the baselines (val PSNR, same frames and threads)", "",
            *(dominance_lines(rows, ms_key) or ["- no baseline with a validation PSNR (baselines, baseline_eval_csv)"]),
            *(["- front variants with fewer than 3 seeds (no claim rests on them yet): "
               + ", ".join(f"#{r['job']}" for r in one_seed)] if one_seed else []), "<!-- pareto:end -->", "",
            "## The front as train overrides", "",
            "```", *(f"denoiser-train {line}" for line in lines), "```", ""]
    if plot:
        text += ["![accuracy vs time](accuracy_vs_time.png)", ""]
    atomic_write_text(out_dir / "pareto.md", "\n".join(text))
    print(table)
    print("\n".join(dominance_lines(rows, ms_key)))
    print(f"wrote {out_dir}/pareto.md, pareto.csv, front.txt" + (", accuracy_vs_time.png" if plot else ""))


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "pareto")()


if __name__ == "__main__":
    main()
