"""`make ablations` (conf/pipeline/ablations.yaml) and its report (denoiser/commands/tools/ablation_summary.py):
the summary's means, paired intervals, verdicts and sentences on synthetic evaluations with known
differences (the paper's direction holding and not holding), its one-line errors, the script's
commands (with stub executables), the configs it composes, and the Makefile targets."""

from __future__ import annotations

import csv
import json
import os
import re
import statistics
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

from denoiser.conf import CONF_DIR
from denoiser.report.seed_groups import format_interval
from denoiser.report.stats import paired_interval

ROOT = Path(__file__).resolve().parents[2]
SEEDS = (0, 1, 2)
SEQUENCES = [f"test/s{i}_012" for i in range(8)]
ALT = [(-1) ** i for i in range(8)]   # +1, -1, ...: a difference with mean 0 (tied)
#: per-sequence PSNR of each variant minus none's (the same for every seed)
OFFSETS = {
    "none": [0.0] * 8,
    "no_pyramid": [-1.0 - 0.1 * i for i in range(8)],   # behind: the paper's noise claim holds
    "direct": [0.3 * a for a in ALT],                   # tied: the claim does not hold for it
    "no_kd": [-2.0] * 8,                                # behind: holds
    "no_unlabeled": [0.2 * a for a in ALT],             # tied: does not hold
    "no_adversarial": [0.4] * 8,                        # ahead: does not hold
    "no_param_transfer": [-3.0 + 0.05 * a for a in ALT],   # behind: holds
    "k3": [-0.5] * 8,                                   # behind: the paper's 5x5 over 3x3 holds
    "k7": [0.6] * 8,                                    # ahead: 7x7 buys quality, the paper's 5x5 does not hold
}
SEED_NOISE = {0: -0.1, 1: 0.0, 2: 0.1}   # averages out over the seeds


def psnr(variant: str, seed: int, i: int, offsets=OFFSETS) -> float:
    return 30.0 + 0.3 * i + offsets[variant][i] + SEED_NOISE[seed]


def metric_rows(offsets=OFFSETS, seeds=SEEDS) -> list[dict]:
    rows = [{"method": "noisy input", "scene": f"s{i}", "sequence": q, "frames": 6, "psnr": 20.0, "ssim": 0.5,
             "tpsnr": 18.0, "flip": 0.2, "relmse": 0.2} for i, q in enumerate(SEQUENCES)]
    for variant in offsets:
        for s in seeds:
            for i, q in enumerate(SEQUENCES):
                p = psnr(variant, s, i, offsets)
                rows.append({"method": f"{variant}_s{s}", "scene": f"s{i}", "sequence": q, "frames": 6, "psnr": p,
                             "ssim": p / 40, "tpsnr": p - 1.5, "flip": 1 / p, "relmse": 0.01})
    return rows


def bench_rows(ms: dict[str, float]) -> list[dict]:
    rows = [{"method": "OIDN-fast", "backend": "OIDN (pyoidn)", "dtype": "fp32", "height": 1080, "width": 1920,
             "status": "ok", "ms_median": 2100.0, "kind": "baseline"}]
    for method, t in ms.items():
        rows += [{"method": method, "backend": "openvino f32", "dtype": "fp32", "height": 1080, "width": 1920,
                  "status": "ok", "ms_median": t, "kind": "checkpoint"},
                 {"method": method, "backend": "openvino bf16", "dtype": "bf16", "height": 1080, "width": 1920,
                  "status": "skipped: CPU has no bf16 support (OpenVINO would run f32)", "ms_median": "",
                  "kind": "checkpoint"},
                 {"method": method, "backend": "openvino f32", "dtype": "fp32", "height": 256, "width": 256,
                  "status": "ok", "ms_median": 1.0, "kind": "checkpoint"}]   # another size: never shown
    return rows


def write_csv(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    columns = list(dict.fromkeys(k for r in rows for k in r))
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, columns)
        writer.writeheader()
        writer.writerows(rows)


MS = {"none_s0": 1050.0, "no_pyramid_s0": 1000.0, "direct_s0": 900.0}


