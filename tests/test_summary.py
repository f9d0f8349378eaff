"""The demo's reporting chain: seed groups (mean ± std), the test-split hash, summary.md, the
README copy script; and the demo dataset's split design (every effect in train, an unseen
family in val, test families held out)."""

from __future__ import annotations

import csv
import statistics
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import STUB_HEADER, stub_calls, stub_pipeline
from omegaconf import OmegaConf

from denoiser.conf import CONF_DIR
from denoiser.render.catalog import load_scene_config
from denoiser.render.effects import EFFECTS
from denoiser.report.summary import format_mean_std, method_means, seed_groups, split_seed, tree_hash

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ["method", "scene", "sequence", "frames", "psnr", "ssim", "tpsnr", "flip", "relmse", "smape", "ms_per_frame"]


def eval_rows() -> list[dict]:
    rows = []
    values = {"noisy input": [20.0, 22.0], "OIDN-fast": [30.0, 31.0], "student_s0": [28.0, 29.0],
              "student_s1": [29.0, 30.0], "student_s2": [27.0, 31.0]}
    for method, psnrs in values.items():
        for i, psnr in enumerate(psnrs):
            rows.append({"method": method, "scene": f"s{i}", "sequence": f"test/s{i}_000", "frames": 6, "psnr": psnr,
                         "ssim": 0.9, "tpsnr": psnr - 1, "flip": 0.1, "relmse": 0.01, "smape": 0.05,
                         "ms_per_frame": 1.0})
    return rows


def test_seed_groups_match_a_plain_computation():
    groups = {g["method"]: g for g in seed_groups(method_means(eval_rows()))}
    assert list(groups) == ["noisy input", "OIDN-fast", "student"]
    per_seed = [statistics.mean([28.0, 29.0]), statistics.mean([29.0, 30.0]), statistics.mean([27.0, 31.0])]
    assert groups["student"]["seeds"] == [0, 1, 2]
    assert groups["student"]["psnr"] == pytest.approx(statistics.mean(per_seed))
    assert groups["student"]["psnr_std"] == pytest.approx(statistics.stdev(per_seed))
    assert groups["OIDN-fast"]["seeds"] == [] and groups["OIDN-fast"]["psnr_std"] == 0.0
    assert format_mean_std(groups["student"], "psnr", 2) == f"{statistics.mean(per_seed):.2f} ± {statistics.stdev(per_seed):.2f}"
    assert format_mean_std(groups["OIDN-fast"], "psnr", 2) == "30.50"
    assert split_seed("student_no_kd_s12") == ("student_no_kd", 12)
    assert split_seed("OIDN-fast") == ("OIDN-fast", None)


def test_tree_hash_names_the_exact_files(tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "frame.exr").write_bytes(b"\x00\x01")
    first = tree_hash(tmp_path)
    assert tree_hash(tmp_path) == first
    (tmp_path / "a" / "frame.exr").write_bytes(b"\x00\x02")
    assert tree_hash(tmp_path) != first
    (tmp_path / "a" / "frame.exr").write_bytes(b"\x00\x01")
    (tmp_path / "a" / "frame.exr").rename(tmp_path / "a" / "other.exr")
    assert tree_hash(tmp_path) != first


def test_summary_and_readme_copy(tmp_path):
    report = tmp_path / "report"
    (report / "eval").mkdir(parents=True)
    with open(report / "eval" / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        writer.writerows(eval_rows())
    data = tmp_path / "data"
    (data / "test" / "s0_000").mkdir(parents=True)
    (data / "test" / "s0_000" / "frame_0000.exr").write_bytes(b"x")
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.demo_summary", f"report={report}",
                           f"data_root={data}", "seeds=[0,1,2]"], capture_output=True, text=True, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = (report / "summary.md").read_text()
    assert tree_hash(data / "test") in summary
    student = next(line for line in summary.splitlines() if line.startswith("| student |"))
    assert "29.00 ± 0.50" in student  # per-seed means 28.5, 29.5, 29.0
    readme = tmp_path / "README.md"
    readme.write_text("# x\n\n<!-- results:begin -->\nold table\n<!-- results:end -->\n\ntail\n")
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--summary",
                           str(report / "summary.md"), "--readme", str(readme)], capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    text = readme.read_text()
    assert "old table" not in text and student in text and text.endswith("\n\ntail\n")
    bad = subprocess.run([sys.executable, "-m", "denoiser.commands.demo_summary", f"report={tmp_path / 'none'}"],
                         capture_output=True, text=True, cwd=tmp_path, check=False)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "metrics.csv" in bad.stderr


