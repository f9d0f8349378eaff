"""`make fast-motion` (scripts/fast_motion.sh, issue 33's val study) with stub executables: what it
renders, trains, evaluates and tables, that it reads no test split, resumes, and refuses bad knobs
with one line; and that its overrides compose."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest
from conftest import STUB_HEADER, stub_calls, stub_pipeline
from hydra import compose, initialize_config_dir

from denoiser.conf import CONF_DIR

ROOT = Path(__file__).resolve().parents[1]
STUB = STUB_HEADER + """for arg in "$@"; do case "$arg" in
  hydra.run.dir=*) d=${arg#hydra.run.dir=}; mkdir -p "$d/checkpoints"; [ -f "$d/DONE" ] || touch "$d/checkpoints/last.ckpt" "$d/DONE"
    case "$d" in *_s1) [ -n "${STUB_COLLAPSE:-}" ] && echo "val PSNR fell" > "$d/COLLAPSED";; esac;;
  out_dir=*) mkdir -p "${arg#out_dir=}"; touch "${arg#out_dir=}/metrics.csv";;
esac; done
exit 0
"""


def _arg(call: list[str], key: str) -> str:
    return next(a.split("=", 1)[1] for a in call if a.startswith(f"{key}="))


def _run(root: Path, **env: str) -> tuple[subprocess.CompletedProcess, list[list[str]]]:
    log = root / "calls.log"
    log.write_text("")
    proc = subprocess.run(["bash", str(root / "scripts" / "fast_motion.sh")], capture_output=True, text=True,
                          check=False, env={**os.environ, "VENV": "venv", "STUB_LOG": str(log),
                                            "DENOISER_DATA": "data", **env})
    return proc, stub_calls(log)


@pytest.fixture
def tree(tmp_path):
    root = stub_pipeline(tmp_path, "fast_motion.sh", ("python", "denoiser-train", "denoiser-eval", "denoiser-render"),
                         STUB)
    runs = root / "reports" / "demo" / "runs"
    for run in ("teacher", "student_distilled_s0", "student_distilled_s1", "student_distilled_s2"):
        (runs / run / "checkpoints").mkdir(parents=True)
        (runs / run / "checkpoints" / "best.ckpt").touch()
        (runs / run / "DONE").touch()
    (root / "data" / "blender" / "val").mkdir(parents=True)
    return root


def test_fast_motion_trains_the_teacher_candidates_and_tables_them_on_val(tree):
    proc, calls = _run(tree, STUB_COLLAPSE="1")
    assert proc.returncode == 0, proc.stderr
    assert calls[0] == ["denoiser-render", "dataset=fast"]
    trained = [c for c in calls if c[0] == "denoiser-train"]
    assert sorted(_arg(c, "hydra.run.dir") for c in trained) == sorted(
        f"reports/fast/teachers/runs/{n}_s{s}" for n in ("lr2e3", "lr1e3", "warmup200") for s in (0, 1, 2))
    for c in trained:
        assert _arg(c, "experiment") == "demo_teacher" and _arg(c, "data.extra_roots") == "[data/fast]"
        assert "skip_done=true" in c and "ckpt_path=auto" in c
    lr1e3 = next(c for c in trained if _arg(c, "hydra.run.dir").endswith("lr1e3_s2"))
    assert _arg(lr1e3, "model.optimizer.lr") == "1e-3" and _arg(lr1e3, "seed") == "2"
    evals = [c for c in calls if c[0] == "denoiser-eval"]
    assert [_arg(c, "out_dir") for c in evals] == ["reports/fast/teachers/mitsuba_val", "reports/fast/teachers/blender_val"]
    assert all(_arg(c, "split") == "val" for c in evals) and not any("test" in a for c in evals for a in c)
    assert _arg(evals[0], "data.extra_roots") == "[data/fast]" and _arg(evals[1], "layout") == "blender"
    ckpts = dict(kv.split(": ") for kv in _arg(evals[0], "ckpt").strip("{}").split(", "))
    assert ckpts.pop("demo_teacher") == "reports/demo/runs/teacher/checkpoints/best.ckpt"
    assert sorted(ckpts) == sorted(f"{n}_s{s}" for n in ("lr2e3", "lr1e3", "warmup200") for s in (0, 1, 2))
    (table,) = [c for c in calls if "denoiser.commands.val_table" in c]
    assert _arg(table, "reference") == "lr2e3" and _arg(table, "candidates") == "[lr2e3,lr1e3,warmup200]"
    assert _arg(table, "seeds") == "[0,1,2]" and _arg(table, "out") == "reports/fast/teachers/val_table.md"
    assert "blender_val/metrics.csv" in _arg(table, "evals") and "model.optimizer.lr=1e-3" in _arg(table, "labels")
    collapsed = (tree / "reports" / "fast" / "teachers" / "collapsed.txt").read_text()
    assert collapsed.count("val PSNR fell") == 3 and "lr1e3_s1" in collapsed
    assert not any("students" in a for c in calls for a in c)   # no FAST_STUDENT_TEACHER: no students

    # a second run: training is skip_done's, the evaluations are done before; then the students
    proc, calls = _run(tree)
    assert proc.returncode == 0, proc.stderr
    assert not [c for c in calls if c[0] == "denoiser-eval"] and "done before" in proc.stdout
    proc, calls = _run(tree, FAST_STUDENT_TEACHER="lr1e3")
    assert proc.returncode == 0, proc.stderr
    students = [c for c in calls if c[0] == "denoiser-train" and "students" in _arg(c, "hydra.run.dir")]
    assert sorted(_arg(c, "hydra.run.dir").rsplit("/", 1)[1] for c in students) == \
        sorted(f"{n}_s{s}" for n in ("fast", "disagree") for s in (0, 1, 2))
    for c in students:
        assert _arg(c, "experiment") == "demo_distill" and _arg(c, "data.extra_roots") == "[data/fast]"
        assert _arg(c, "model.teacher_ckpt") == "reports/fast/teachers/runs/lr1e3_s0/checkpoints/last.ckpt"
        assert ("ablation=history_disagreement" in c) == ("/disagree_s" in _arg(c, "hydra.run.dir"))
    ev = [c for c in calls if c[0] == "denoiser-eval" and "students" in _arg(c, "out_dir")]
    ckpts = dict(kv.split(": ") for kv in _arg(ev[0], "ckpt").strip("{}").split(", "))
    assert ckpts["base_s1"] == "reports/demo/runs/student_distilled_s1/checkpoints/best.ckpt"
    assert ckpts["disagree_s1"] == "reports/fast/students/runs/disagree_s1/checkpoints/last.ckpt"
    assert sorted(ckpts) == sorted(f"{n}_s{s}" for n in ("base", "fast", "disagree") for s in (0, 1, 2))
    table = [c for c in calls if "denoiser.commands.val_table" in c][-1]
    assert _arg(table, "reference") == "base" and _arg(table, "candidates") == "[base,fast,disagree]"
    assert "ablation=history_disagreement" in _arg(table, "labels")


def test_fast_motion_students_of_the_demo_teacher_alone(tree):
    proc, calls = _run(tree, FAST_TEACHERS="none", FAST_STUDENT_TEACHER="demo", FAST_STUDENTS="x:model.optimizer.lr=1e-3")
    assert proc.returncode == 0, proc.stderr
    trained = [c for c in calls if c[0] == "denoiser-train"]
    assert sorted(_arg(c, "hydra.run.dir") for c in trained) == [f"reports/fast/students/runs/x_s{s}" for s in (0, 1, 2)]
    assert all(_arg(c, "model.teacher_ckpt") == "reports/demo/runs/teacher/checkpoints/best.ckpt"
               and _arg(c, "model.optimizer.lr") == "1e-3" for c in trained)
    assert [_arg(c, "out_dir") for c in calls if c[0] == "denoiser-eval"] == \
        ["reports/fast/students/mitsuba_val", "reports/fast/students/blender_val"]


def test_fast_motion_candidate_overrides_keep_their_lists_whole(tree):
    proc, calls = _run(tree, FAST_TEACHERS="none", FAST_STUDENT_TEACHER="demo",
                       FAST_STUDENTS="nz:ablation=no_kd,data.augment.noise_scale=[0.2,1.0],data.crop={a: 1, b: 2}")
    assert proc.returncode == 0, proc.stderr
    trained = [c for c in calls if c[0] == "denoiser-train"]
    assert len(trained) == 3
    for c in trained:
        assert _arg(c, "ablation") == "no_kd" and _arg(c, "data.augment.noise_scale") == "[0.2,1.0]"
        assert _arg(c, "data.crop") == "{a: 1, b: 2}"


def test_fast_motion_one_teacher_seed_with_its_own_threads_teaches_every_student_seed(tree):
    proc, calls = _run(tree, FAST_TEACHERS="t:ablation=noise_scale", FAST_TEACHER_SEEDS="0", FAST_TEACHER_THREADS="2",
                       FAST_STUDENT_TEACHER="t", FAST_STUDENTS="s:")
    assert proc.returncode == 0, proc.stderr
    trained = [c for c in calls if c[0] == "denoiser-train"]
    teachers = [c for c in trained if _arg(c, "experiment") == "demo_teacher"]
    students = [c for c in trained if _arg(c, "experiment") == "demo_distill"]
    assert [_arg(c, "hydra.run.dir") for c in teachers] == ["reports/fast/teachers/runs/t_s0"]
    assert _arg(teachers[0], "threads") == "2" and _arg(teachers[0], "ablation") == "noise_scale"
    assert sorted(_arg(c, "seed") for c in students) == ["0", "1", "2"]
    assert all(_arg(c, "threads") == "1" and _arg(c, "model.teacher_ckpt") ==
               "reports/fast/teachers/runs/t_s0/checkpoints/last.ckpt" for c in students)
    tables = [c for c in calls if c[:3] == ["python", "-m", "denoiser.commands.val_table"]]
    assert [(_arg(c, "out"), _arg(c, "seeds")) for c in tables] == [
        ("reports/fast/teachers/val_table.md", "[0]"), ("reports/fast/students/val_table.md", "[0,1,2]")]


def test_fast_motion_tables_finished_students_of_another_report_beside_its_own(tree):
    other = tree / "reports" / "other" / "students" / "runs"
    for seed in (0, 1, 2):
        (other / f"o_s{seed}" / "checkpoints").mkdir(parents=True)
        (other / f"o_s{seed}" / "DONE").touch()
    proc, calls = _run(tree, FAST_TEACHERS="none", FAST_STUDENT_TEACHER="demo", FAST_STUDENTS="s:",
                       FAST_ALSO_STUDENTS="o:reports/other/students/runs")
    assert proc.returncode == 0, proc.stderr
    assert sorted(_arg(c, "hydra.run.dir") for c in calls if c[0] == "denoiser-train") == [
        f"reports/fast/students/runs/s_s{s}" for s in (0, 1, 2)]  # the other runs are not trained again
    ckpts = dict(kv.split(": ") for kv in _arg(next(c for c in calls if c[0] == "denoiser-eval"), "ckpt")
                 .strip("{}").split(", "))
    assert ckpts["o_s2"] == "reports/other/students/runs/o_s2/checkpoints/last.ckpt" and "s_s0" in ckpts
    table = next(c for c in calls if c[:3] == ["python", "-m", "denoiser.commands.val_table"])
    assert _arg(table, "candidates") == "[base,s,o]"
    proc, calls = _run(tree, FAST_TEACHERS="none", FAST_STUDENT_TEACHER="demo", FAST_STUDENTS="s:",
                       FAST_ALSO_STUDENTS="p:reports/other/students/runs")
    assert proc.returncode == 2 and "reports/other/students/runs/p_s0: no finished run" in proc.stderr and not calls


def test_fast_motion_joins_more_roots_into_its_own_report(tree):
    proc, calls = _run(tree, FAST_TEACHERS="none", FAST_STUDENT_TEACHER="demo", FAST_STUDENTS="more:",
                       FAST_ROOTS="fast fast_more", FAST_REPORT="reports/fast_more")
    assert proc.returncode == 0, proc.stderr
    assert [c for c in calls if c[0] == "denoiser-render"] == [["denoiser-render", "dataset=fast"],
                                                               ["denoiser-render", "dataset=fast_more"]]
    trained = [c for c in calls if c[0] == "denoiser-train"]
    assert sorted(_arg(c, "hydra.run.dir") for c in trained) == [f"reports/fast_more/students/runs/more_s{s}"
                                                                 for s in (0, 1, 2)]
    evals = [c for c in calls if c[0] == "denoiser-eval"]
    assert all(_arg(c, "data.extra_roots") == "[data/fast,data/fast_more]" for c in trained + evals[:1])
    assert [_arg(c, "out_dir") for c in evals] == ["reports/fast_more/students/mitsuba_val",
                                                   "reports/fast_more/students/blender_val"]
    table = next(c for c in calls if c[:3] == ["python", "-m", "denoiser.commands.val_table"])
    assert _arg(table, "out") == "reports/fast_more/students/val_table.md"
    assert "Mitsuba val (data/demo/val + data/fast/val + data/fast_more/val)" in _arg(table, "evals")


@pytest.mark.parametrize(("env", "message"), [
    ({"FAST_TEACHERS": "lr-1:model.optimizer.lr=1e-3"}, "FAST_TEACHERS: 'lr-1:model.optimizer.lr=1e-3' is not"),
    ({"FAST_STUDENT_TEACHER": "nope"}, "FAST_STUDENT_TEACHER: 'nope' is not demo or a candidate"),
    ({"FAST_STUDENT_TEACHER": "demo", "FAST_STUDENTS": "base:"}, "FAST_STUDENTS: 'base:' is not"),
])
def test_fast_motion_refuses_bad_knobs_in_one_line(tree, env, message):
    proc, calls = _run(tree, **env)
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and message in proc.stderr
    assert not calls  # before anything runs


def test_fast_motion_needs_make_demo(tmp_path):
    root = stub_pipeline(tmp_path, "fast_motion.sh", ("python", "denoiser-train", "denoiser-eval", "denoiser-render"),
                         STUB)
    proc, calls = _run(root)
    assert proc.returncode == 2 and "run make demo first" in proc.stderr and not calls


LABELS = "labels={lr2e3: 'experiment=demo_teacher data.extra_roots=[data/fast] model.optimizer.lr=2e-3'}"
EVALS = "evals={mitsuba: {title: 'Mitsuba val (data/demo/val + data/fast/val)', csv: reports/mitsuba_val/metrics.csv}}"


def test_the_overrides_of_the_script_compose():
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        teacher = compose("train", overrides=["experiment=demo_teacher", "data.extra_roots=[data/fast]",
                                              "model.scheduler.warmup_steps=200", "model.optimizer.lr=1e-3"])
        ev = compose("eval", overrides=["data=demo", "split=val", "data.extra_roots=[data/fast]",
                                        "~baselines.oidn_balanced", "~baselines.oidn_high"])
        table = compose("val_table", overrides=["reference=lr2e3", "candidates=[lr2e3,lr1e3]", "seeds=[0,1,2]",
                                                "plain_rows=['noisy input',OIDN-fast,demo_teacher]",
                                                LABELS, EVALS])
    assert list(teacher.data.extra_roots) == ["data/fast"] and teacher.model.scheduler.warmup_steps == 200
    assert teacher.model.optimizer.lr == 1e-3
    assert list(ev.data.extra_roots) == ["data/fast"] and list(ev.baselines) == ["noisy", "oidn_fast"]
    assert list(table.evals) == ["mitsuba"] and table.labels.lr2e3.endswith("lr=2e-3")
    assert list(table.plain_rows) == ["noisy input", "OIDN-fast", "demo_teacher"]