def report(tmp_path: Path, rows=None, ms=MS, images=True) -> Path:
    out = tmp_path / "report"
    write_csv(out / "eval" / "metrics.csv", metric_rows() if rows is None else rows)
    write_csv(out / "bench" / "bench.csv", bench_rows(ms))
    if images:
        for q in SEQUENCES:
            (out / "eval" / "images").mkdir(parents=True, exist_ok=True)
            (out / "eval" / "images" / f"{q.replace('/', '_')}.png").write_bytes(q.encode())
    return out


class Done:
    """What a command left: its exit code and stderr (the shape of subprocess.CompletedProcess)."""

    def __init__(self, returncode: int, stderr: str):
        self.returncode, self.stderr = returncode, stderr


def summary(tmp_path: Path, *overrides: str) -> Done:
    """The summary task in this process (as its console entry runs it: composed config, user
    errors as one line and exit 2), run from ``tmp_path``."""
    import contextlib
    import io

    from denoiser.commands.app import guarded
    from denoiser.commands.tools.ablation_summary import run

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("ablation_summary", overrides=[f"report={tmp_path / 'report'}", f"data_root={tmp_path / 'data'}",
                                                     "seeds=[0,1,2]", *overrides])
    err, cwd = io.StringIO(), os.getcwd()
    os.chdir(tmp_path)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            guarded(run)(cfg)
        code = 0
    except SystemExit as exc:
        code = exc.code
    finally:
        os.chdir(cwd)
    return Done(code, err.getvalue())


def cli(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "denoiser.commands.tools.ablation_summary", *args], capture_output=True,
                          text=True, cwd=tmp_path, check=False, env={**os.environ, "PYTHONPATH": str(ROOT)})


def table(text: str, first: str) -> dict[str, list[str]]:
    """{first cell: cells} of the markdown table whose header starts with ``| first |``."""
    lines = text.split(f"| {first} |", 1)[1].split("\n\n", 1)[0].splitlines()[2:]
    cells = [[c.strip() for c in line.strip("|").split("|")] for line in lines]
    return {c[0]: c for c in cells}


def interval(variant: str, metric=lambda p: p) -> str:
    a = [statistics.fmean(metric(psnr(variant, s, i)) for s in SEEDS) for i in range(8)]
    b = [statistics.fmean(metric(psnr("none", s, i)) for s in SEEDS) for i in range(8)]
    return paired_interval(a, b)


