"""Claims with intervals: the paired bootstrap (against a hand loop), the summary's verdicts from
synthetic metrics.csv files, the frames-2+ PSNR, merged identical rows, and the results table's
fp32 and bf16 columns. The README's staleness check is tests/core/test_readme_check.py."""

from __future__ import annotations

import csv
import math
import statistics
from pathlib import Path

import numpy as np
import pytest
import torch

from denoiser.metrics import COLUMNS, METRICS, MetricAccumulator, psnr
from denoiser.report.seed_groups import (
    group_sequences,
    group_timing,
    merge_identical,
    method_means,
    seed_groups,
    sequence_values,
)
from denoiser.report.stats import paired_interval

ROOT = Path(__file__).resolve().parents[2]


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
    # one sequence is no sample: its interval is the one difference, [x, x], and it decides nothing
    one = paired_interval([31.0], [30.0])
    assert (one.lo, one.hi, one.n) == (1.0, 1.0, 1) and one.verdict() == "tied" == one.verdict(lower_is_better=True)
    assert paired_interval([31.0, 32.0], [30.0, 31.0]).verdict() == "ahead"


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
    from denoiser.commands.tools.eval_summary import run
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
    from denoiser.commands.tools.eval_summary import run
    from denoiser.configs import compose_config

    report = tmp_path / "report"
    for folder in ("eval", "blender", "cycles"):
        write_metrics(report / folder / "metrics.csv", synthetic_rows())
    run(compose_config([f"report={report}", f"data_root={tmp_path}", "extra_evals.blender=null", "+extra_evals.cycles=Cycles"],
                       "demo_summary"))
    summary = (report / "summary.md").read_text()
    assert "<!-- cycles:begin -->" in summary and "## Cycles" in summary
    assert "<!-- blender:begin -->" not in summary


# --- time columns: fp32 beside bf16 ---------------------------------------------------------------


def test_results_table_puts_fp32_beside_bf16_with_the_paired_speedup(tmp_path):
    """The student's fastest fp32 row and fastest bf16 row each get their own columns; the speed-up
    is the bench's paired one with its interval (not a ratio of the fastest of any precision)."""
    from denoiser.commands.tools.eval_summary import bench_rows, results_table
    from denoiser.report.seed_groups import seed_groups

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
