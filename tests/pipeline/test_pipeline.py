"""denoiser-pipeline (denoiser/pipeline): the stages of conf/pipeline/*.yaml run by stub commands
that log their calls. Skipping, resuming after a killed stage, jobs side by side, a failed stage,
the stage-time table and the checkpoint choice, plus the grammar's pieces against plain loops."""

from __future__ import annotations

import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.configs import compose_command
from helpers.stubs import STUB_HEADER, stub_calls

ROOT = Path(__file__).resolve().parents[2]
COMMANDS = ["denoiser-train", "denoiser-eval", "denoiser-bench", "denoiser-render", "denoiser-pareto", "python"]

# A stub of every command: logs its call; a training run (hydra.run.dir=...) leaves DONE, a best.ckpt
# and a last.ckpt, as the trainer does (skip_done=true with DONE there: nothing written, as the trainer's own skip); STUB_FAIL
# (a run name) fails that run; STUB_SLEEP sleeps first (STUB_SIDE: a file the job's start and end go to).
STUB = STUB_HEADER + r"""
dir=""
for a in "$@"; do case $a in hydra.run.dir=*) dir=${a#hydra.run.dir=} ;; out_dir=*) out=${a#out_dir=} ;; esac; done
[ -n "${STUB_SIDE:-}" ] && echo "start ${dir##*/}- $(date +%s.%N) threads=${OMP_NUM_THREADS:-}" >> "$STUB_SIDE"
[ -n "${STUB_SLEEP:-}" ] && sleep "$STUB_SLEEP"
[ -n "${STUB_SIDE:-}" ] && echo "end ${dir##*/}- $(date +%s.%N)" >> "$STUB_SIDE"
if [ -n "${STUB_FAIL:-}" ] && [ "${dir##*/}" = "$STUB_FAIL" ]; then echo "stub: $STUB_FAIL fails" >&2; exit 1; fi
if [ -n "$dir" ]; then
    [ -f "$dir/DONE" ] && exit 0
    mkdir -p "$dir/checkpoints" && touch "$dir/checkpoints/best.ckpt" "$dir/checkpoints/last.ckpt" "$dir/DONE"
fi
if [ -n "${out:-}" ]; then mkdir -p "$out/images" && echo "| a |" > "$out/metrics.md" && echo "| b |" > "$out/report.md"; fi
for a in "$@"; do case $a in out=*) mkdir -p "$(dirname "${a#out=}")" && touch "${a#out=}" ;; esac; done
exit 0
"""


@pytest.fixture
def tree(tmp_path):
    """``tmp_path`` as a checkout's working folder with a ``bin`` of stub commands and demo data."""
    (tmp_path / "bin").mkdir()
    for name in COMMANDS:
        (tmp_path / "bin" / name).write_text(STUB)
        (tmp_path / "bin" / name).chmod(0o755)
    (tmp_path / "data" / "demo" / "test").mkdir(parents=True)
    return tmp_path


def pipeline(tree: Path, *overrides: str, env: dict | None = None, check: bool = True, popen: bool = False):
    """``denoiser-pipeline`` in ``tree`` with the stubs; the finished process (or the Popen)."""
    argv = [sys.executable, "-m", "denoiser.commands.pipeline", f"bin_dir={tree / 'bin'}",
            f"python={tree / 'bin' / 'python'}", "cores=2", *overrides]
    environ = {**os.environ, "STUB_LOG": str(tree / "calls.log"), "DENOISER_DATA": str(tree / "data"), **(env or {})}
    if popen:
        return subprocess.Popen(argv, cwd=tree, env=environ, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                                start_new_session=True)
    proc = subprocess.run(argv, cwd=tree, env=environ, capture_output=True, text=True, timeout=120, check=False)
    if check:
        assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return proc


def rows(table_path: Path) -> dict[str, list[str]]:
    out = {}
    for line in table_path.read_text().splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        out[cells[0]] = cells[1:]
    return out


def train_dirs(calls) -> list[str]:
    return [a.split("=", 1)[1] for c in calls if c[0] == "denoiser-train" for a in c if a.startswith("hydra.run.dir=")]


def arg(call, key: str) -> str | None:
    return next((a.split("=", 1)[1] for a in call if a.startswith(key + "=")), None)


# --- the grammar's pieces against plain computations ---------------------------------------------

