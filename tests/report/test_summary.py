"""The demo's reporting chain: seed groups (mean ± std), the test-split hash, summary.md, the
README copy script; and the demo dataset's split design (every effect in train, an unseen
family in val, test families held out)."""

from __future__ import annotations

import csv
import json
import statistics
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from denoiser.conf import CONF_DIR
from denoiser.render.catalog import load_scene_config
from denoiser.render.effects import EFFECTS
from denoiser.report.provenance import tree_hash
from denoiser.report.seed_groups import format_mean_std, method_means, seed_groups, split_seed

ROOT = Path(__file__).resolve().parents[2]
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
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={report}",
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
    bad = subprocess.run([sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={tmp_path / 'none'}"],
                         capture_output=True, text=True, cwd=tmp_path, check=False)
    assert bad.returncode == 2 and bad.stderr.count("\n") == 1 and "metrics.csv" in bad.stderr


def test_summary_names_the_evaluations_commit_and_the_looks_of_its_split(tmp_path):
    """The summary's commit is the one its evaluation ran at (eval/evaluation.json, which
    denoiser-eval writes; tests/commands/test_eval.py), and readme_results/readme_check read that commit; each
    block opens with the ledger's looks of its split: how many now, and which one this evaluation
    was. An evaluation without evaluation.json (older than it): the summary's own commit, said so,
    and its looks not recorded."""
    import json
    import re

    from denoiser.report import ledger

    report, book = tmp_path / "report", tmp_path / "ledger.csv"
    for sub in ("eval", "blender"):
        (report / sub).mkdir(parents=True)
        with open(report / sub / "metrics.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, FIELDS)
            writer.writeheader()
            writer.writerows(eval_rows())
    digest = "ab12" * 16
    for _ in range(3):  # three looks at the split; the evaluation summarised was the second
        ledger.record("data/demo", "test", digest, 2, ["student_s0"], ["OIDN-fast"], "0123abc", "report", book)
    told = ledger.provenance("4567def-dirty", "2026-01-02T03:04:05Z", "data/demo", "test", digest, 2, 2, book)
    (report / "eval" / "evaluation.json").write_text(json.dumps(told))
    cmd = [sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={report}", f"data_root={tmp_path}",
           f"ledger={book}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = (report / "summary.md").read_text()
    assert "\n- commit: 4567def-dirty (the evaluation's)\n" in summary
    block = summary.split("<!-- results:begin -->\n")[1].split("<!-- results:end -->")[0]
    assert block.startswith(f"Test ledger: this test split (SHA-256 {digest[:12]}) has been evaluated 3 times "
                            f"({book}); this summary's evaluation is look 2; a split looked at more than once is "
                            "no longer unseen.\n\n| method |")
    blender = summary.split("<!-- blender:begin -->\n")[1]
    assert blender.startswith("Test ledger: looks not recorded (evaluated before the ledger")
    readme = tmp_path / "README.md"
    readme.write_text("<!-- results:pending -->\n")
    subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--summary", str(report / "summary.md"),
                    "--readme", str(readme)], capture_output=True, text=True, check=True)
    copied = readme.read_text()
    assert "has been evaluated 3 times" in copied  # the block says it too
    sys.path.insert(0, str(ROOT / "scripts"))
    try:
        from readme_check import COPIED_COMMIT
    finally:
        sys.path.remove(str(ROOT / "scripts"))
    assert COPIED_COMMIT.search(copied)["commit"] == "4567def"
    # an evaluation older than evaluation.json
    (report / "eval" / "evaluation.json").unlink()
    assert subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False).returncode == 0
    summary = (report / "summary.md").read_text()
    assert re.search(r"^- commit: \S+ \(the summary's: the evaluation wrote no evaluation.json\)$", summary, re.MULTILINE)
    assert "<!-- results:begin -->\nTest ledger: looks not recorded (evaluated before the ledger" in summary


