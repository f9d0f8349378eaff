"""The Pareto sweep (docs/pareto.md): the front function against a plain loop, denoiser-pareto on
a real (tiny) multirun trained through denoiser-train -m, and the Optuna multi-objective sweeper
(hydra/sweeper=optuna_pareto) running and resuming after being killed during a trial."""

from __future__ import annotations

import contextlib
import csv
import json
import math
import os
import random
import statistics
import subprocess
import sys
import time
from pathlib import Path

import pytest

from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.report.pareto import dominates, front_indices, group_seeds, read_job, seed_of, varying_overrides

REPO = Path(__file__).resolve().parents[2]
#: tiny, quiet training jobs: 2 steps of net=tiny on 16x16 crops, one validation at the end
TINY = ["data=tiny", "net=tiny", "threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null",
        "trainer.enable_model_summary=false", "trainer.max_steps=2", "trainer.val_check_interval=2",
        "trainer.limit_val_batches=1", "model.image_interval=0", "hydra/job_logging=disabled",
        "hydra/hydra_logging=disabled"]
#: the time objective at a test size on eager PyTorch
TIME = "objectives.time={size:[32,32],backend:eager,warmup:1,repeats:2}"


def plain_front(points):
    """The definition, one pair at a time."""
    out = []
    for i, (qa, ta) in enumerate(points):
        if math.isnan(qa) or math.isnan(ta):
            continue
        if not any(qb >= qa and tb <= ta and (qb > qa or tb < ta)
                   for j, (qb, tb) in enumerate(points) if j != i and not (math.isnan(qb) or math.isnan(tb))):
            out.append(i)
    return out


def test_front_matches_a_plain_loop():
    rng = random.Random(0)
    for trial in range(300):
        n = rng.randint(0, 12)
        # few distinct values: ties in time, in PSNR and exact duplicates happen often
        points = [(float(rng.randint(0, 5)), float(rng.randint(1, 6))) for _ in range(n)]
        if n and trial % 5 == 0:
            points[0] = (math.nan, 1.0)
        got = front_indices(points)
        assert sorted(got) == plain_front(points), points
        assert [points[i][1] for i in got] == sorted(points[i][1] for i in got)  # fastest first


def test_front_of_known_points():
    # (psnr, ms): a slow good one, a fast bad one, one dominated by both ends' neighbour
    points = [(30.0, 10.0), (25.0, 1.0), (24.0, 2.0), (30.0, 12.0), (28.0, 5.0)]
    assert front_indices(points) == [1, 4, 0]


def test_varying_overrides_keeps_what_differs():
    jobs = [["net=tiny", "kernel.sizes=[3]", "ablation=none"], ["net=tiny", "kernel.sizes=[5,5]", "ablation=none"],
            ["net=tiny", "kernel.sizes=[5,5]", "ablation=none", "seed=1"]]
    assert varying_overrides(jobs) == [["kernel.sizes=[3]"], ["kernel.sizes=[5,5]"], ["kernel.sizes=[5,5]", "seed=1"]]


def test_seeds_of_one_variant_are_one_group():
    def job(name, *overrides):
        return {"dir": Path(name), "overrides": list(overrides)}

    jobs = [job("0", "net=tiny", "kernel.sizes=[3]"), job("1", "net=tiny", "kernel.sizes=[5]"),
            job("0_s2", "net=tiny", "seed=2", "kernel.sizes=[3]"), job("0_s1", "net=tiny", "kernel.sizes=[3]", "seed=1"),
            job("1_s1", "net=tiny", "kernel.sizes=[5]", "+seed=1")]
    groups = group_seeds(jobs)
    assert [[j["dir"].name for j in g] for g in groups] == [["0", "0_s1", "0_s2"], ["1", "1_s1"]]
    assert [seed_of(j["overrides"]) for j in groups[0]] == [None, 1, 2]


def test_dominates_is_the_definition():
    nan = math.nan
    assert dominates((30.0, 10.0), (29.0, 12.0)) and dominates((30.0, 10.0), (30.0, 11.0))
    assert dominates((30.5, 10.0), (30.0, 10.0))
    assert not dominates((30.0, 10.0), (30.0, 10.0))        # equal: neither dominates
    assert not dominates((31.0, 12.0), (30.0, 10.0))        # better but slower
    assert not dominates((nan, 1.0), (30.0, 10.0)) and not dominates((31.0, 1.0), (30.0, nan))