def test_matrix_jobs_are_every_combination_in_order_with_their_extra_args():
    from denoiser.pipeline.stages import expand

    stage = {"matrix": {"seed": [0, 1, 2], "kind": {"distilled": ["experiment=d"], "no_kd": ["experiment=n"]}},
             "name": "student_{kind}_s{seed}", "run_dir": "runs/{name}", "args": ["seed={seed}", "ckpt={a: b}"]}
    jobs = expand("students", stage)
    expected = [(s, k) for s, k in itertools.product([0, 1, 2], ["distilled", "no_kd"])]  # the last key fastest
    assert [j.name for j in jobs] == [f"student_{k}_s{s}" for s, k in expected]
    for job, (seed, kind) in zip(jobs, expected):
        assert job.args == [f"seed={seed}", "ckpt={a: b}", "experiment=" + kind[0]]  # other braces kept
        assert job.run_dir == f"runs/student_{kind}_s{seed}" and job.checkpoint() == f"runs/student_{kind}_s{seed}/checkpoints/last.ckpt"
    assert [j.name for j in expand("teacher", {"run_dir": "t"})] == ["teacher"]


def test_best_checkpoint_is_best_then_last_and_the_choice_follows_where(tmp_path):
    from denoiser.pipeline.stages import Job, best, choose_checkpoints, ckpt_override

    run = tmp_path / "run"
    assert best(run) == str(run / "checkpoints" / "last.ckpt")  # the path it will have
    (run / "checkpoints").mkdir(parents=True)
    (run / "checkpoints" / "last.ckpt").touch()
    assert best(run) == str(run / "checkpoints" / "last.ckpt")
    (run / "checkpoints" / "best.ckpt").touch()
    assert best(run) == str(run / "checkpoints" / "best.ckpt")
    stages = {"teacher": [Job("teacher", {"name": "teacher"}, [], ckpt="t.ckpt")],
              "students": [Job(f"s{seed}_{v}", {"seed": str(seed), "variant": v}, [], ckpt=f"{seed}{v}.ckpt")
                           for seed in (0, 1) for v in ("a", "b", "c")]}
    chosen = choose_checkpoints({"stages": ["teacher", "students"], "where": {"seed": 0, "variant": ["a", "c"]}}, stages)
    assert chosen == {"teacher": "t.ckpt", "s0_a": "0a.ckpt", "s0_c": "0c.ckpt"}
    assert ckpt_override(chosen) == "ckpt={teacher: t.ckpt, s0_a: 0a.ckpt, s0_c: 0c.ckpt}"


def test_a_stage_with_an_unknown_key_or_nothing_to_run_is_one_line(tree):
    proc = pipeline(tree, "pipeline=demo", "+stages.render.jbos=2", check=False)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0
    assert "stages.render: unknown key(s) jbos" in proc.stderr
    proc = pipeline(tree, "pipeline=demo", "stages.render.command=null", check=False)
    assert proc.returncode == 2 and "stages.render: give exactly one of command, module, script or copy" in proc.stderr


# --- make demo through the command ---------------------------------------------------------------