def test_summary_intervals_verdicts_and_sentences(tmp_path):
    out = report(tmp_path)
    proc = summary(tmp_path)
    assert proc.returncode == 0, proc.stderr
    text = (out / "summary.md").read_text()
    block = text.split("<!-- ablations:begin -->", 1)[1].split("<!-- ablations:end -->", 1)[0]
    # Fig. A.1: means ± std over seeds and the paired interval against the pyramid student
    a1 = table(block, "variant")
    assert list(a1) == ["none", "no_pyramid", "direct"]
    for variant, cells in a1.items():
        per_seed = [statistics.fmean(psnr(variant, s, i) for i in range(8)) for s in SEEDS]
        assert cells[1] == "3" and cells[2] == f"{statistics.fmean(per_seed):.2f} ± {statistics.stdev(per_seed):.2f}"
    assert a1["none"][6:] == ["", "", "", ""]
    iv = interval("no_pyramid")
    assert a1["no_pyramid"][6] == f"{format_interval(iv, 'psnr')} behind"
    assert a1["no_pyramid"][8] == f"{format_interval(interval('no_pyramid', lambda p: 1 / p), 'flip')} behind"  # FLIP ↓
    assert a1["direct"][6].endswith(" tied")
    # the paper's claims, one sentence each: holds for no_pyramid, does not hold for direct (tied)
    noise = [line for line in block.splitlines() if "struggles to remove noise" in line]
    assert len(noise) == 2
    assert "(no_pyramid: " in noise[0] and "**holds** here: no_pyramid is behind the pyramid student on PSNR dB: " \
        f"{format_interval(iv, 'psnr')} (± {iv.half_width:.2f}, 8 sequences); SSIM behind, FLIP behind, tPSNR dB behind." \
        in noise[0]
    assert "**does not hold** here: direct is tied with the pyramid student" in noise[1]
    assert "crop figure below" in noise[1]
    # the time: 1050 against 1000 ms, +5% <= 10%: holds; bf16 was skipped and says why
    times = table(block.split("Time per 1920x1080 frame", 1)[1], "variant")
    assert times["none"][1] == "1050" and times["no_pyramid"][1:] == ["1000", "+50 ms (+5.0%)"]
    assert times["direct"][1:] == ["900", "+150 ms (+16.7%)"]
    runtime = next(line for line in block.splitlines() if "did not significantly impact the runtime" in line)
    assert "**holds** here" in runtime and "at most 10% more time" in runtime
    assert "openvino f32: 1050 ms against no_pyramid's 1000 ms, +50 ms (+5.0%)" in runtime
    assert "openvino bf16 not timed (skipped: CPU has no bf16 support" in runtime
    # the ablations: one row and one sentence each, the paper's direction as designed above
    rows = table(block.split("**The distillation ablations", 1)[1], "variant")
    assert list(rows) == ["none", "no_kd", "no_unlabeled", "no_adversarial", "no_param_transfer", "k3", "k7"]
    expect = {"no_kd": ("holds", "behind"), "no_unlabeled": ("does not hold", "tied"),
              "no_adversarial": ("does not hold", "ahead"), "no_param_transfer": ("holds", "behind"),
              "k3": ("holds", "behind"), "k7": ("does not hold", "ahead")}
    for name, (holds, verdict) in expect.items():
        (line,) = [x for x in block.splitlines() if x.startswith(f"- {name}, ")]
        assert f"It **{holds}** here: {name} {verdict.replace('tied', 'is tied with').replace('ahead', 'is ahead of').replace('behind', 'is behind')} the full recipe (none) on PSNR dB: " \
            f"{format_interval(interval(name), 'psnr')}" in line, line
        assert rows[name][6] == f"{format_interval(interval(name), 'psnr')} {verdict}"
    assert "5x5 kernels" in next(x for x in block.splitlines() if x.startswith("- k3, "))
    # the header names the run id and commit (readme_results copies them), the crop figure is the
    # sequence of the median no_pyramid - none difference (sorted: s7 .. s0, lower middle: s4)
    assert re.search(r"^- run id: \d{4}-\d\d-\d\dT", text, re.MULTILINE) and "\n- commit: " in text
    assert (out / "crops_a1.png").read_bytes() == b"test/s4_012" and "![Fig. A.1 crops](crops_a1.png)" in text
    # runs not found: the runs table says so
    assert "| none | 0 | reports/demo/runs/student_distilled_s0 |" in text and "not found" in text


def test_the_summary_names_the_evaluations_commit_and_looks(tmp_path):
    """The header's commit is the one the evaluation ran at (eval/evaluation.json), and the block
    opens with the test ledger's line: its split's looks now and which look the evaluation was; an
    evaluation without evaluation.json says its looks were not recorded."""
    from denoiser.report import ledger

    out, book = report(tmp_path), tmp_path / "ledger.csv"
    assert summary(tmp_path, f"ledger={book}").returncode == 0
    text = (out / "summary.md").read_text()
    assert "\n- commit: " in text and "(the summary's: the evaluation wrote no evaluation.json)" in text
    assert "<!-- ablations:begin -->\nTest ledger: looks not recorded (evaluated before the ledger" in text
    digest = "cd34" * 16
    look = ledger.record("data/demo", "test", digest, 8, ["none_s0"], [], "89abcde", "report", book)
    told = ledger.provenance("89abcde", "2026-01-02T03:04:05Z", "data/demo", "test", digest, 8, look, book)
    (out / "eval" / "evaluation.json").write_text(json.dumps(told))
    assert summary(tmp_path, f"ledger={book}").returncode == 0
    text = (out / "summary.md").read_text()
    assert "\n- commit: 89abcde (the evaluation's)\n" in text
    assert (f"<!-- ablations:begin -->\nTest ledger: this test split (SHA-256 {digest[:12]}) has been evaluated 1 time "
            f"({book}); this summary's evaluation is look 1.\n") in text


