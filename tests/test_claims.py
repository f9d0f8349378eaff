"""Claims with intervals: the paired bootstrap (against a hand loop), the summary's verdicts from
synthetic metrics.csv files, the frames-2+ PSNR, merged identical rows, and the README's
staleness check (scripts/readme_check.py) in a throwaway git repository."""

from __future__ import annotations

import csv
import math
import statistics
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from denoiser.metrics import COLUMNS, METRICS, MetricAccumulator, psnr
from denoiser.report.stats import paired_interval
from denoiser.report.summary import (
    group_sequences,
    group_timing,
    merge_identical,
    method_means,
    seed_groups,
    sequence_values,
)

ROOT = Path(__file__).resolve().parents[1]


# --- denoiser.report.stats -------------------------------------------------------------------------------


def hand_bootstrap(a, b, confidence, resamples, seed):
    """A plain loop: draw n indices one at a time, average, sort, interpolate the quantiles."""
    diff = [x - y for x, y in zip(a, b)]
    n = len(diff)
    rng = np.random.default_rng(seed)
    means = sorted(sum(diff[int(rng.integers(0, n))] for _ in range(n)) / n for _ in range(resamples))

    def quantile(q):
        pos = q * (resamples - 1)
        low = math.floor(pos)
        return means[low] + (pos - low) * (means[min(low + 1, resamples - 1)] - means[low])

    return statistics.fmean(diff), quantile((1 - confidence) / 2), quantile((1 + confidence) / 2)


def test_paired_interval_matches_a_hand_loop_bootstrap():
    rng = np.random.default_rng(5)
    a, b = rng.normal(30, 2, 13).tolist(), rng.normal(29.5, 2, 13).tolist()
    got = paired_interval(a, b, confidence=0.9, resamples=500, seed=11)
    mean, lo, hi = hand_bootstrap(a, b, 0.9, 500, 11)
    assert got.n == 13 and got.confidence == 0.9
    assert got.mean == pytest.approx(mean, abs=1e-12)
    assert (got.lo, got.hi) == (pytest.approx(lo, abs=1e-12), pytest.approx(hi, abs=1e-12))
    assert got.half_width == pytest.approx((hi - lo) / 2, abs=1e-12) and lo < mean < hi
    assert paired_interval(a, b, seed=1) == paired_interval(a, b, seed=1)  # a fixed seed: the same numbers


def test_paired_interval_known_cases_and_verdicts():
    same = paired_interval([30.0, 31.5, 29.25], [30.0, 31.5, 29.25])
    assert (same.mean, same.lo, same.hi, same.half_width) == (0.0, 0.0, 0.0, 0.0)
    assert same.verdict() == "tied"
    shift = paired_interval([30.5, 32.0, 29.75], [30.0, 31.5, 29.25])
    assert (shift.mean, shift.lo, shift.hi) == (0.5, 0.5, 0.5) and shift.verdict() == "ahead"
    assert shift.verdict(lower_is_better=True) == "behind"  # +0.5 of an error is worse
    mixed = paired_interval([1.0, -1.0, 2.0, -2.0], [0.0] * 4)
    assert mixed.lo < 0 < mixed.hi and mixed.verdict() == "tied" == mixed.verdict(lower_is_better=True)
    with pytest.raises(ValueError, match="equal-length"):
        paired_interval([1.0, 2.0], [1.0])


# --- frames 2+ ------------------------------------------------------------------------------------