def test_demo_renders_trains_the_recipe_evaluates_and_writes_the_table(tree):
    proc = pipeline(tree, "pipeline=demo")
    calls = stub_calls(tree / "calls.log")
    renders = [c for c in calls if c[0] == "denoiser-render"]
    assert sorted(arg(c, "render_set") for c in renders) == ["demo", "demo_motion"]  # the demo's two roots
    dirs = train_dirs(calls)
    students = sorted(f"student_{k}_s{s}" for s in (0, 1, 2) for k in ("distilled", "no_kd"))
    assert dirs[0] == "reports/demo/runs/teacher" and len(dirs) == 7
    assert sorted(dirs[1:]) == [f"reports/demo/runs/{n}" for n in students]  # side by side: any order
    by_dir = {arg(c, "hydra.run.dir"): c for c in calls if c[0] == "denoiser-train"}
    assert arg(by_dir["reports/demo/runs/teacher"], "experiment") == "demo_teacher"
    distilled = by_dir["reports/demo/runs/student_distilled_s2"]
    assert arg(distilled, "experiment") == "demo_distill" and arg(distilled, "model.teacher_ckpt") == \
        "reports/demo/runs/teacher/checkpoints/best.ckpt"  # resolved when the stage started: the teacher's best
    assert arg(distilled, "threads") == "1" and arg(distilled, "seed") == "2"
    assert "skip_done=true" in distilled and "ckpt_path=auto" in distilled
    no_kd = by_dir["reports/demo/runs/student_no_kd_s2"]
    assert arg(no_kd, "experiment") == "demo" and arg(no_kd, "model.teacher_ckpt") is None
    assert not any(arg(c, "model.init_ckpt") for c in by_dir.values())  # one stage: every run from its own start
    evaluations = [c for c in calls if c[0] == "denoiser-eval"]
    assert len(evaluations) == 1  # no data/blender/test: no Cycles evaluation
    ckpt = arg(evaluations[0], "ckpt")
    # every run's best.ckpt, looked up when the evaluation starts (not when its run was planned, before it trained)
    assert ckpt.startswith("{teacher: reports/demo/runs/teacher/checkpoints/best.ckpt, student_distilled_s0: "
                           "reports/demo/runs/student_distilled_s0/checkpoints/best.ckpt")
    assert ckpt.count("/checkpoints/best.ckpt") == 7 and "last.ckpt" not in ckpt
    assert ckpt.count("reports/demo/runs/student_") == 6 and arg(evaluations[0], "purpose")
    bench = next(c for c in calls if c[0] == "denoiser-bench")
    assert arg(bench, "ckpt").count("_s0:") == 2 and "_s1" not in arg(bench, "ckpt")  # the first seed only
    summary = next(c for c in calls if c[0] == "python" and "denoiser.commands.tools.eval_summary" in c)
    assert summary[summary.index("denoiser.commands.tools.eval_summary") + 1:] == ["report=reports/demo", "seeds=[0, 1, 2]"]
    assert (tree / "reports" / "demo" / "metrics.md").is_file() and (tree / "reports" / "demo" / "bench.md").is_file()
    table = rows(tree / "reports" / "demo" / "timings.md")
    assert list(table) == ["render", "teacher", "students", "eval", "bench", "summary", "report", "total", "work"]
    assert table["total"][1].endswith(": wall time") and "==== demo finished" in proc.stdout


def test_demo_with_more_seeds_fewer_jobs_and_a_stage_left_out_are_keys(tree):
    pipeline(tree, "pipeline=demo", "seeds=[3,4]", "jobs=1", "~stages.render")
    calls = stub_calls(tree / "calls.log")
    assert not any(c[0] == "denoiser-render" for c in calls)
    students = [c for c in calls if c[0] == "denoiser-train" and "reports/demo/runs/student" in (arg(c, "hydra.run.dir") or "")]
    assert [arg(c, "seed") for c in students] == ["3", "3", "4", "4"] and {arg(c, "threads") for c in students} == {"2"}


def test_a_second_run_skips_what_is_done_and_keeps_the_seconds_of_the_run_that_did_it(tree):
    pipeline(tree, "pipeline=demo")
    first = rows(tree / "reports" / "demo" / "timings.md")
    time.sleep(1.1)  # another run id
    (tree / "calls.log").unlink()
    pipeline(tree, "pipeline=demo")
    second = rows(tree / "reports" / "demo" / "timings.md")
    for stage in ("teacher", "students"):  # the trainer skipped them (no new DONE)
        assert second[stage] == first[stage], stage
    this_run = second["total"][1].removesuffix(": wall time")
    assert this_run != first["total"][1].removesuffix(": wall time") and second["eval"] == first["eval"]
    assert not any(c[0] in ("denoiser-eval", "denoiser-bench") for c in stub_calls(tree / "calls.log"))  # no second look
    assert second["work"][0] == str(sum(int(v[0]) for k, v in second.items() if k not in ("total", "work")))


def test_a_failed_job_stops_the_pipeline_with_one_line_naming_it(tree):
    proc = pipeline(tree, "pipeline=demo", env={"STUB_FAIL": "student_no_kd_s1"}, check=False)
    assert proc.returncode == 3
    errors = [line for line in proc.stderr.splitlines() if line.startswith("error:")]
    assert errors == ["error: [students] student_no_kd_s1 failed (exit 1), see reports/demo/runs/student_no_kd_s1.log"]
    assert "stub: student_no_kd_s1 fails" in (tree / "reports/demo/runs/student_no_kd_s1.log").read_text()
    calls = stub_calls(tree / "calls.log")
    assert not any(c[0] in ("denoiser-eval", "denoiser-bench") for c in calls)
    assert not (tree / "reports" / "demo" / "timings.md").exists()  # the table of a finished run only