def test_readme_copy_of_the_block_and_its_figure(tmp_path):
    out = report(tmp_path)
    assert summary(tmp_path).returncode == 0
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\nintro\n\n<!-- ablations:pending -->\nPending: make ablations.\n\n## next\n")
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--summary",
                           str(out / "summary.md"), "--readme", str(readme), "--marker", "ablations", "--image",
                           f"{out / 'crops_a1.png'}:{tmp_path / 'docs' / 'images' / 'ablations_a1.png'}"],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    text = readme.read_text()
    assert "Pending" not in text and "struggles to remove noise" in text and "## next" in text
    assert re.search(r"<!-- copied by scripts/readme_results.py from .*, run id .*, commit \S+ \(the summary's: .*\) -->", text)
    assert "![ablations: crops_a1.png](docs/images/ablations_a1.png)" in text


def test_the_runtime_claim_does_not_hold_and_the_paired_rounds_decide(tmp_path):
    out = report(tmp_path, ms={"none_s0": 1500.0, "no_pyramid_s0": 1000.0, "direct_s0": 950.0})
    proc = summary(tmp_path)
    assert proc.returncode == 0, proc.stderr
    runtime = next(x for x in (out / "summary.md").read_text().splitlines() if "impact the runtime" in x)
    assert "**does not hold** here" in runtime and "+500 ms (+50.0%)" in runtime
    # per-round times (bench.json): the ratio paired per round, its median and min-max (7 rounds)
    rounds = {"none_s0": [1030, 1050, 1040, 1200, 1045, 1060, 1055], "no_pyramid_s0": [1000] * 7,
              "direct_s0": [900] * 7}
    rows = bench_rows({m: float(statistics.median(t)) for m, t in rounds.items()})
    write_csv(out / "bench" / "bench.csv", rows)
    for r in rows:
        if r["method"] in rounds and r["height"] == 1080 and r["status"] == "ok":
            r["times_ms"] = rounds[r["method"]]
    (out / "bench" / "bench.json").write_text(json.dumps({"rows": rows}))
    assert summary(tmp_path).returncode == 0
    text = (out / "summary.md").read_text()
    runtime = next(x for x in text.splitlines() if "impact the runtime" in x)
    assert "+50 ms (+5.0%, paired +5.0% [+3.0%, +20.0%])" in runtime
    assert "**undecided** here" in runtime   # the interval reaches above 10%
    assert summary(tmp_path, "figure.runtime_tolerance=0.25").returncode == 0
    assert "**holds** here" in next(x for x in (out / "summary.md").read_text().splitlines() if "impact the runtime" in x)


def test_k7_tied_agrees_with_the_papers_choice(tmp_path):
    offsets = {**OFFSETS, "k7": [0.1 * a for a in ALT]}
    report(tmp_path, rows=metric_rows(offsets))
    assert summary(tmp_path).returncode == 0
    (line,) = [x for x in (tmp_path / "report" / "summary.md").read_text().splitlines() if x.startswith("- k7, ")]
    assert "It **holds** here: k7 is tied with the full recipe" in line


def one_line_error(proc: subprocess.CompletedProcess, *words: str) -> None:
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1, (proc.returncode, proc.stderr)
    assert proc.stderr.startswith("error: ") and all(w in proc.stderr for w in words), proc.stderr


def test_bad_input_is_one_line_and_a_non_zero_exit(tmp_path):
    one_line_error(cli(tmp_path, f"report={tmp_path / 'report'}"), "eval/metrics.csv", "not found", "make ablations")
    one_line_error(summary(tmp_path), "eval/metrics.csv", "not found", "make ablations")
    out = report(tmp_path)
    (out / "bench" / "bench.csv").unlink()
    one_line_error(summary(tmp_path), "bench/bench.csv", "not found")
    report(tmp_path, rows=[r for r in metric_rows() if not r["method"].startswith("k7_")])
    one_line_error(summary(tmp_path), "metrics.csv", "no runs of variant 'k7'")
    assert summary(tmp_path, "variants=[none,no_pyramid,direct,no_kd]").returncode == 0   # a subset: fine
    report(tmp_path, rows=[r for r in metric_rows() if r["method"] != "direct_s2"])
    one_line_error(summary(tmp_path), "variant 'direct' lacks seed(s) [2]")
    report(tmp_path)
    one_line_error(summary(tmp_path, "variants=[none,no_temporal]"), "variants", "no_temporal")
    one_line_error(summary(tmp_path, "decide_metric=sharpness"), "sharpness")
    one_line_error(summary(tmp_path, "ablations.k7.paper=better"), "ablations.k7.paper")