def test_frame_2_plus_psnr_skips_only_the_first_frame():
    """Frame 1 (index 0) is far worse than the rest: psnr_f2 averages frames 2-4 and psnr_all frames
    1-4, whatever the warm-up."""
    torch.manual_seed(0)
    ref = torch.rand(4, 3, 8, 8)
    noise = torch.tensor([0.5, 0.02, 0.05, 0.03])[:, None, None, None]
    out = ref + noise * torch.randn(4, 3, 8, 8)
    per_frame = [float(psnr(out[t:t + 1], ref[t:t + 1])[0]) for t in range(4)]
    for warmup, kept in ((0, [0, 1, 2, 3]), (2, [2, 3])):
        acc = MetricAccumulator(["psnr", "ssim"], warmup=warmup)
        for t in range(4):  # frame by frame, as denoiser-eval feeds it
            acc.update(out[t:t + 1], ref[t:t + 1], "seq", frame_index=[t], reset=[t == 0])
        values = acc.per_sequence()["seq"]
        assert values["psnr_f2"] == pytest.approx(statistics.fmean(per_frame[1:]), rel=1e-6)
        assert values["psnr_all"] == pytest.approx(statistics.fmean(per_frame), rel=1e-6)
        assert values["psnr"] == pytest.approx(statistics.fmean(per_frame[t] for t in kept), rel=1e-6)
        assert acc.columns == ["psnr", "ssim", "psnr_all", "psnr_f2"] and acc.compute(subsets=True)["psnr_f2"] == values["psnr_f2"]
        assert "psnr_f2" not in acc.compute()  # what validation logs and DDP combines: the metrics
    assert MetricAccumulator(["ssim"]).columns == ["ssim"]  # no PSNR, no PSNR frames 2+
    assert COLUMNS["psnr_all"].header == "PSNR dB all frames ↑"
    assert COLUMNS["psnr_f2"].header == "PSNR dB frames 2+ ↑" and COLUMNS["psnr_f2"].digits == METRICS["psnr"].digits


# --- the summary ----------------------------------------------------------------------------------

FAMILIES = ["gallery", "blur_spin", "atrium", "plaza", "workshop", "library", "kitchen"]
FIELDS = ["method", "scene", "sequence", "frames", "psnr", "psnr_f2", "ssim", "tpsnr", "flip", "relmse", "smape",
          "ms_per_frame"]