def test_jobs_run_side_by_side_with_their_share_of_the_cores(tree):
    side = tree / "side.txt"
    pipeline(tree, "pipeline=demo", "seeds=[0]", "~stages.eval", "~stages.bench", "~stages.summary", "~stages.report",
             env={"STUB_SLEEP": "1", "STUB_SIDE": str(side)})
    events = {}
    for line in side.read_text().splitlines():
        kind, name, stamp, *rest = line.split()
        events[(kind, name.removesuffix("-"))] = (float(stamp), rest)
    a, b = "student_distilled_s0", "student_no_kd_s0"
    assert events[("start", a)][0] < events[("end", b)][0] and events[("start", b)][0] < events[("end", a)][0]  # overlap
    assert events[("start", a)][1] == ["threads=1"] and events[("start", "teacher")][1] == ["threads="]


def test_a_killed_pipeline_stops_its_jobs_and_the_next_run_resumes(tree):
    proc = pipeline(tree, "pipeline=demo", "seeds=[0]", env={"STUB_SLEEP": "30"}, popen=True)
    deadline = time.time() + 60
    while time.time() < deadline and not ((tree / "calls.log").exists() and "denoiser-render" in (tree / "calls.log").read_text()):
        time.sleep(0.2)
    time.sleep(0.5)
    os.kill(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=20)
    assert proc.returncode == 130 and "interrupted" in err
    time.sleep(0.5)
    ps = subprocess.run(["pgrep", "-f", f"{tree}/bin/"], capture_output=True, text=True, check=False)
    assert ps.stdout.strip() == "", "a stub command outlived the pipeline"
    pipeline(tree, "pipeline=demo", "seeds=[0]")
    calls = stub_calls(tree / "calls.log")
    assert "reports/demo/runs/teacher" in train_dirs(calls) and (tree / "reports/demo/timings.md").is_file()
    assert all("ckpt_path=auto" in c for c in calls if c[0] == "denoiser-train")  # the trainer resumes a run


def test_an_evaluation_of_the_same_checkpoints_is_not_redone_and_a_newer_checkpoint_redoes_it(tree):
    (tree / "reports" / "demo" / "runs").mkdir(parents=True)
    for name in ["student_distilled_s0", "student_no_kd_s0", "teacher"]:
        (tree / "reports" / "demo" / "runs" / name / "checkpoints").mkdir(parents=True)
        (tree / "reports" / "demo" / "runs" / name / "checkpoints" / "last.ckpt").touch()
        (tree / "reports" / "demo" / "runs" / name / "DONE").touch()
    ablate = ["pipeline=ablations", "seeds=[0]", "variants=[no_pyramid,direct]"]
    pipeline(tree, *ablate)
    first = stub_calls(tree / "calls.log")
    assert sum(c[0] == "denoiser-eval" for c in first) == 1
    ckpt = arg(next(c for c in first if c[0] == "denoiser-eval"), "ckpt")
    assert ckpt == ("{none_s0: reports/demo/runs/student_distilled_s0/checkpoints/last.ckpt, no_kd_s0: "
                    "reports/demo/runs/student_no_kd_s0/checkpoints/last.ckpt, no_pyramid_s0: "
                    "reports/ablations/runs/no_pyramid_s0/checkpoints/best.ckpt, direct_s0: "
                    "reports/ablations/runs/direct_s0/checkpoints/best.ckpt}")  # trained here: their best
    bench = next(c for c in first if c[0] == "denoiser-bench")
    assert arg(bench, "ckpt").count(": ") == 3 and "no_kd" not in arg(bench, "ckpt")
    (tree / "calls.log").unlink()
    pipeline(tree, *ablate)
    assert not any(c[0] in ("denoiser-eval", "denoiser-bench") for c in stub_calls(tree / "calls.log"))
    assert rows(tree / "reports" / "ablations" / "timings.md")["eval"][1].startswith("run ")  # the first run's row
    time.sleep(0.05)
    (tree / "reports" / "ablations" / "runs" / "direct_s0" / "checkpoints" / "best.ckpt").touch()  # retrained
    (tree / "calls.log").unlink()
    pipeline(tree, *ablate)
    assert [c[0] for c in stub_calls(tree / "calls.log") if c[0] in ("denoiser-eval", "denoiser-bench")] == \
        ["denoiser-eval", "denoiser-bench"]