def test_help_names_the_command(tmp_path):
    proc = cli(tmp_path, "--help")
    assert proc.returncode == 0 and proc.stdout.startswith("ablation_summary: "), proc.stdout[:200]
    assert "\nfigure:" in proc.stdout and "\nablations:" in proc.stdout and "powered by hydra" not in proc.stdout.lower()


# --- the configs the pipeline composes -------------------------------------------------------------


def script_variants() -> list[str]:
    """The variants make ablations trains (conf/pipeline/ablations.yaml: its `variants` key)."""
    from omegaconf import OmegaConf

    return list(OmegaConf.load(ROOT / "conf" / "pipeline" / "ablations.yaml").variants)


def compose_train(*overrides: str):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("train", overrides=["output_dir=/tmp/denoiser-test-ablations", *overrides])


def test_every_variant_composes_with_the_demo_recipe_and_changes_one_thing():
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        conf = compose("ablation_summary")
    # the script trains every configured variant but make demo's two (none, no_kd)
    assert sorted(script_variants()) == sorted({*conf.figure.variants, *conf.ablations} - {"none", "no_kd"})
    recipe = ["experiment=demo_distill", "model.teacher_ckpt=/t.ckpt"]
    base = compose_train(*recipe)
    changed = {
        "no_pyramid": lambda c: c.net.filter._target_ == "denoiser.nn.filters.SingleKernelFilter",
        "direct": lambda c: c.net.filter._target_ == "denoiser.nn.filters.DirectColor",
        "no_unlabeled": lambda c: c.data.use_unlabeled is False and base.data.use_unlabeled is True,
        "no_adversarial": lambda c: c.model.loss.adversarial_weight == 0 < base.model.loss.adversarial_weight,
        "no_param_transfer": lambda c: c.model.param_transfer is None and base.model.param_transfer is not None,
        "k3": lambda c: list(c.kernel.sizes) == [3, 3, 3],
        "k7": lambda c: list(c.kernel.sizes) == [7, 7, 7],
    }
    assert set(changed) == set(script_variants())
    for variant, check in changed.items():
        cfg = compose_train(*recipe, f"ablation={variant}")
        assert check(cfg), variant
        # the same steps, teacher, learning rate and data as make demo's distilled students
        assert cfg.trainer.max_steps == base.trainer.max_steps and cfg.model.teacher_ckpt == "/t.ckpt"
        assert cfg.model.optimizer.lr == base.model.optimizer.lr and cfg.data.root == base.data.root
    # make demo's no-KD students (experiment=demo, reused as no_kd) train as many steps as its distilled ones
    assert compose_train("experiment=demo").trainer.max_steps == base.trainer.max_steps


def test_the_bench_and_eval_overrides_of_the_script_compose():
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        bench = compose("bench", overrides=["data=demo", "~baselines.oidn_balanced", "~baselines.oidn_high",
                                            "quality=false", "check_oidn=false", "sizes=[[1080,1920]]",
                                            "use_backends=[openvino_f32,openvino_bf16]", "compare.student=none_s0"])
        ev = compose("eval", overrides=["data=demo", "~baselines.oidn_fast", "~baselines.oidn_balanced",
                                        "~baselines.oidn_high", "images.methods=['noisy input',none_s0,direct_s0]"])
    assert set(bench.baselines) == {"noisy", "oidn_fast"} and bench.baselines.noisy is None
    assert list(ev.baselines) == ["noisy"] and list(ev.images.methods) == ["noisy input", "none_s0", "direct_s0"]