def synthetic_rows() -> list[dict]:
    """7 families x 6 sequences. Distilled: +0.5 dB over OIDN-fast (+-0.2 noise); no-KD: the
    distilled student's value, its mean 0.05 dB lower, scattered by +-1.5 dB (tied); teacher:
    0.4 dB below OIDN-fast everywhere; OIDN-balanced and OIDN-high the same numbers. Frames 2+:
    the distilled student 0.3 dB below OIDN-fast (its first frame is what helps it)."""
    rng = np.random.default_rng(0)
    rows = []
    scatter = rng.normal(0, 1.5, 42)
    scatter -= scatter.mean() - 0.05
    for i in range(42):
        family, seq = FAMILIES[i // 6], f"test/{FAMILIES[i // 6]}_{i % 6:03d}"
        base = 25 + rng.normal(0, 2)
        seeds = base + 0.5 + rng.normal(0, 0.2, 3)
        values = {"OIDN-fast": (base, base), "OIDN-balanced": (base + 0.3, base + 0.3),
                  "OIDN-high": (base + 0.3, base + 0.3), "teacher": (base - 0.4, base - 0.4)}
        values.update({f"student_distilled_s{k}": (seeds[k], base - 0.3) for k in range(3)})
        values.update({f"student_no_kd_s{k}": (seeds.mean() - scatter[i], base) for k in range(3)})
        for method, (p, p2) in values.items():
            rows.append({"method": method, "scene": family, "sequence": seq, "frames": 6, "psnr": p, "psnr_f2": p2,
                         "ssim": 0.9, "tpsnr": p - 1, "flip": 0.1, "relmse": 0.01, "smape": 0.05,
                         "ms_per_frame": 1.0})
    for method in dict.fromkeys(r["method"] for r in rows):  # denoiser-eval's mean rows
        rows.append({"method": method, "scene": "mean", "sequence": "mean", "frames": 252, "psnr": 99.0})
    return rows


def write_metrics(path: Path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, FIELDS)
        writer.writeheader()
        writer.writerows(rows)


def test_merge_identical_rows_from_the_data_and_the_mean_rows_ignored():
    rows = synthetic_rows()
    per_sequence = group_sequences(sequence_values(rows))
    merged = merge_identical(seed_groups(method_means(rows)), per_sequence)
    names = [g["method"] for g in merged]
    assert names == ["OIDN-fast", "OIDN-balanced = OIDN-high", "teacher", "student_distilled", "student_no_kd"]
    assert merged[1]["members"] == ["OIDN-balanced", "OIDN-high"]
    assert group_timing(merged[1], {"OIDN-balanced": {"ms_median": 7}}) == {"ms_median": 7}
    fast = [r["psnr"] for r in rows if r["method"] == "OIDN-fast" and r["sequence"] != "mean"]
    assert merged[0]["psnr"] == pytest.approx(statistics.fmean(fast))  # the 99.0 mean row is not a sequence
    rows[next(i for i, r in enumerate(rows) if r["method"] == "OIDN-high")]["psnr"] += 1e-6  # one cell differs
    per_sequence = group_sequences(sequence_values(rows))
    assert len(merge_identical(seed_groups(method_means(rows)), per_sequence)) == 6


def test_summary_claims_come_from_the_paired_intervals(tmp_path):
    from denoiser.commands.demo_summary import run
    from denoiser.configs import compose_config

    rows = synthetic_rows()
    report = tmp_path / "report"
    write_metrics(report / "eval" / "metrics.csv", rows)
    run(compose_config([f"report={report}", f"data_root={tmp_path}", "extra_evals={}"], "demo_summary"))
    summary = (report / "summary.md").read_text()
    block = summary.split("<!-- results:begin -->")[1].split("<!-- results:end -->")[0]

    # the reference: per sequence, the seeds' mean by hand, minus OIDN-fast's; the same bootstrap
    by = {(r["method"], r["sequence"]): r for r in rows if r["sequence"] != "mean"}
    seqs = sorted({r["sequence"] for r in rows if r["sequence"] != "mean"}, key=[r["sequence"] for r in rows].index)

    def seed_mean(group, seq, column):
        return statistics.fmean(by[(f"{group}_s{k}", seq)][column] for k in range(3))

    head = paired_interval([seed_mean("student_distilled", q, "psnr") for q in seqs],
                           [by[("OIDN-fast", q)]["psnr"] for q in seqs])
    assert head.lo > 0
    assert (f"- student_distilled is ahead of OIDN-fast on PSNR dB: {head.mean:+.2f} [{head.lo:+.2f}, "
            f"{head.hi:+.2f}] (± {head.half_width:.2f}, 42 sequences).") in block
    assert "- student_distilled is behind OIDN-fast on PSNR dB frames 2+: -0.30 [-0.30, -0.30]" in block
    # the headline's tPSNR (temporal stability) with its paired interval: here tPSNR = PSNR - 1 for every method
    tpsnr = paired_interval([seed_mean("student_distilled", q, "tpsnr") for q in seqs],
                            [by[("OIDN-fast", q)]["tpsnr"] for q in seqs])
    assert (f"- student_distilled is ahead of OIDN-fast on tPSNR dB: {tpsnr.mean:+.2f} [{tpsnr.lo:+.2f}, "
            f"{tpsnr.hi:+.2f}] (± {tpsnr.half_width:.2f}, 42 sequences).") in block
    assert "| student_distilled | OIDN-fast | tPSNR dB ↑ |" in block
    no_kd = paired_interval([seed_mean("student_distilled", q, "psnr") for q in seqs],
                            [seed_mean("student_no_kd", q, "psnr") for q in seqs])
    assert no_kd.mean > 0 and no_kd.lo < 0  # the means favour distillation; the interval does not
    assert "- student_distilled is tied with student_no_kd on PSNR dB: +0.05 [" in block
    assert "- teacher is behind OIDN-fast on PSNR dB: -0.40 [-0.40, -0.40] (± 0.00, 42 sequences)." in block
    assert "| OIDN-balanced = OIDN-high |" in block and "| OIDN-high |" not in block
    assert "| PSNR dB ↑ | PSNR dB all frames ↑ | PSNR dB frames 2+ ↑ |" in next(line for line in block.splitlines() if line.startswith("| method"))
    family = summary.split("Per family")[1].split("\n## ")[0]
    table = [line for line in family.splitlines() if line.startswith("| ") and "family" not in line]
    assert [line.split("|")[1].strip() for line in table] == FAMILIES
    assert all("| 6 |" in line and line.count("[") == 3 for line in table)


def test_an_extra_table_turned_off_in_a_composed_config_is_not_written(tmp_path):
    """``extra_evals`` entries are tables ``{dir: title}``; a null title (a config composed on
    demo_summary's turning off its ``blender`` entry, conf/recipe_check_summary.yaml) writes no table
    even where its metrics.csv exists."""
    from denoiser.commands.demo_summary import run
    from denoiser.configs import compose_config

    report = tmp_path / "report"
    for folder in ("eval", "blender", "cycles"):
        write_metrics(report / folder / "metrics.csv", synthetic_rows())
    run(compose_config([f"report={report}", f"data_root={tmp_path}", "extra_evals.blender=null", "+extra_evals.cycles=Cycles"],
                       "demo_summary"))
    summary = (report / "summary.md").read_text()
    assert "<!-- cycles:begin -->" in summary and "## Cycles" in summary
    assert "<!-- blender:begin -->" not in summary


# --- README provenance and staleness --------------------------------------------------------------

README = """# x

<!-- results:begin -->
<!-- copied by scripts/readme_results.py from reports/demo/summary.md, run id 2026-01-01T00:00:00Z, commit {commit} -->
| a | b |
<!-- results:end -->

<!-- pareto:pending -->
pending
"""


def git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-C", str(repo), *args], capture_output=True, text=True, check=True,
                          env={"GIT_AUTHOR_NAME": "t", "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t",
                               "GIT_COMMITTER_EMAIL": "t@t", "PATH": "/usr/bin:/bin"}).stdout.strip()