def test_ablations_and_compare_need_make_demo_in_one_line(tree):
    for name in ("ablations", "compare", "paper"):
        proc = pipeline(tree, f"pipeline={name}", check=False)
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1, proc.stderr
        assert "(run make demo first" in proc.stderr
    (tree / "reports" / "demo" / "runs" / "teacher").mkdir(parents=True)
    (tree / "reports" / "demo" / "runs" / "teacher" / "DONE").touch()
    proc = pipeline(tree, "pipeline=ablations", check=False)
    assert proc.returncode == 2 and "student_distilled_s0: make demo's distilled student missing" in proc.stderr


def test_paper_runs_each_pipeline_as_a_stage_and_adds_up_their_work(tree):
    calls = pipeline(tree, "pipeline=paper", "dry_run=true").stdout.splitlines()
    assert [line.split("]")[0][1:] for line in calls] == ["ablations", "compare", "pareto", "summary"]
    assert calls[0].endswith("denoiser-pipeline pipeline=ablations")
    assert "denoiser.commands.tools.paper_budget paper=reports/paper/timings.md" in calls[3]


@pytest.mark.parametrize("name", ["demo", "ablations", "compare", "pareto", "paper"])
def test_every_pipeline_composes_and_its_training_overrides_compose_with_train(tree, name):
    """Each pipeline's dry run, and each of its training command lines composed by denoiser-train's config."""
    import shlex

    out = pipeline(tree, f"pipeline={name}", "dry_run=true").stdout
    trains = [line.split("denoiser-train ", 1)[1] for line in out.splitlines() if "denoiser-train " in line]
    for line in trains:
        args = [a for a in shlex.split(line) if not a.startswith(("hydra", "-m")) and "," not in a.split("=", 1)[-1]]
        cfg = compose_command("train", args)
        assert cfg.trainer.max_steps > 0
    # the other Hydra commands' lines compose with their own entry configs, their values as written
    # (lists, quoted strings with spaces, checkpoint mappings: what the shell passes)
    entry = {"denoiser-eval ": "eval", "denoiser-bench ": "bench", "denoiser-render ": "render",
             "denoiser.commands.tools.eval_summary ": "demo_summary", "denoiser.commands.tools.ablation_summary ": "ablation_summary"}
    composed = 0
    for line in out.splitlines():
        for marker, config in entry.items():
            if marker not in line:
                continue
            args = shlex.split(line.split(marker, 1)[1])
            if args[:1] == ["--config-name"]:
                config, args = args[1], args[2:]
            cfg = compose_command(config, [a for a in args if not a.startswith("hydra.")])
            if "ckpt" in cfg and any(a.startswith("ckpt=") for a in args) and name != "pareto":  # pareto's: runs not there yet
                assert len(cfg.ckpt) >= 1 and all(str(v).endswith(".ckpt") for v in cfg.ckpt.values())
            if "seeds" in cfg and any(a.startswith("seeds=") for a in args):
                assert list(cfg.seeds) == [0, 1, 2]
            if config == "ablation_summary":
                assert list(cfg.variants)[:3] == ["none", "no_kd", "no_pyramid"]
            if config == "eval" and "images.methods" in line:
                assert list(cfg.images.methods) == ["noisy input", "none_s0", "no_pyramid_s0", "direct_s0"]
            composed += 1
    assert composed >= {"demo": 5, "ablations": 3, "compare": 4, "pareto": 2, "paper": 0}[name]


def test_help_lists_the_pipelines_and_their_keys(tree):
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.pipeline", "pipeline=ablations", "--help"],
                          capture_output=True, text=True, check=True)
    for word in ("denoiser-pipeline", "variants:", "seeds:", "stages:"):
        assert word in proc.stdout, word
    header = proc.stdout.split("== Keys")[0]
    for path in sorted((ROOT / "conf" / "pipeline").glob("*.yaml")):  # every pipeline is named in the header
        assert path.stem in header, path.stem