def test_mean_std_of_seed_values():
    from denoiser.commands.pareto import mean_std

    mean, std = mean_std([30.0, 31.0, 32.0, math.nan])
    assert mean == pytest.approx(31.0) and std == pytest.approx(1.0)  # sample std, NaN left out
    assert math.isnan(mean_std([29.0])[1]) and all(math.isnan(v) for v in mean_std([]))


def test_dominance_lines_name_the_winners_or_the_gap():
    from denoiser.commands.pareto import dominance_lines

    rows = [{"kind": "network", "job": "0", "front": True, "val_psnr": 29.0, "n_seeds": 3, "ms": 50.0},
            {"kind": "network", "job": "1", "front": True, "val_psnr": 31.0, "n_seeds": 3, "ms": 200.0},
            {"kind": "network", "job": "2", "front": False, "val_psnr": 32.0, "n_seeds": 1, "ms": 90.0},
            {"kind": "baseline", "variant": "OIDN-fast", "front": False, "val_psnr": 30.0, "ms": 100.0},
            {"kind": "baseline", "variant": "OIDN-slow", "front": False, "val_psnr": 30.0, "ms": 300.0}]
    fast, slow = dominance_lines(rows, "ms")
    assert fast.startswith("- OIDN-fast (val PSNR 30.00 dB, 100 ms): no front variant dominates it")
    assert "#0, is -1.00 dB" in fast  # #2 would dominate it, but it is not on the front
    assert slow.startswith("- OIDN-slow (val PSNR 30.00 dB, 300 ms) is dominated by #1 (31.00 dB over 3 seed(s)")


@pytest.fixture(scope="module")
def data_root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("paretodata")
    for split, count in (("train", 2), ("val", 1)):
        for i in range(count):
            write_synthetic_sequence(root / split / f"seq{i}", frames=4, width=32, height=32, labeled=True,
                                     seed=10 * i + len(split))
    return root


def command(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", f"denoiser.commands.{module}", *args]


def env() -> dict:
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]),
            "HYDRA_FULL_ERROR": "1"}