def readme_check(repo: Path, **env: str) -> subprocess.CompletedProcess:
    import os

    return subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_check.py"), "--readme",
                           str(repo / "README.md")], capture_output=True, text=True, check=False,
                          env={**os.environ, **env}, timeout=600)


def test_readme_check_fails_on_a_block_older_than_the_measured_code(tmp_path):
    repo = tmp_path / "repo"
    (repo / "denoiser" / "nn").mkdir(parents=True)
    git(repo, "init", "-q")
    (repo / "denoiser" / "nn" / "unet.py").write_text("width = 16\n")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "first")
    old = git(repo, "rev-parse", "--short", "HEAD")
    (repo / "denoiser" / "nn" / "unet.py").write_text("width = 32\n")  # the measured network changes
    git(repo, "commit", "-qam", "wider")
    new = git(repo, "rev-parse", "--short", "HEAD")
    (repo / "docs.md").write_text("words\n")  # a later commit that measures nothing
    git(repo, "add", "docs.md")
    git(repo, "commit", "-qm", "docs")

    (repo / "README.md").write_text(README.format(commit=old))
    proc = readme_check(repo)
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1
    assert "block 'results'" in proc.stderr and f"commit {old}" in proc.stderr and "denoiser/nn/unet.py" in proc.stderr
    (repo / "README.md").write_text(README.format(commit=new + "-dirty"))
    assert readme_check(repo).returncode == 0  # at the change (or after it): current
    (repo / "README.md").write_text(README.format(commit=git(repo, "rev-parse", "HEAD")))
    assert readme_check(repo).returncode == 0
    (repo / "README.md").write_text(README.replace(", commit {commit}", ""))
    proc = readme_check(repo)
    assert proc.returncode == 1 and "names no commit" in proc.stderr
    (repo / "README.md").write_text(README.format(commit="abcdef1"))
    assert "does not have" in readme_check(repo).stderr

    # a move with identical content (the configs to the top level) measures the same thing ...
    (repo / "denoiser" / "conf" / "net").mkdir(parents=True)
    (repo / "denoiser" / "conf" / "net" / "student.yaml").write_text("width: 32\n")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "net config")
    at = git(repo, "rev-parse", "HEAD")
    (repo / "conf").mkdir()
    git(repo, "mv", "denoiser/conf/net", "conf/net")
    git(repo, "commit", "-qm", "conf at the top level")
    (repo / "README.md").write_text(README.format(commit=at))
    assert readme_check(repo).returncode == 0
    # ... and so do a comment, a docstring and a YAML comment ...
    (repo / "denoiser" / "nn" / "unet.py").write_text('"""The U-Net."""\nwidth = 32  # channels\n')
    (repo / "conf" / "net" / "student.yaml").write_text("# the student\nwidth: 32   # channels\n")
    git(repo, "commit", "-qam", "words only")
    assert readme_check(repo).returncode == 0
    # ... and a new option of a config group (composed only when selected by name) ...
    (repo / "conf" / "net" / "wide.yaml").write_text("width: 64\n")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "another net option")
    assert readme_check(repo).returncode == 0
    # ... but deleting one does not (a composition may have selected it) ...
    git(repo, "rm", "-q", "conf/net/wide.yaml")
    git(repo, "commit", "-qm", "net option removed")
    assert readme_check(repo).returncode == 0  # it was added after the block's commit: nothing measured it
    (repo / "README.md").write_text(README.format(commit=git(repo, "rev-parse", "HEAD~1")))
    proc = readme_check(repo)
    assert proc.returncode == 1 and "conf/net/wide.yaml" in proc.stderr
    (repo / "README.md").write_text(README.format(commit=at))
    # ... a change of a value after the move does not
    (repo / "conf" / "net" / "student.yaml").write_text("width: 48\n")
    git(repo, "commit", "-qam", "wider config")
    proc = readme_check(repo)
    assert proc.returncode == 1 and "conf/net/student.yaml" in proc.stderr