def test_demo_evaluates_on_the_blender_sequences_when_they_exist_and_drops_a_stale_table(tree):
    (tree / "reports" / "demo" / "blender").mkdir(parents=True)  # an earlier run's table, no sequences now
    pipeline(tree, "pipeline=demo", "seeds=[0]")
    assert not (tree / "reports" / "demo" / "blender").exists()
    (tree / "data" / "blender" / "test").mkdir(parents=True)
    (tree / "calls.log").unlink()
    pipeline(tree, "pipeline=demo", "seeds=[0]")
    evaluations = [c for c in stub_calls(tree / "calls.log") if c[0] == "denoiser-eval"]
    assert len(evaluations) == 1 and "layout=blender" in evaluations[0]  # the demo split's evaluation was done before
    assert arg(evaluations[0], "data.root") == str(tree / "data" / "blender")
    assert arg(evaluations[0], "ckpt").startswith("{teacher: reports/demo/runs/teacher/checkpoints/best.ckpt, ")


def test_a_collapsed_training_run_stops_demo_and_is_kept_by_ablations(tree):
    run = tree / "reports" / "demo" / "runs" / "teacher"
    run.mkdir(parents=True)
    (run / "COLLAPSED").write_text("collapse: val/psnr fell 9 dB below its best at step 300")
    proc = pipeline(tree, "pipeline=demo", "seeds=[0]", check=False)
    assert proc.returncode == 3
    assert proc.stderr.strip().splitlines()[-1] == "error: [teacher] teacher: collapse: val/psnr fell 9 dB below its best at step 300"
    for name in ["student_distilled_s0", "student_no_kd_s0"]:
        (tree / "reports" / "demo" / "runs" / name).mkdir(parents=True)
        (tree / "reports" / "demo" / "runs" / name / "DONE").touch()
    (run / "DONE").touch()
    (tree / "reports" / "ablations" / "runs" / "k3_s0").mkdir(parents=True)
    (tree / "reports" / "ablations" / "runs" / "k3_s0" / "COLLAPSED").write_text("collapse: k3")
    proc = pipeline(tree, "pipeline=ablations", "seeds=[0]", "variants=[k3]")
    assert "warning: [k3_s0] collapse: k3 (kept, marked in the summary)" in proc.stdout


def test_compare_renders_its_data_and_evaluates_nppd_ws_and_make_demos_networks_with_onnd(tree):
    for name in ["teacher", "student_distilled_s0", "student_distilled_s1"]:
        (tree / "reports" / "demo" / "runs" / name / "checkpoints").mkdir(parents=True)
        (tree / "reports" / "demo" / "runs" / name / "DONE").touch()
        (tree / "reports" / "demo" / "runs" / name / "checkpoints" / "best.ckpt").touch()
    pipeline(tree, "pipeline=compare", "seeds=[0,1]")
    calls = stub_calls(tree / "calls.log")
    render = next(c for c in calls if c[0] == "denoiser-render")
    assert "render_set=demo_compare" in render and arg(render, "reference_from") == str(tree / "data" / "demo")
    assert train_dirs(calls) == [f"reports/compare/runs/{n}_demo_s{s}" for s in (0, 1) for n in ("nppd", "ws")]
    nppd = next(c for c in calls if c[0] == "denoiser-train")
    assert arg(nppd, "model.teacher_ckpt") == "reports/demo/runs/teacher/checkpoints/best.ckpt" and arg(nppd, "net") == "nppd_demo"
    evaluation = next(c for c in calls if c[0] == "denoiser-eval")
    assert arg(evaluation, "baselines") == "compare" and arg(evaluation, "ckpt") == (
        "{teacher: reports/demo/runs/teacher/checkpoints/best.ckpt, student_s0: reports/demo/runs/student_distilled_s0/"
        "checkpoints/best.ckpt, student_s1: reports/demo/runs/student_distilled_s1/checkpoints/best.ckpt, nppd_s0: "
        "reports/compare/runs/nppd_demo_s0/checkpoints/best.ckpt, ws_s0: reports/compare/runs/ws_demo_s0/checkpoints/"
        "best.ckpt, nppd_s1: reports/compare/runs/nppd_demo_s1/checkpoints/best.ckpt, ws_s1: reports/compare/runs/"
        "ws_demo_s1/checkpoints/best.ckpt}")  # make demo's runs and the ones trained here alike: each run's best
    summary = next(c for c in calls if c[0] == "python")
    assert summary[1:5] == ["-m", "denoiser.commands.tools.eval_summary", "--config-name", "compare_summary"]
    (tree / "calls.log").unlink()
    pipeline(tree, "pipeline=compare", "seeds=[0,1]")  # resumed (make paper again): no second look at the test split
    assert [c[0] for c in stub_calls(tree / "calls.log") if c[0] != "denoiser-train"] == ["denoiser-render", "python"]