def run_ok(argv, cwd) -> subprocess.CompletedProcess:
    proc = subprocess.run(argv, check=False, cwd=cwd, env=env(), capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


@pytest.mark.slow
def test_report_of_a_trained_multirun(data_root, tmp_path):
    """Three variants trained by denoiser-train -m (the basic grid sweeper and launcher), then denoiser-pareto."""
    sweep = tmp_path / "sweep"
    run_ok(command("train", "-m", *TINY, f"data.root={data_root}", "kernel.sizes=[3],[5,5],[3,5,5]",
                   f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=${hydra.job.num}", "skip_done=true"), tmp_path)
    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2"]
    assert all((sweep / j / "DONE").is_file() and (sweep / j / "metrics.json").is_file() for j in "012")

    out = tmp_path / "report"
    eval_csv = tmp_path / "metrics.csv"  # the shape of denoiser-eval's table, test PSNR of job 1 only
    eval_csv.write_text("method,scene,sequence,psnr,tpsnr\njob1,a,seq0,30.0,29.0\njob1,mean,mean,31.5,30.5\n")
    report = command("pareto", f"sweep_dir={sweep}", f"out_dir={out}", "backend=eager", "sizes=[[32,32],[16,16]]",
                     "warmup=0", "repeats=1", "threads=1", f"eval_csv={eval_csv}")
    run_ok(report, tmp_path)
    with open(out / "pareto.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["variant"] for r in rows] == ["kernel.sizes=[3]", "kernel.sizes=[5,5]", "kernel.sizes=[3,5,5]"]
    for r in rows:
        assert float(r["val_psnr"]) > 0 and float(r["ms_32x32"]) > 0 and float(r["ms_16x16"]) > 0
        assert int(r["params"]) > 0 and float(r["gflop"]) > 0 and r["backend"] == "eager fp32"
    assert [r["test_psnr"] for r in rows] == ["", "31.5", ""] and rows[1]["test_tpsnr"] == "30.5"
    front = [r for r in rows if r["front"] == "True"]
    assert front and (out / "accuracy_vs_time.png").stat().st_size > 1000
    lines = (out / "front.txt").read_text().splitlines()
    assert len(lines) == len(front) and all("net=tiny" in line and "kernel.sizes=" in line for line in lines)
    assert f"denoiser-train {lines[0]}" in (out / "pareto.md").read_text()
    cached = sorted((out / "cache").iterdir())
    assert len(cached) == 3

    # a rerun reuses the cached timings; a rerun of the sweep skips the finished jobs
    run_ok(report, tmp_path)
    assert sorted((out / "cache").iterdir()) == cached

    # variant 0 retrained with seeds 1 and 2 (as make pareto does for the front) is one row: mean ± std,
    # timed once; OIDN-fast is timed in the same process, with its val PSNR from denoiser-eval's table
    seeds = tmp_path / "seeds"
    run_ok(command("train", "-m", *TINY, f"data.root={data_root}", "kernel.sizes=[3]", "skip_done=true",
                   "seed=1,2", f"hydra.sweep.dir={seeds}", "hydra.sweep.subdir=0_s${seed}"), tmp_path)
    val_csv = tmp_path / "val.csv"
    val_csv.write_text("method,scene,sequence,psnr,tpsnr\nOIDN-fast,mean,mean,99.0,98.0\n")

    def report_over_seeds() -> list[dict]:
        run_ok(command("pareto", f"sweep_dir=[{sweep},{seeds}]", f"out_dir={out}", "backend=eager",
                       "sizes=[[32,32],[16,16]]", "warmup=0", "repeats=1", "threads=1", "baselines=default",
                       "baselines.noisy=null", "baselines.oidn_balanced=null", "baselines.oidn_high=null",
                       f"baseline_eval_csv={val_csv}"), tmp_path)
        with open(out / "pareto.csv", newline="") as fh:
            return list(csv.DictReader(fh))

    rows = report_over_seeds()
    assert [r["variant"] for r in rows] == ["kernel.sizes=[3]", "kernel.sizes=[5,5]", "kernel.sizes=[3,5,5]",
                                            "OIDN-fast"]
    vals = [json.loads((d / "metrics.json").read_text())["metrics"]["val/psnr"] for d in
            (sweep / "0", seeds / "0_s1", seeds / "0_s2")]
    assert rows[0]["seeds"] == "cfg 1 2" and float(rows[0]["val_psnr"]) == pytest.approx(sum(vals) / 3, abs=1e-6)
    assert float(rows[0]["val_psnr_std"]) == pytest.approx(statistics.stdev(vals), abs=1e-6)
    assert rows[1]["val_psnr_std"] == ""  # one seed: no spread
    networks = [p for p in (out / "cache").iterdir() if not p.name.startswith("baseline_")]
    assert len(networks) == 3  # the seeds were not timed again
    assert len(list((out / "cache").glob("baseline_*.json"))) == 1  # OIDN-fast's times, cached like the networks'
    oidn = rows[3]
    assert oidn["kind"] == "baseline" and float(oidn["val_psnr"]) == 99.0 and float(oidn["ms_32x32"]) > 0
    assert oidn["front"] == "False"  # the front is the variants'; OIDN is measured against it
    text = (out / "pareto.md").read_text()
    assert "- OIDN-fast (val PSNR 99.00 dB," in text and "no front variant dominates it" in text
    # a later report keeps OIDN's times of the first timing pass (not re-timed under other conditions)
    again = report_over_seeds()
    assert again[3]["ms_32x32"] == oidn["ms_32x32"] and again[3]["ms_16x16"] == oidn["ms_16x16"]
    proc = run_ok(command("train", "-m", *TINY, f"data.root={data_root}", "kernel.sizes=[3],[5,5],[3,5,5]",
                          f"hydra.sweep.dir={sweep}", "hydra.sweep.subdir=${hydra.job.num}", "skip_done=true"), tmp_path)
    assert proc.stderr.count("finished before, skipped") == 3


def trial_counts(db: Path) -> dict[str, int]:
    """Trials of the sweep's optuna database per state, read-only: {} while its tables do not exist.
    Never through optuna's storage, which writes its schema into a file that lacks it (the sweep
    writes it too, and the second writer fails)."""
    import sqlite3

    try:
        with contextlib.closing(sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=5)) as con:
            rows = con.execute("SELECT state, COUNT(*) FROM trials GROUP BY state").fetchall()
    except sqlite3.OperationalError:  # no file or no table yet, or locked by the writer: read again later
        return {}
    return {str(state): int(n) for state, n in rows}


def test_trial_counts_never_writes_the_sweeps_database(tmp_path):
    """The kill test polls the sweep's database while the sweep creates it: a reader that writes
    (optuna's storage stamps its schema version into a file without one) raced the sweep's own
    stamp, and the sweep died of the unique constraint (CI, 2026-11-29: exit 1, no trial). The
    poll reads without writing, so an empty file (the sweep's first connection) stays empty."""
    pytest.importorskip("optuna")
    db = tmp_path / "optuna.db"
    db.touch()
    assert trial_counts(db) == {}
    assert db.stat().st_size == 0


@pytest.mark.slow
def test_optuna_sweeper_runs_and_resumes_after_a_kill(data_root, tmp_path):
    pytest.importorskip("optuna")
    sweep = tmp_path / "sweep"
    db = sweep / "optuna.db"
    argv = command("train", "-m", "hydra/sweeper=optuna_pareto", "hydra.sweeper.n_trials=6",
                   "hydra.sweeper.population_size=4", *TINY, f"data.root={data_root}", TIME,
                   "kernel.sizes=[3],[5,5],[3,5,5]", "ablation=none,no_temporal", f"hydra.sweep.dir={sweep}",
                   "hydra.sweep.subdir=${hydra.job.num}")
    first = subprocess.Popen(argv, cwd=tmp_path, env=env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 200
    try:
        while True:  # kill it during a trial, once two are complete
            counts = trial_counts(db) if db.exists() else {}
            if counts.get("COMPLETE", 0) >= 2 and counts.get("RUNNING", 0) >= 1:
                break
            if first.poll() is not None:  # its last lines say why (seen once under make test: exit 1, no trial)
                pytest.fail(f"the sweep ended (exit {first.returncode}) before it could be killed: {counts}\n"
                            + first.stderr.read().decode(errors="replace")[-3000:])
            assert time.monotonic() < deadline, counts
            time.sleep(0.1)
    finally:
        first.kill()
        first.wait()
    killed = trial_counts(db)
    # one trial RUNNING (0 only if the kill fell in the instant between one trial's tell and the next ask)
    running = killed.get("RUNNING", 0)
    assert running <= 1 and 2 <= killed.get("COMPLETE", 0) < 6, killed

    proc = run_ok(argv, tmp_path)
    assert ("marked FAIL" in proc.stderr) == bool(running)
    counts = trial_counts(db)
    assert counts.get("COMPLETE") == 6 and counts.get("FAIL", 0) == running and "RUNNING" not in counts, counts

    import optuna

    study = optuna.load_study(study_name="pareto", storage=f"sqlite:///{db}")
    complete = [t for t in study.trials if t.state.name == "COMPLETE"]
    assert all(t.values[0] > 0 and t.values[1] > 0 for t in complete)  # [val PSNR, ms]
    assert study.best_trials  # the front
    from omegaconf import OmegaConf

    results = OmegaConf.load(sweep / "optimization_results.yaml")
    assert results.n_complete == 6 and len(results.pareto_front) == len(study.best_trials)
    # each completed trial's job directory holds its run: ms in metrics.json, TensorBoard hparams with final/ms
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    job = sweep / str(complete[-1].number)
    assert (job / "DONE").is_file()
    acc = EventAccumulator(str(job / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    assert {"final/psnr", "final/ms"} <= set(acc.Tags()["scalars"])


@pytest.mark.parametrize("backend", ["openvino", "onnxruntime"])
def test_a_network_without_recurrence_times_on_the_graph_backends(backend):
    """Without temporal recurrence the exported graph has no ``motion`` input: the feed leaves it out."""
    from denoiser.configs import build_net, compose_net_config
    from denoiser.inference.backends import OnnxRuntimeBackend, OpenVinoBackend
    from denoiser.report.pareto import time_network

    impl = OpenVinoBackend() if backend == "openvino" else OnnxRuntimeBackend()
    if impl.available():
        pytest.skip(impl.available())
    net = build_net(compose_net_config("tiny", "student", ["net.temporal=null"]))
    row = time_network(net, impl, (16, 16), threads=1, warmup=1, repeats=1)
    assert row["status"] == "ok" and row["ms_median"] > 0


def test_the_pareto_experiment_grid():
    """experiment=pareto: the demo_distill recipe for a fixed step count, the three axes of the issue
    (54 variants), the widths 0.5x/1x/2x of the demo student; the Optuna sweeper keeps the axes."""
    from hydra import compose, initialize_config_dir
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from denoiser.conf import CONF_DIR
    from denoiser.configs import build_net, compose_net_config

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=["experiment=pareto", "output_dir=/tmp/x"], return_hydra_config=True)
        optuna_cfg = compose("train", overrides=["experiment=pareto", "hydra/sweeper=optuna_pareto", "output_dir=/tmp/x"],
                             return_hydra_config=True)
    assert cfg.model._target_.endswith("DistillationModule") and cfg.trainer.max_steps == 300
    assert cfg.trainer.max_time is None and cfg.seed == 0
    params = dict(cfg.hydra.sweeper.params)
    assert set(params) == {"net", "kernel.sizes", "ablation"}
    parser = OverridesParser.create()
    sizes = [len(list(parser.parse_overrides([f"{k}={v}"])[0].sweep_iterator())) for k, v in params.items()]
    assert sizes == [3, 9, 2]
    assert dict(optuna_cfg.hydra.sweeper.params) == params
    assert optuna_cfg.hydra.sweeper._target_.endswith("OptunaParetoSweeper")
    widths = [build_net(compose_net_config(n, "student")).num_parameters()
              for n in ("demo_student_w05", "demo_student", "demo_student_w2")]
    assert widths[0] < widths[1] < widths[2]


def test_the_installed_package_finds_the_sweeper_plugin(tmp_path):
    """hydra/sweeper=optuna_pareto is found outside the source tree: through the installed package
    (make's editable install, or a wheel: tests/core/test_wheel.py), not through the current directory."""
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    probe = ("import importlib.util, sys; sys.exit(0 if importlib.util.find_spec('denoiser') else 3)")
    if subprocess.run([sys.executable, "-c", probe], cwd=tmp_path, env=env, check=False).returncode == 3:
        pytest.skip("the denoiser package is not installed in this interpreter (make setup installs it)")
    code = ("from hydra.core.plugins import Plugins; from hydra.plugins.sweeper import Sweeper; "
            "print(*[p.__module__ + '.' + p.__name__ for p in Plugins.instance().discover(Sweeper)], sep='\\n')")
    proc = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env, capture_output=True, text=True,
                          check=False, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "hydra_plugins.denoiser_optuna.optuna_pareto_sweeper.OptunaParetoSweeper" in proc.stdout.split()


def test_a_job_of_an_older_sweep_names_its_lever_where_it_is_now(tmp_path):
    """A job directory from before the levers left conf/ablation/ (issue 63) stores ``ablation=<lever>``
    in .hydra/overrides.yaml: read_job gives ``lever=<lever>`` (so its label, its seed group and the
    front's command lines are today's), an ablation as stored."""
    for name, stored in (("old", "ablation=history_clamp"), ("ablated", "ablation=no_temporal")):
        (tmp_path / name / ".hydra").mkdir(parents=True)
        (tmp_path / name / ".hydra" / "overrides.yaml").write_text(f"- {stored}\n- seed=0\n")
    assert read_job(tmp_path / "old")["overrides"] == ["lever=history_clamp", "seed=0"]
    assert read_job(tmp_path / "ablated")["overrides"] == ["ablation=no_temporal", "seed=0"]