RECIPE_FILES = {
    "denoiser/lit/distill.py": "ALPHA = 0.5\n",
    "denoiser/commands/netstats.py": "WIDTH = 1\n",
    "conf/base/model.yaml": "lr: 0.001\n",
    "conf/experiment/demo_distill.yaml": "trainer:\n  max_steps: 900\n",
    "conf/pipeline/demo.yaml": "alpha: 0.75\n",
    "conf/hydra/help/command.yaml": "header: usage\n",
    "docs/notes.md": "words\n",
}


def test_readme_check_catches_a_changed_recipe_in_every_file_of_blocks(tmp_path):
    """What a result depends on is all of denoiser/ and conf/ (less hydra/help and the tools no
    pipeline runs): a changed value of a recipe config (conf/base, conf/experiment, conf/pipeline)
    or a changed line of denoiser/lit makes a block stale, in README.md and in docs/results.md, one
    line per block naming its file; comments, --help text and a tool's code do not. With no
    --readme, both files are checked; --report-only lists the stale blocks and exits 0."""
    repo = tmp_path / "repo"
    for path, text in RECIPE_FILES.items():
        (repo / path).parent.mkdir(parents=True, exist_ok=True)
        (repo / path).write_text(text)
    git(repo, "init", "-q")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "recipe")
    at = git(repo, "rev-parse", "--short", "HEAD")
    (repo / "README.md").write_text(README.format(commit=at))
    (repo / "docs" / "results.md").write_text(README.format(commit=at).replace("results:", "ablations:"))

    def check(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, str(ROOT / "scripts" / "readme_check.py"), *args], cwd=repo,
                              capture_output=True, text=True, check=False, timeout=600)

    def commit(path: str, text: str) -> None:
        (repo / path).write_text(text)
        git(repo, "commit", "-qam", f"edit {path}")

    # comments, the help text, a tool that no pipeline runs, and the docs: both blocks stay current
    commit("denoiser/lit/distill.py", "ALPHA = 0.5  # the distillation weight\n")
    commit("conf/base/model.yaml", "# the base recipe\nlr: 0.001  # Adam\n")
    commit("conf/hydra/help/command.yaml", "header: usage, longer\n")
    commit("denoiser/commands/netstats.py", "WIDTH = 2\n")
    commit("docs/notes.md", "other words\n")
    proc = check()
    assert proc.returncode == 0, proc.stderr
    assert "README.md" in proc.stdout and "docs/results.md" in proc.stdout
    # each recipe change alone makes both blocks stale, one line each, naming its file
    for path, text in (("conf/experiment/demo_distill.yaml", "trainer:\n  max_steps: 1200\n"),
                       ("conf/base/model.yaml", "lr: 0.002\n"), ("conf/pipeline/demo.yaml", "alpha: 1.0\n"),
                       ("denoiser/lit/distill.py", "ALPHA = 0.7\n")):
        before = (repo / path).read_text()
        commit(path, text)
        proc = check()
        assert proc.returncode == 1, (path, proc.stdout)
        lines = proc.stderr.splitlines()
        assert len(lines) == 2 and all(path in line for line in lines), (path, lines)
        assert lines[0].startswith("README.md: block 'results'") and lines[1].startswith("docs/results.md: block 'ablations'")
        assert check("--readme", "docs/results.md").stderr.splitlines() == lines[1:]  # one file: its blocks only
        report = check("--report-only")
        assert report.returncode == 0 and report.stderr.splitlines() == lines
        commit(path, before)  # back to the block's values: current again
        assert check().returncode == 0, path