def test_pareto_retrains_the_fronts_variants_named_in_its_table(tree, tmp_path):
    from denoiser.report.pareto import finished_runs, front_seed_jobs

    table = tmp_path / "pareto.csv"
    table.write_text("job,kind,front,seeds,overrides\n0,network,True,cfg,experiment=pareto net=a\n"
                     "1,network,False,cfg,experiment=pareto net=b\n2,network,True,\"0,1,2\",net=c\n3,baseline,True,,\n")
    assert front_seed_jobs(table, [1, 2]) == [{"name": "front_seeds_0", "args": [
        "experiment=pareto", "net=a", "seed=1,2", "hydra.sweep.subdir=0_s${seed}"]}]
    assert front_seed_jobs(table, []) == [] and front_seed_jobs(tmp_path / "none.csv", [1]) == []
    for job, done in (("0", True), ("1", False)):
        (tmp_path / "sweep" / job / ".hydra").mkdir(parents=True)
        (tmp_path / "sweep" / job / ".hydra" / "overrides.yaml").write_text("- net=a\n")
        (tmp_path / "sweep" / job / "checkpoints").mkdir()
        (tmp_path / "sweep" / job / "checkpoints" / "last.ckpt").touch()
        if done:
            (tmp_path / "sweep" / job / "DONE").touch()
    assert finished_runs([tmp_path / "sweep", tmp_path / "missing"]) == [
        {"name": "job0", "run_dir": str(tmp_path / "sweep" / "0"), "ckpt": str(tmp_path / "sweep" / "0" / "checkpoints" / "last.ckpt")}]


def test_a_pipeline_runs_as_one_slurm_job_through_hydras_submitit_launcher():
    """``denoiser-pipeline -m pipeline=paper hydra/launcher=submitit_slurm``: the pipeline process is
    one SLURM job (its stages then run on that job's node); the launcher composes with the app."""
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    from hydra import compose, initialize_config_dir

    from denoiser.conf import CONF_DIR

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("pipeline", overrides=["pipeline=paper", "hydra/launcher=submitit_slurm",
                                             "hydra.launcher.timeout_min=360"], return_hydra_config=True)
    assert cfg.hydra.launcher._target_.endswith("SlurmLauncher") and cfg.hydra.launcher.timeout_min == 360
    assert list(cfg.stages) == ["ablations", "compare", "pareto", "summary"]


def test_a_dry_run_read_by_head_ends_without_a_traceback(tree):
    argv = [sys.executable, "-m", "denoiser.commands.pipeline", "pipeline=demo", "dry_run=true", f"bin_dir={tree / 'bin'}"]
    proc = subprocess.run(f"{' '.join(argv)} | head -2", shell=True, cwd=tree, capture_output=True, text=True, check=False,
                          env={**os.environ, "DENOISER_DATA": str(tree / "data")})
    assert len(proc.stdout.splitlines()) == 2 and "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr


def test_paper_summary_stage_reads_the_table_of_the_run_it_is_part_of(tree):
    """make paper's last stage sums the stages' work from make paper's own table, which is still
    ``timings.md.tmp`` while the pipeline runs (a real summary here, each pipeline a stub that writes its table)."""
    (tree / "bin" / "denoiser-pipeline").write_text(STUB_HEADER + r"""
for a in "$@"; do case $a in pipeline=*) name=${a#pipeline=} ;; esac; done
mkdir -p "reports/$name" && printf '| stage | seconds | run |\n|---|---:|---|\n| a | 7 | run x |\n| total | 7 | x |\n| work | 7 | x |\n' > "reports/$name/timings.md"
file=summary.md; [ "$name" = pareto ] && file=pareto.md
printf '<!-- %s:begin -->\n%s results\n<!-- %s:end -->\n' "$name" "$name" "$name" > "reports/$name/$file"
""")
    (tree / "bin" / "denoiser-pipeline").chmod(0o755)
    (tree / "reports" / "demo" / "runs" / "teacher").mkdir(parents=True)
    (tree / "reports" / "demo" / "runs" / "teacher" / "DONE").touch()
    pipeline(tree, "pipeline=paper", f"python={sys.executable}")
    block = (tree / "reports" / "paper" / "summary.md").read_text().split("<!-- paper:begin -->")[1]
    assert "| all | 21 | 0.01 h |" in block and "within the budget of 6.00 h" in block
    assert all(f"{name} results" in block for name in ("ablations", "compare", "pareto"))
    assert set(rows(tree / "reports" / "paper" / "timings.md")) >= {"ablations", "compare", "pareto", "summary", "work"}