def test_a_multirun_job_is_the_same_run_as_the_scripts_single_run():
    """skip_done compares overrides as Hydra parses them: the documented SLURM multirun's jobs
    (docs/training.md) are the runs make ablations (conf/pipeline/ablations.yaml) asks for, so it skips them."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    from denoiser.commands.train import same_overrides

    common = ["experiment=demo_distill", "model.teacher_ckpt=reports/demo/runs/teacher/checkpoints/best.ckpt"]
    tail = ["skip_done=true", "ckpt_path=auto", "trainer.enable_progress_bar=false", "callbacks.progress=null"]
    sweep = [*common, "ablation=no_pyramid,k7", "seed=0,1", *tail]
    (jobs,) = BasicSweeper.split_arguments(OverridesParser.create().parse_overrides(sweep), None)
    assert len(jobs) == 4 and "skip_done=True" in jobs[0]   # what Hydra writes back, not what was typed
    for job in jobs:
        variant, seed = (o.split("=")[1] for o in job if o.split("=")[0] in ("ablation", "seed"))
        single = [*common, f"ablation={variant}", f"seed={seed}", *tail]
        assert same_overrides(job, single) and same_overrides(job, list(reversed(single)))
        assert not same_overrides(job, [*single, "trainer.max_steps=50"])
        assert not same_overrides(job, [o.replace(f"seed={seed}", "seed=7") for o in single])


def test_runs_at_other_steps_by_another_teacher_or_collapsed_are_named(tmp_path):
    import torch

    out = report(tmp_path)
    for variant in OFFSETS:
        for s in SEEDS:
            run = out / "runs" / f"{variant}_s{s}"
            (run / "checkpoints").mkdir(parents=True)
            steps = 200 if variant == "k3" else 400
            torch.save({"global_step": steps, "callbacks": {}}, run / "checkpoints" / "last.ckpt")
            torch.save({"global_step": steps, "callbacks": {"ModelCheckpoint{'monitor': 'val/psnr'}":
                                                            {"best_model_score": 31.5 + s}}}, run / "checkpoints" / "best.ckpt")
            (run / ".hydra").mkdir()
            teacher = "other.ckpt" if variant == "direct" else "t.ckpt"
            (run / ".hydra" / "overrides.yaml").write_text(f"- experiment=demo_distill\n- model.teacher_ckpt={teacher}\n")
    (out / "runs" / "no_param_transfer_s1" / "COLLAPSED").write_text("collapse: ...\n")
    assert summary(tmp_path, "run_dirs=null").returncode == 0
    text = (out / "summary.md").read_text()
    block = text.split("<!-- ablations:begin -->", 1)[1].split("<!-- ablations:end -->", 1)[0]
    assert "- Not at equal steps: the runs trained 200, 400 steps" in block
    assert "- Not the same teacher: `other.ckpt`, `t.ckpt`." in block
    (line,) = [x for x in block.splitlines() if x.startswith("- no_param_transfer, ")]
    assert line.endswith("1 of its 3 runs collapsed (runs table): their numbers are those of a broken run.")
    runs = table(text.split("## Training runs", 1)[1], "variant")   # the last row (seed 2) per variant
    assert runs["k3"][1:7] == ["2", str(out / "runs" / "k3_s2"), "200", "33.50", "no", "t.ckpt"]


def test_one_teacher_named_relative_and_absolute_is_one_teacher(tmp_path):
    """A user's runs name their teacher as they typed it: ``runs/teacher/...`` from the folder they
    trained in (``.hydra/hydra.yaml``'s ``hydra.runtime.cwd``) is the pipeline's absolute path."""
    out, ckpt = report(tmp_path), tmp_path / "runs" / "teacher" / "checkpoints" / "best.ckpt"
    for variant in OFFSETS:
        for s in SEEDS:
            hydra = out / "runs" / f"{variant}_s{s}" / ".hydra"
            hydra.mkdir(parents=True)
            given = "runs/teacher/checkpoints/best.ckpt" if variant == "none" else str(ckpt)
            (hydra / "overrides.yaml").write_text(f"- experiment=demo_distill\n- model.teacher_ckpt={given}\n")
            (hydra / "hydra.yaml").write_text(f"hydra:\n  runtime:\n    cwd: {tmp_path}\n")
    assert summary(tmp_path, "run_dirs=null").returncode == 0
    text = (out / "summary.md").read_text()
    assert "Not the same teacher" not in text
    assert table(text.split("## Training runs", 1)[1], "variant")["none"][6] == str(ckpt)