def test_what_readme_check_leaves_unmeasured_no_pipeline_runs_and_no_measured_module_imports():
    """scripts/readme_check.py's UNMEASURED modules cannot change a block: no measured Python file
    imports one (at any depth of its syntax tree) or names
    one in a string (``python -m <module>``), no measured config names one (a _target_, a pipeline
    stage's module), and no pipeline stage runs one as its console command."""
    import ast
    import importlib.util

    import tomllib
    import yaml

    spec = importlib.util.spec_from_file_location("readme_check", ROOT / "scripts" / "readme_check.py")
    check = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(check)

    off = {p.removesuffix(".py").replace("/", ".") for p in check.UNMEASURED if p.endswith(".py")}
    assert "denoiser.commands.netstats" in off and all(importlib.util.find_spec(m) for m in off)

    def measured(path: Path) -> bool:
        rel = path.relative_to(ROOT).as_posix()
        return rel.startswith(check.MEASURED) and not rel.startswith(check.UNMEASURED)

    def strings(data):
        if isinstance(data, dict):
            for key, value in data.items():
                yield from strings(key)
                yield from strings(value)
        elif isinstance(data, list):
            for value in data:
                yield from strings(value)
        elif isinstance(data, str):
            yield data

    scripts = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"]
    for path in [*(ROOT / "denoiser").rglob("*.py"), *(ROOT / "scripts").glob("*.py")]:
        if not measured(path):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Constant):
                assert node.value not in off, f"{path}:{node.lineno} names {node.value}"
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                names = [node.module or "", *(f"{node.module}.{a.name}" for a in node.names)]
            else:
                continue
            assert not off & set(names), f"{path} imports {off & set(names)}"
    configs = [p for p in (ROOT / "conf").rglob("*.yaml") if measured(p)]
    assert any(p.parent.name == "pipeline" for p in configs)
    for path in configs:
        data = yaml.safe_load(path.read_text())
        named = {s for s in strings(data) if any(s == m or s.startswith(m + ".") for m in off)}
        assert not named, f"{path} names {named}"
        for stage in ((data or {}).get("stages") or {}).values() if path.parent.name == "pipeline" else []:
            if stage.get("command"):
                target = scripts[f"denoiser-{stage['command']}"].split(":")[0]
                assert target not in off, f"{path}: a stage runs {target}"