def demo_report(tmp_path: Path) -> Path:
    """``<tmp_path>/reports/demo`` holding an evaluation's metrics.csv (:func:`eval_rows`)."""
    report = tmp_path / "reports" / "demo"
    (report / "eval").mkdir(parents=True)
    with open(report / "eval" / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        writer.writerows(eval_rows())
    return report


def test_summary_lists_the_reports_own_runs_by_name(tmp_path):
    """The training table holds one row per run directory of <report>/runs (those with checkpoints/),
    by name, sorted; the header has no lines beyond the run id, commit, seeds and test split."""
    report = demo_report(tmp_path)
    for name in ("teacher", "student_s0"):
        (report / "runs" / name / "checkpoints").mkdir(parents=True)
    (report / "runs" / "notes").mkdir()  # no checkpoints/: not a run
    cmd = [sys.executable, "-m", "denoiser.commands.tools.eval_summary", "report=reports/demo", f"data_root={tmp_path}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = (report / "summary.md").read_text()
    runs = [line.split("|")[1].strip() for line in summary.split("## Training runs")[1].splitlines()[4:] if line.startswith("| ")]
    assert runs == ["student_s0", "teacher"]
    header = [line for line in summary.split("Metrics:")[0].splitlines() if line.startswith("- ")]
    assert [line.split(":")[0] for line in header] == ["- run id", "- commit", "- seeds (students)", "- test split"]


def test_results_block_states_the_pipelines_stage_times(tmp_path):
    """make demo's 45-minute budget is shown where the README copies from: the results block ends with
    the stage-time table's seconds and their sum, from timings.md.tmp while the pipeline still runs
    (the summary is one of its stages), else timings.md; no line without a table."""
    report = demo_report(tmp_path)
    cmd = [sys.executable, "-m", "denoiser.commands.tools.eval_summary", "report=reports/demo", f"data_root={tmp_path}"]

    def block():
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, check=False)
        assert proc.returncode == 0, proc.stderr
        text = (report / "summary.md").read_text()
        return text.split("<!-- results:begin -->")[1].split("<!-- results:end -->")[0]

    assert "Stage times" not in block()
    (report / "timings.md").write_text("| stage | seconds | run |\n|---|---:|---|\n| render | 700 | run A |\n"
                                       "| teacher | 400 | run B |\n| total | 1100 | run B: wall time |\n"
                                       "| work | 1100 | every stage's seconds |\n")
    assert "Stage times of the pipeline that made this report: 1100 s (18.3 min) in all, render 700, teacher 400" \
        in block()
    (report / "timings.md.tmp").write_text("| stage | seconds | run |\n|---|---:|---|\n| render | 5 | run C |\n")
    assert ": 5 s (0.1 min) in all, render 5 (seconds" in block()
    (report / "bench").mkdir()
    (report / "bench" / "bench.json").write_text(json.dumps({"machine": {"cpu": "AMD EPYC", "logical_cores": 2,
                                                                          "cpu_id": "AuthenticAMD family 25 model 17"}}))
    assert "timings.md`), on AMD EPYC (AuthenticAMD family 25 model 17), 2 logical cores." in block()


def test_summary_adds_the_blender_table_with_gains_when_its_evaluation_exists(tmp_path):
    report = tmp_path / "report"
    for sub, rows in (("eval", eval_rows()), ("blender", eval_rows()[:2] + eval_rows()[4:])):
        (report / sub).mkdir(parents=True)
        with open(report / sub / "metrics.csv", "w", newline="") as f:
            writer = csv.DictWriter(f, FIELDS)
            writer.writeheader()
            writer.writerows(rows)
    cmd = [sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={report}", f"data_root={tmp_path}"]
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
    jobs = {job.split: list(job.scenes) for job in OmegaConf.load(Path(CONF_DIR) / "render_set" / "demo.yaml").render_set.jobs}
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
    cmd = [sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={report}", f"data_root={tmp_path}"]
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


def test_the_ledger_rows_a_run_appends_do_not_make_its_commit_dirty(tmp_path, monkeypatch):
    """make demo's evaluation appends to the committed ledger, then its bench records the commit: that
    is the same code (not "-dirty"); a change to any other tracked file still is."""
    import subprocess

    from denoiser.report.provenance import git_commit

    def git(*args):
        subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "docs" / "results").mkdir(parents=True)
    (tmp_path / "docs" / "results" / "test_ledger.csv").write_text("date\n")
    (tmp_path / "code.py").write_text("x = 1\n")
    git("add", ".")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "c")
    (tmp_path / "docs").joinpath("results", "test_ledger.csv").write_text("date\n2026\n")
    monkeypatch.chdir(tmp_path / "docs")        # from a subfolder too: the paths are the checkout's
    clean = git_commit()
    assert clean and not clean.endswith("-dirty") and clean != "unknown"
    (tmp_path / "code.py").write_text("x = 2\n")
    assert git_commit() == clean + "-dirty"


def test_summary_checks_the_warp_error_against_tpsnr_per_sequence(tmp_path):
    """Issue 64: make demo's summary says in how many test sequences the warp error (no reference)
    orders noisy input, OIDN-fast and the student (its seeds' mean) as tPSNR does."""
    report = tmp_path / "report"
    (report / "eval").mkdir(parents=True)
    # per sequence (tpsnr, warp): noisy worst, then OIDN-fast, then the student, on both measures but in
    # test/s3 (the warp error puts OIDN-fast ahead of the student there) and ...
    table = {"noisy input": [(20, 9.0)] * 5, "OIDN-fast": [(30, 5.0)] * 5,
             "student_distilled_s0": [(32, 3.0), (32, 3.0), (32, 3.0), (32, 6.0), (32, 7.0)],
             "student_distilled_s1": [(32, 3.0), (32, 3.0), (32, 3.0), (32, 6.0), (32, 1.0)]}
    # ... test/s4, where seed 0 alone would disagree but the seeds' mean (4.0) agrees
    rows = [{"method": m, "scene": f"s{i}", "sequence": f"test/s{i}", "frames": 6, "psnr": t + 1, "ssim": 0.9,
             "tpsnr": t, "warp": w, "flip": 0.1, "relmse": 0.01, "smape": 0.05, "ms_per_frame": 1.0}
            for m, cells in table.items() for i, (t, w) in enumerate(cells)]
    with open(report / "eval" / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, [*FIELDS, "warp"])
        writer.writeheader()
        writer.writerows(rows)
    proc = subprocess.run([sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={report}",
                           f"data_root={tmp_path / 'data'}", "seeds=[0,1]"], capture_output=True, text=True,
                          cwd=tmp_path, check=False)
    assert proc.returncode == 0, proc.stderr
    summary = (report / "summary.md").read_text()
    section = summary.split("## The warp error against tPSNR", 1)[1].split("\n## ", 1)[0]
    assert "**80%** of 5 sequences (meets the 80% goal)" in section, section
    assert "differ: `test/s3`." in section, section
    assert "Spearman's rank correlation" in section and "bootstrap interval" in section
    off = subprocess.run([sys.executable, "-m", "denoiser.commands.tools.eval_summary", f"report={report}",
                          f"data_root={tmp_path / 'data'}", "seeds=[0,1]", "flicker_check.goal=0.9"],
                         capture_output=True, text=True, cwd=tmp_path, check=False)
    assert off.returncode == 0, off.stderr
    assert "(misses the 90% goal)" in (report / "summary.md").read_text()