def test_recipe_check_evaluates_both_recipes_students_on_each_split_once(tree):
    """make demo's students and another recipe's (its runs, its own checkpoint file) in one evaluation per
    split, each a declared look; the summary's claims pair the two recipes; a second run looks at nothing."""
    other = tree / "old" / "runs"
    for root, ckpt in ((tree / "reports" / "demo" / "runs", "best.ckpt"), (other, "interpolated_a0.75.ckpt")):
        for name in ["student_distilled_s0", "student_no_kd_s0"]:
            (root / name / "checkpoints").mkdir(parents=True)
            (root / name / "DONE").touch()
            (root / name / "checkpoints" / ckpt).touch()
    keys = ["pipeline=recipe_check", "seeds=[0]", f"other_runs={other}", "other_ckpt=checkpoints/interpolated_a0.75.ckpt",
            "purpose=against refine"]
    proc = pipeline(tree, *keys[:-1], check=False)  # the purpose is required: a look at a test split says why
    assert proc.returncode != 0 and "purpose" in proc.stderr and "Traceback" not in proc.stderr
    (tree / "data" / "blender" / "test").mkdir(parents=True)
    pipeline(tree, *keys)
    calls = stub_calls(tree / "calls.log")
    assert [c[0] for c in calls] == ["denoiser-eval", "denoiser-eval", "python"]  # nothing trained
    demo_split, cycles = calls[0], calls[1]
    assert arg(demo_split, "data") == "demo" and arg(cycles, "layout") == "blender"
    assert arg(demo_split, "purpose") == "'against refine'" and arg(cycles, "purpose") == "'against refine (Cycles)'"
    for call in (demo_split, cycles):
        assert arg(call, "ckpt") == (
            "{student_distilled_s0: reports/demo/runs/student_distilled_s0/checkpoints/best.ckpt, student_no_kd_s0: "
            f"reports/demo/runs/student_no_kd_s0/checkpoints/best.ckpt, refine_distilled_s0: {other}/student_distilled_s0/"
            f"checkpoints/interpolated_a0.75.ckpt, refine_no_kd_s0: {other}/student_no_kd_s0/checkpoints/interpolated_a0.75.ckpt}}")
        assert "~baselines.oidn_high" in call and "~baselines.oidn_balanced" in call  # the noisy input and OIDN-fast
    summary = calls[2]
    assert summary[1:5] == ["-m", "denoiser.commands.tools.eval_summary", "--config-name", "recipe_check_summary"]
    from denoiser.configs import compose_config

    cfg = compose_config(summary[5:], "recipe_check_summary")
    assert [(c.network, c.baseline) for c in cfg.claims][:2] == [("student_distilled", "refine_distilled"),
                                                                  ("student_no_kd", "refine_no_kd")]
    assert "tpsnr" in cfg.claims[0].metrics and cfg.title.endswith("the refine recipe's")
    # the Cycles block has a name of its own (docs/results.md holds make demo's blender block too)
    assert arg(cycles, "out_dir") == "reports/recipe_check/recipe_cycles" and [k for k, v in cfg.extra_evals.items() if v] == ["recipe_cycles"]
    (tree / "calls.log").unlink()
    pipeline(tree, *keys)  # again: the same checkpoints, no second look at either split
    assert [c[0] for c in stub_calls(tree / "calls.log")] == ["python"]
    (other / "student_no_kd_s0" / "DONE").unlink()
    proc = pipeline(tree, *keys, check=False)
    assert proc.returncode == 2 and proc.stderr == (
        f"error: {other}/student_no_kd_s0: the other recipe's student missing (other_runs)\n")