@pytest.mark.slow
def test_readme_check_judges_network_code_by_what_it_computes(tmp_path):
    """A refactor of denoiser/nn (another syntax tree, the same numbers) leaves a block current; a
    change of what a network computes makes it stale (denoiser/commands/nn_fingerprint.py on both trees)."""
    import shutil

    repo = tmp_path / "repo"
    for name in ("denoiser", "conf"):
        shutil.copytree(ROOT / name, repo / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.so"))
    git(repo, "init", "-q")
    git(repo, "add", ".")
    git(repo, "commit", "-qm", "code")
    (repo / "README.md").write_text(README.format(commit=git(repo, "rev-parse", "HEAD")))
    inputs = repo / "denoiser" / "nn" / "inputs.py"
    text = inputs.read_text()
    line = "    return log1p(x.float().clamp_min(0) / scale)\n"
    assert line in text
    inputs.write_text(text.replace(line, "    ratio = x.float().clamp_min(0) / scale\n    return log1p(ratio)\n"))
    git(repo, "commit", "-qam", "refactor")
    proc = readme_check(repo, README_CHECK_NETS="tiny")
    assert proc.returncode == 0, proc.stderr
    assert "denoiser/nn/inputs.py changed in form only: 1 network configs compute the same" in proc.stdout
    inputs.write_text(text.replace(line, "    return log1p(x.float().clamp_min(0) / (2 * scale))\n"))
    git(repo, "commit", "-qam", "another feature scale")
    proc = readme_check(repo, README_CHECK_NETS="tiny")
    assert proc.returncode == 1 and proc.stderr.count("\n") == 1
    assert "denoiser/nn/inputs.py; the networks compute differently (tiny)" in proc.stderr


def test_readme_results_fills_a_pending_block_and_names_its_commit(tmp_path):
    summary = tmp_path / "pareto.md"
    summary.write_text("# P\n\n- run id: R1\n- commit: 1234abc\n\n<!-- pareto:begin -->\n| t |\n<!-- pareto:end -->\n")
    (tmp_path / "plot.png").write_bytes(b"png")
    readme = tmp_path / "README.md"
    readme.write_text(README.format(commit="0"))
    cmd = [sys.executable, str(ROOT / "scripts" / "readme_results.py"), "--summary", str(summary), "--readme",
           str(readme), "--marker", "pareto", "--image", f"{tmp_path / 'plot.png'}:{tmp_path / 'docs' / 'p.png'}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    text = readme.read_text()
    assert "pending" not in text and (tmp_path / "docs" / "p.png").read_bytes() == b"png"
    assert ("<!-- pareto:begin -->\n<!-- copied by scripts/readme_results.py from " in text
            and "run id R1, commit 1234abc -->\n| t |\n\n![pareto: plot.png](docs/p.png)\n<!-- pareto:end -->" in text)
    summary.write_text("<!-- pareto:begin -->\n| t |\n<!-- pareto:end -->\n")  # no commit: no copy
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert proc.returncode == 1 and "states no '- commit" in proc.stderr


# --- time columns: fp32 beside bf16 ---------------------------------------------------------------


def test_results_table_puts_fp32_beside_bf16_with_the_paired_speedup(tmp_path):
    """The student's fastest fp32 row and fastest bf16 row each get their own columns; the speed-up
    is the bench's paired one with its interval (not a ratio of the fastest of any precision)."""
    from denoiser.commands.demo_summary import bench_rows, results_table
    from denoiser.report.summary import seed_groups

    rows = [
        {"method": "OIDN-fast", "backend": "oidn", "dtype": "fp32", "kind": "baseline", "ms": 1400.0, "sp": (1.0, 1.0, 1.0)},
        {"method": "student_s0", "backend": "openvino_f32", "dtype": "fp32", "kind": "network", "ms": 1380.0,
         "sp": (1.01, 0.97, 1.06)},
        {"method": "student_s0", "backend": "eager", "dtype": "fp32", "kind": "network", "ms": 3000.0, "sp": (0.47, 0.45, 0.5)},
        {"method": "student_s0", "backend": "openvino_bf16", "dtype": "bf16", "kind": "network", "ms": 800.0,
         "sp": (1.75, 1.70, 1.80)},
    ]
    path = tmp_path / "bench.csv"
    with path.open("w") as f:
        f.write("method,backend,dtype,kind,height,width,status,ms_median,speedup,speedup_lo,speedup_hi\n")
        for r in rows:
            f.write(f"{r['method']},{r['backend']},{r['dtype']},{r['kind']},1080,1920,ok,{r['ms']},{','.join(map(str, r['sp']))}\n")
    bench = bench_rows(path, (1080, 1920))
    assert bench["fp32"]["student_s0"]["backend"] == "openvino_f32" and bench["bf16"]["student_s0"]["backend"] == "openvino_bf16"
    groups = seed_groups({"OIDN-fast": {"psnr": 30.0}, "student_s0": {"psnr": 31.0}})
    table = results_table(groups, bench, (1080, 1920), "OIDN-fast").splitlines()
    header = [c.strip() for c in table[0].split("|")[1:-1]]
    assert header[-4:] == ["ms/frame 1920x1080 fp32", "fp32 vs OIDN-fast (interval)",
                           "ms/frame 1920x1080 bf16", "bf16 vs OIDN-fast (interval)"]
    student = [c.strip() for c in table[3].split("|")[1:-1]]
    assert student[-4:] == ["1380 (openvino_f32)", "1.01x (0.97-1.06)", "800 (openvino_bf16)", "1.75x (1.70-1.80)"]
    oidn = [c.strip() for c in table[2].split("|")[1:-1]]
    assert oidn[-4:] == ["1400 (oidn)", "1.00x", "", ""]