def test_summary_of_a_recipe_of_fine_tunes_names_their_starts_and_the_interpolation(tmp_path):
    """base_runs (make demo's refine: the runs its networks start from) are listed by path beside the
    report's own runs, and interpolation_alpha says how the students were evaluated; an alpha outside
    [0, 1] is one error line and no summary."""
    report, base = tmp_path / "reports" / "demo_refine", tmp_path / "reports" / "demo" / "runs"
    (report / "eval").mkdir(parents=True)
    with open(report / "eval" / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        writer.writerows(eval_rows())
    for runs in (base, report / "runs"):
        for name in ("teacher" if runs == base else "teacher_tuned", "student_s0"):
            (runs / name / "checkpoints").mkdir(parents=True)
    cmd = [sys.executable, "-m", "denoiser.commands.demo_summary", "report=reports/demo_refine",
           f"data_root={tmp_path}", "base_runs=reports/demo/runs"]
    proc = subprocess.run([*cmd, "interpolation_alpha=0.75"], capture_output=True, text=True, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = (report / "summary.md").read_text()
    runs = [line.split("|")[1].strip() for line in summary.split("## Training runs")[1].splitlines()[4:] if line.startswith("| ")]
    assert runs == ["reports/demo/runs/student_s0", "reports/demo/runs/teacher",
                    "reports/demo_refine/runs/student_s0", "reports/demo_refine/runs/teacher_tuned"]
    header = summary.split("Metrics:")[0]
    assert "- fine-tunes (`reports/demo_refine/runs`) of the runs in `reports/demo/runs`" in header
    assert "(1 - 0.75) x its start in `reports/demo/runs` + 0.75 x its fine-tune" in header
    (report / "summary.md").unlink()
    bad = subprocess.run([*cmd, "interpolation_alpha=1.5"], capture_output=True, text=True, cwd=tmp_path, check=False)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "interpolation_alpha" in bad.stderr
    assert not (report / "summary.md").exists()
    # the default recipe's summary: its own runs by name, no recipe lines
    proc = subprocess.run(cmd[:-1], capture_output=True, text=True, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = (report / "summary.md").read_text()
    assert "fine-tunes" not in summary and "| teacher_tuned |" in summary


def test_summary_adds_the_blender_table_with_gains_when_its_evaluation_exists(tmp_path):
    report = tmp_path / "report"
    for sub, rows in (("eval", eval_rows()), ("blender", eval_rows()[:2] + eval_rows()[4:])):
        (report / sub).mkdir(parents=True)
        with open(report / sub / "metrics.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, FIELDS)
            writer.writeheader()
            writer.writerows(rows)
    cmd = [sys.executable, "-m", "denoiser.commands.demo_summary", f"report={report}", f"data_root={tmp_path}"]
    assert subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False).returncode == 0
    summary = (report / "summary.md").read_text()
    section = summary.split("## Blender Cycles sequences")[1].split("\n## ")[0]
    rows = {line.split("|")[1].strip(): line for line in section.splitlines() if line.startswith("| ")}
    assert "noisy input" in rows and "OIDN-fast" not in rows  # only the methods of its own metrics.csv
    assert "29.00 ± 0.50" in rows["student"] and rows["student"].rstrip(" |").endswith("+8.00")  # 29.0 - 21.0
    assert "PSNR gain dB" in section
    readme = tmp_path / "README.md"
    readme.write_text("x\n<!-- blender:begin -->\nold\n<!-- blender:end -->\n")
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--summary",
                           str(report / "summary.md"), "--readme", str(readme), "--marker", "blender"],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    assert rows["student"] in readme.read_text() and "\nold\n" not in readme.read_text()
    # the test table is unchanged, and no blender evaluation means no section
    assert "| OIDN-fast |" in summary.split("## Blender")[0]
    (report / "blender" / "metrics.csv").unlink()
    assert subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False).returncode == 0
    assert "Blender" not in (report / "summary.md").read_text()


def test_demo_dataset_splits():
    """Every effect appears in train; val has a family train never sees; test families are new."""
    jobs = {job.split: list(job.scenes) for job in OmegaConf.load(Path(CONF_DIR) / "dataset" / "demo.yaml").dataset.jobs}
    train, val, test = set(jobs["train"]), set(jobs["val"]), set(jobs["test"])
    effects = set()
    for scene in train:
        for effect in load_scene_config(scene).effects:
            effects.update([effect] if isinstance(effect, str) else list(effect.keys()))
    assert effects == set(EFFECTS)
    assert val - train, "val needs a scene family that train does not have"
    assert not test & (train | val)
    assert all(load_scene_config(s).test_only for s in test)
    assert set(jobs["unlabeled"]) <= train


# --- scripts/demo.sh with stub commands: the Blender stage ----------------------------------------

DEMO_STUB = STUB_HEADER + """for arg in "$@"; do case "$arg" in
  hydra.run.dir=*) mkdir -p "${arg#hydra.run.dir=}/checkpoints"; touch "${arg#hydra.run.dir=}/checkpoints/last.ckpt";;
  out_dir=*) d="${arg#out_dir=}"; mkdir -p "$d/images"; touch "$d/metrics.md" "$d/report.md";;
  report=*) touch "${arg#report=}/summary.md";;
esac; done
"""


DEMO_COMMANDS = ("python", "denoiser-render", "denoiser-train", "denoiser-eval", "denoiser-bench")


def _demo_env() -> dict[str, str]:
    """The environment demo.sh runs in here: this one's, less the DEMO_ knobs a developer may have set."""
    import os

    return {k: v for k, v in os.environ.items() if not k.startswith("DEMO_")}


def _demo_sh(root: Path, status: int = 0, **env: str) -> list[list[str]]:
    log = root / "calls.log"
    log.unlink(missing_ok=True)
    proc = subprocess.run(["bash", str(root / "scripts" / "demo.sh")], capture_output=True, text=True, check=False,
                          env={**_demo_env(), "VENV": "venv", "STUB_LOG": str(log), "DEMO_SEEDS": "0", **env})
    assert proc.returncode == status, proc.stderr
    return stub_calls(log)


def test_demo_sh_leaves_skipping_and_resuming_to_the_trainer_and_stops_on_a_collapse(tmp_path):
    stub_pipeline(tmp_path, "demo.sh", DEMO_COMMANDS, DEMO_STUB)
    calls = _demo_sh(tmp_path, DEMO_SEEDS="0 1", DEMO_RECIPE="demo")
    trained = {_arg(c, "hydra.run.dir"): c for c in calls if c[0] == "denoiser-train"}
    runs = "reports/demo/runs/"
    assert sorted(trained) == [runs + r for r in ("student_distilled_s0", "student_distilled_s1", "student_no_kd_s0",
                                                   "student_no_kd_s1", "teacher")]
    for run, call in trained.items():
        assert "skip_done=true" in call and "ckpt_path=auto" in call, run
    assert _arg(trained[runs + "teacher"], "experiment") == "demo_teacher"
    assert _arg(trained[runs + "student_no_kd_s1"], "experiment") == "demo"
    distilled = trained[runs + "student_distilled_s1"]
    assert _arg(distilled, "experiment") == "demo_distill" and _arg(distilled, "seed") == "1"
    assert [_arg(c, "dataset") for c in calls if c[0] == "denoiser-render"] == ["demo"]
    assert _arg(distilled, "model.teacher_ckpt") == runs + "teacher/checkpoints/last.ckpt"   # no best.ckpt: last
    timings = (tmp_path / "reports" / "demo" / "timings.md").read_text()
    assert "| teacher |" in timings and "| students |" in timings and "| total |" in timings
    # a run the CollapseDetector stopped ends the demo (exit 3), before any evaluation
    (tmp_path / "reports" / "demo" / "runs" / "student_no_kd_s0" / "COLLAPSED").write_text("collapse at step 90\n")
    calls = _demo_sh(tmp_path, 3, DEMO_SEEDS="0 1", DEMO_RECIPE="demo")
    assert not [c for c in calls if c[0] == "denoiser-eval"]


@pytest.mark.parametrize("recipe,experiments", [
    ("motion", {"teacher": "demo_motion_teacher"}),
    ("tune", {"teacher": "demo_teacher", "teacher_tuned": "demo_motion_tune"}),
])
def test_demo_sh_fast_motion_recipes_train_their_experiments_into_their_own_report(tmp_path, recipe, experiments):
    """DEMO_RECIPE=motion or tune (scripts/lib.sh): their experiments (tune: the demo teacher, then its
    fine-tune, which teaches the students), the datasets they read rendered too, and
    reports/demo_<recipe>, so that reports/demo keeps the default recipe's runs."""
    stub_pipeline(tmp_path, "demo.sh", DEMO_COMMANDS, DEMO_STUB)
    calls = _demo_sh(tmp_path, DEMO_RECIPE=recipe)
    trained = {_arg(c, "hydra.run.dir"): c for c in calls if c[0] == "denoiser-train"}
    runs = f"reports/demo_{recipe}/runs/"
    assert {run: _arg(c, "experiment") for run, c in trained.items()} == {
        **{runs + name: experiment for name, experiment in experiments.items()},
        runs + "student_distilled_s0": "demo_motion_distill", runs + "student_no_kd_s0": "demo_motion"}
    teacher = runs + ("teacher_tuned" if recipe == "tune" else "teacher") + "/checkpoints/last.ckpt"
    assert _arg(trained[runs + "student_distilled_s0"], "model.teacher_ckpt") == teacher
    if recipe == "tune":
        assert _arg(trained[runs + "teacher_tuned"], "model.init_ckpt") == runs + "teacher/checkpoints/last.ckpt"
    assert [_arg(c, "dataset") for c in calls if c[0] == "denoiser-render"] == ["demo", "fast", "fast_more", "vivid"]
    assert not (tmp_path / "reports" / "demo").exists()
    bad = subprocess.run(["bash", str(tmp_path / "scripts" / "demo.sh")], capture_output=True, text=True,
                         check=False, env={"PATH": "/usr/bin:/bin", "VENV": "venv", "DEMO_RECIPE": "fast"})
    assert bad.returncode == 2 and bad.stderr == "error: DEMO_RECIPE=fast: demo, tune, motion or refine\n"


def test_demo_sh_refine_fine_tunes_make_demos_own_runs(tmp_path):
    """DEMO_RECIPE=refine, make demo's recipe when DEMO_RECIPE is unset: the paper recipe's teacher and
    students in reports/demo/runs, the teacher fine-tuned into reports/demo_refine, then each student
    fine-tuned there from its namesake in reports/demo, the distilled ones under the fine-tuned teacher,
    and evaluated interpolated with it at DEMO_REFINE_ALPHA (0.75 unless set; 1: the fine-tunes as they
    are); the summary lists both runs and names the interpolation."""
    stub_pipeline(tmp_path, "demo.sh", DEMO_COMMANDS, DEMO_STUB)
    assert "DEMO_RECIPE" not in _demo_env()
    calls = _demo_sh(tmp_path)   # the default
    trained = {_arg(c, "hydra.run.dir"): c for c in calls if c[0] == "denoiser-train"}
    base, runs = "reports/demo/runs/", "reports/demo_refine/runs/"
    assert {run: _arg(c, "experiment") for run, c in trained.items()} == {
        base + "teacher": "demo_teacher", base + "student_distilled_s0": "demo_distill", base + "student_no_kd_s0": "demo",
        runs + "teacher_tuned": "demo_motion_tune", runs + "student_distilled_s0": "demo_motion_distill_tune",
        runs + "student_no_kd_s0": "demo_motion_nokd_tune"}
    assert _arg(trained[base + "student_distilled_s0"], "model.teacher_ckpt") == base + "teacher/checkpoints/last.ckpt"
    assert _arg(trained[runs + "teacher_tuned"], "model.init_ckpt") == base + "teacher/checkpoints/last.ckpt"
    refined = trained[runs + "student_distilled_s0"]
    assert _arg(refined, "model.init_ckpt") == base + "student_distilled_s0/checkpoints/last.ckpt"
    assert _arg(refined, "model.teacher_ckpt") == runs + "teacher_tuned/checkpoints/last.ckpt"
    no_kd = trained[runs + "student_no_kd_s0"]
    assert _arg(no_kd, "model.init_ckpt") == base + "student_no_kd_s0/checkpoints/last.ckpt"
    assert not any(a.startswith("model.teacher_ckpt=") for a in no_kd)
    assert [_arg(c, "dataset") for c in calls if c[0] == "denoiser-render"] == ["demo", "fast", "fast_more", "vivid"]
    evaluated = next(c for c in calls if c[0] == "denoiser-eval")  # at the recipe's alpha, chosen on val
    assert runs + "student_distilled_s0/checkpoints/interpolated_a0.75.ckpt" in _arg(evaluated, "ckpt")
    assert "| refine |" in (tmp_path / "reports" / "demo_refine" / "timings.md").read_text()
    summary = next(c for c in calls if c[:3] == ["python", "-m", "denoiser.commands.demo_summary"])
    assert _arg(summary, "report") == "reports/demo_refine" and _arg(summary, "base_runs") == "reports/demo/runs"
    assert _arg(summary, "interpolation_alpha") == "0.75"
    calls = _demo_sh(tmp_path, DEMO_RECIPE="refine", DEMO_REFINE_ALPHA="1")  # the fine-tunes as they are
    evaluated = next(c for c in calls if c[0] == "denoiser-eval")
    assert runs + "student_distilled_s0/checkpoints/last.ckpt" in _arg(evaluated, "ckpt")
    assert not [c for c in calls if c[:3] == ["python", "-m", "denoiser.commands.interpolate"]]


def test_demo_sh_refine_alpha_evaluates_each_student_interpolated_with_its_start(tmp_path):
    """DEMO_REFINE_ALPHA=0.5 with DEMO_RECIPE=refine: each student's fine-tune interpolated with make
    demo's namesake (python -m denoiser.commands.interpolate), and that checkpoint evaluated and timed;
    with another recipe, or outside [0, 1], one error line before anything runs."""
    stub_pipeline(tmp_path, "demo.sh", DEMO_COMMANDS, DEMO_STUB)
    calls = _demo_sh(tmp_path, DEMO_RECIPE="refine", DEMO_REFINE_ALPHA="0.5")
    base, runs = "reports/demo/runs/", "reports/demo_refine/runs/"
    mixed = {_arg(c, "out"): c for c in calls if c[:3] == ["python", "-m", "denoiser.commands.interpolate"]}
    out = runs + "student_distilled_s0/checkpoints/interpolated_a0.5.ckpt"
    assert sorted(mixed) == [out, runs + "student_no_kd_s0/checkpoints/interpolated_a0.5.ckpt"]
    assert _arg(mixed[out], "start") == base + "student_distilled_s0/checkpoints/last.ckpt"
    assert _arg(mixed[out], "end") == runs + "student_distilled_s0/checkpoints/last.ckpt"
    assert _arg(mixed[out], "alpha") == "0.5"
    first_eval = next(i for i, c in enumerate(calls) if c[0] == "denoiser-eval")
    assert max(i for i, c in enumerate(calls) if c in mixed.values()) < first_eval
    assert f"student_distilled_s0: {out}" in _arg(calls[first_eval], "ckpt")
    assert out in _arg(next(c for c in calls if c[0] == "denoiser-bench"), "ckpt")
    assert "| interpolate |" in (tmp_path / "reports" / "demo_refine" / "timings.md").read_text()
    for env in ({"DEMO_RECIPE": "demo", "DEMO_REFINE_ALPHA": "0.5"}, {"DEMO_REFINE_ALPHA": "1.5"}):
        bad = subprocess.run(["bash", str(tmp_path / "scripts" / "demo.sh")], capture_output=True, text=True,
                             check=False, env={"PATH": "/usr/bin:/bin", "VENV": "venv", **env})
        assert bad.returncode == 2 and bad.stderr.count("\n") == 1, bad.stderr
        assert bad.stderr.startswith(f"error: DEMO_REFINE_ALPHA={env['DEMO_REFINE_ALPHA']}: a number in [0, 1]")
    assert not (tmp_path / "reports" / "demo" / "timings.md.tmp").exists()


def _arg(call: list[str], key: str) -> str:
    return next(a.split("=", 1)[1] for a in call if a.startswith(f"{key}="))


def test_demo_sh_evaluates_its_networks_on_the_blender_sequences_when_they_exist(tmp_path):
    stub_pipeline(tmp_path, "demo.sh", DEMO_COMMANDS, DEMO_STUB)

    def evals(calls):
        return {next(a for a in c if a.startswith("out_dir=")): c for c in calls if c[0] == "denoiser-eval"}

    assert list(evals(_demo_sh(tmp_path, DEMO_RECIPE="demo"))) == ["out_dir=reports/demo/eval"]  # no sequences: no stage
    (tmp_path / "data" / "blender" / "test").mkdir(parents=True)
    (tmp_path / "reports" / "demo" / "blender").mkdir(parents=True)
    calls = evals(_demo_sh(tmp_path, DEMO_RECIPE="demo"))
    test, blender = calls["out_dir=reports/demo/eval"], calls["out_dir=reports/demo/blender"]
    assert "layout=blender" in blender and "data.root=data/blender" in blender
    ckpt = [a for a in blender if a.startswith("ckpt=")]
    assert ckpt == [a for a in test if a.startswith("ckpt=")] and "student_distilled_s0" in ckpt[0]
    assert list(evals(_demo_sh(tmp_path, DEMO_BLENDER="", DEMO_RECIPE="demo"))) == ["out_dir=reports/demo/eval"]
    assert not (tmp_path / "reports" / "demo" / "blender").exists()  # no stale table once it is off


def test_blender_block_holds_the_claims_per_family_in_frames_2_plus(tmp_path):
    """extra_family_metric (psnr_f2): inside the Blender block, each claim's paired difference per
    family (the fast-moving objects apart from the camera orbit: the Blender layout's scenes fast_201,
    fast_202 are one family, fast), checked against a hand computation; a family of one sequence gets
    its difference alone, no interval."""
    report = tmp_path / "report"
    f2 = {"OIDN-fast": [30.0, 31.0, 33.0], "student_distilled_s0": [31.0, 31.5, 32.0],
          "student_distilled_s1": [31.2, 31.9, 32.4], "student_distilled_s2": [30.8, 31.6, 32.2],
          "noisy input": [25.0, 26.0, 27.0]}
    rows = [{"method": m, "scene": scene, "sequence": f"test/{seq}", "frames": 8, "psnr": v, "psnr_f2": v,
             "ssim": 0.9, "tpsnr": v, "flip": 0.1, "relmse": 0.01, "smape": 0.05, "ms_per_frame": 1.0}
            for m, vs in f2.items() for (scene, seq), v in zip([("fast_201", "fast_201"), ("fast_202", "fast_202"),
                                                                ("orbit", "orbit")], vs)]
    for sub in ("eval", "blender"):
        (report / sub).mkdir(parents=True)
        with open(report / sub / "metrics.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, [*FIELDS, "psnr_f2"])
            writer.writeheader()
            writer.writerows(rows)
    cmd = [sys.executable, "-m", "denoiser.commands.demo_summary", f"report={report}", f"data_root={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    block = (report / "summary.md").read_text().split("<!-- blender:begin -->")[1].split("<!-- blender:end -->")[0]
    assert "\n\nPer family: PSNR dB frames 2+" in block   # a paragraph of its own, not the last claim's
    family = {line.split("|")[1].strip(): line.split("|") for line in block.split("Per family")[1].splitlines()
              if line.startswith("| ")}
    # fast: seeds averaged per sequence (31.0, 31.67) minus OIDN-fast (30.0, 31.0): +1.00 and +0.67
    assert family["fast"][2].strip() == "2" and family["fast"][3].strip().startswith("+0.83 [+0.67, +1.00]")
    assert family["orbit"][2].strip() == "1" and family["orbit"][3].strip() == "-0.80 (one sequence)"   # 32.2 - 33.0
    off = subprocess.run([*cmd, "extra_family_metric=null"], capture_output=True, text=True, cwd=tmp_path, check=False)
    assert off.returncode == 0 and "Per family" not in (report / "summary.md").read_text().split("<!-- blender:begin -->")[1]
