"""`make compare`: its data (render_set=demo_compare: demo's test job with per-sample radiance, in
its own root) and its summary (the Fig. A.2 / A.3 tables of conf/compare_summary.yaml, their
mean ± std over seeds, 1080p times and ranking lines), checked against plain computations."""

from __future__ import annotations

import dataclasses
import re
import statistics
import subprocess
import sys
from pathlib import Path

from hydra import compose, initialize_config_dir

from denoiser.commands.render import plan
from denoiser.conf import CONF_DIR


def _render_cfg(*overrides: str):
    with initialize_config_dir(CONF_DIR, version_base=None):
        return compose("render", overrides=list(overrides))


def test_demo_compare_renders_exactly_demos_test_job_with_samples_in_its_own_root():
    demo, compare = _render_cfg("render_set=demo"), _render_cfg("render_set=demo_compare")
    demo_test = [j for j in plan(demo) if j.split == "test"]
    jobs = plan(compare)
    assert demo_test and len(jobs) == len(demo_test)
    for ours, theirs in zip(jobs, demo_test):
        assert ours.directory == theirs.directory and ours.index == theirs.index
        assert ours.scene_config == theirs.scene_config
        assert ours.settings.save_samples and not theirs.settings.save_samples
        assert ours.settings == dataclasses.replace(theirs.settings, save_samples=True)
    # sequence seeds derive from seed, scene, split and index: the same scenes, cameras and references
    assert compare.seed == demo.seed
    assert Path(compare.root).name == "demo_compare" and Path(compare.root).parent == Path(demo.root).parent
    with initialize_config_dir(CONF_DIR, version_base=None):
        data = compose("eval", overrides=["data=demo_compare"]).data
        demo_data = compose("eval", overrides=["data=demo"]).data
    assert data.root == compare.root
    assert {k: v for k, v in data.items() if k != "root"} == {k: v for k, v in demo_data.items() if k != "root"}


# --- the summary's figure tables -------------------------------------------------------------

PSNR = {  # method label -> per-sequence PSNR (two sequences); students and NPPD/WS with seeds
    "OIDN-fast": [30.0, 31.0], "OIDN-high": [31.0, 32.5], "ONND": [27.0, 26.0], "teacher": [33.0, 34.0],
    "student_s0": [29.0, 30.0], "student_s1": [29.5, 31.0], "student_s2": [28.0, 29.0],
    "nppd_s0": [28.0, 28.5], "nppd_s1": [27.0, 29.0], "nppd_s2": [28.5, 28.0],
    "ws_s0": [26.0, 25.0], "ws_s1": [25.5, 26.5], "ws_s2": [24.0, 27.0],
}


def _metric_rows(psnr: dict[str, list[float]]) -> list[dict]:
    rows = []
    for method, values in psnr.items():
        for i, p in enumerate(values):
            rows.append({"method": method, "scene": f"s{i}", "sequence": f"test/s{i}_002", "frames": 8,
                         "psnr": p, "ssim": p / 40, "tpsnr": p - 1.5, "flip": 1 / p, "relmse": 0.01})
    return rows


def _bench_rows() -> list[dict]:
    rows = []
    for i, method in enumerate(["OIDN-fast", "OIDN-high", "ONND", "student_s0", "nppd_s0", "ws_s0"]):
        for backend, ms in (("eager", 100.0 + 10 * i), ("openvino_bf16", 40.0 + 7 * i)):
            rows.append({"method": method, "backend": backend, "dtype": "", "height": 1080, "width": 1920,
                         "status": "ok", "ms_median": ms})
        rows.append({"method": method, "backend": "openvino_bf16", "dtype": "", "height": 256, "width": 256,
                     "status": "ok", "ms_median": 1.0})  # another size: never the 1080p time
        rows.append({"method": method, "backend": "onnxruntime", "dtype": "", "height": 1080, "width": 1920,
                     "status": "error", "ms_median": 0.5})  # failed: never the time
    return rows


def _write_csv(path: Path, rows: list[dict]) -> None:
    import csv

    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w", newline="") as f:
        writer = csv.DictWriter(f, list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _summary(tmp_path: Path, psnr: dict[str, list[float]], *overrides: str) -> subprocess.CompletedProcess:
    report = tmp_path / "report"
    _write_csv(report / "eval" / "metrics.csv", _metric_rows(psnr))
    _write_csv(report / "bench" / "bench.csv", _bench_rows())
    return subprocess.run([sys.executable, "-m", "denoiser.commands.tools.eval_summary", "--config-name", "compare_summary",
                           f"report={report}", f"data_root={tmp_path / 'data'}", "seeds=[0,1,2]", *overrides],
                          capture_output=True, text=True, cwd=tmp_path, check=False)


def _section(summary: str, title: str) -> tuple[list[list[str]], list[str]]:
    """(table rows as cells, bullet lines) of the section ``## title``."""
    lines = summary.split(f"## {title}\n", 1)[1].split("\n## ", 1)[0].splitlines()
    table = [[c.strip() for c in line.strip("|").split("|")] for line in lines if line.startswith("| ")]
    return table[1:], [line[2:] for line in lines if line.startswith("- ")]


def _tables():
    with initialize_config_dir(CONF_DIR, version_base=None):
        return compose("compare_summary").tables


def _plain_psnr(psnr: dict[str, list[float]], group: str) -> list[float]:
    """Per-seed (or single-run) PSNR of a group: the mean over its sequences."""
    return [statistics.fmean(v) for m, v in psnr.items() if m == group or re.fullmatch(rf"{re.escape(group)}_s\d+", m)]


def test_figure_tables_rows_means_std_times_and_ranking(tmp_path):
    proc = _summary(tmp_path, PSNR)
    assert proc.returncode == 0, proc.stderr
    summary = (tmp_path / "report" / "summary.md").read_text()
    # its own README block (make readme), never make demo's `results` block
    assert summary.count("<!-- compare:begin -->") == summary.count("<!-- compare:end -->") == 1
    assert "<!-- results:begin -->" not in summary
    tables = _tables()
    assert [t.title for t in tables][:2] == ["Fig. A.2: real-time denoisers at 4 spp", "Fig. A.3: OIDN, teacher and student"]
    bench = _bench_rows()
    for spec in tables:
        rows, notes = _section(summary, spec.title)
        assert [r[0] for r in rows] == [r.label for r in spec.rows]
        means = {}
        for cells, row in zip(rows, spec.rows):
            per_seed = _plain_psnr(PSNR, row.method)
            means[row.method] = statistics.fmean(per_seed)
            expect = f"{statistics.fmean(per_seed):.2f}"
            if len(per_seed) > 1:
                expect += f" ± {statistics.stdev(per_seed):.2f}"
            seeds = [m for m in PSNR if re.fullmatch(rf"{re.escape(row.method)}_s\d+", m)]
            assert cells[1] == (str(len(seeds)) if seeds else "")
            assert cells[2] == expect, (row.method, cells)
            timed = row.method if row.method in {b["method"] for b in bench} else f"{row.method}_s0"
            ms = [b["ms_median"] for b in bench if b["method"] == timed and b["status"] == "ok" and b["height"] == 1080]
            assert cells[-1] == (f"{min(ms):.0f}" if ms else ""), (row.method, cells)
        labels = {r.method: r.label for r in spec.rows}
        mine = means[spec.rank]
        above = [labels[m] for m, v in means.items() if m != spec.rank and v < mine]
        below = [labels[m] for m, v in means.items() if m != spec.rank and v > mine]
        assert f"{labels[spec.rank]} ranks above {', '.join(above) or 'none'}; below {', '.join(below) or 'none'} " \
               "(PSNR dB ↑, mean over seeds)" in notes
        claimed = [means[m] for m in spec.order.methods]
        verdict = "yes" if claimed == sorted(claimed, reverse=True) else "no"
        order = [n for n in notes if n.startswith(f"{spec.order.name}: ")]
        assert len(order) == 1 and order[0].split(": ")[2].split(" ")[0] == verdict
    # the paper's claims hold in these numbers: NPPD > ONND > WS, teacher > OIDN high > student
    a2 = _section(summary, tables[0].title)[1]
    assert "baselines: NPPD > ONND > WS: yes (PSNR dB ↑)" in a2
    assert "student (ours) ranks above ONND, WS, NPPD; below none (PSNR dB ↑, mean over seeds)" in a2
    assert summary.count("mean ± std over seeds") == 1


def test_figure_tables_say_no_and_name_missing_methods(tmp_path):
    swapped = {**PSNR, "ONND": [20.0, 21.0]}  # ONND below WS: the paper's order does not hold
    assert _summary(tmp_path, swapped).returncode == 0
    notes = _section((tmp_path / "report" / "summary.md").read_text(), _tables()[0].title)[1]
    assert "baselines: NPPD > ONND > WS: no (measured: NPPD > WS > ONND; PSNR dB ↑)" in notes
    without = {k: v for k, v in PSNR.items() if k != "ONND"}  # COMPARE_ONND=0
    assert _summary(tmp_path, without).returncode == 0
    rows, notes = _section((tmp_path / "report" / "summary.md").read_text(), _tables()[0].title)
    assert rows[0][0] == "ONND" and set(rows[0][1:]) == {""}
    assert "not evaluated: ONND" in notes
    assert "baselines: NPPD > ONND > WS: n/a (not evaluated: ONND)" in notes
    assert "student (ours) ranks above WS, NPPD; below none (PSNR dB ↑, mean over seeds)" in notes


def test_a_table_without_rows_is_one_line_error(tmp_path):
    proc = _summary(tmp_path, PSNR, "tables=[{title: empty}]")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "title and rows" in proc.stderr
    proc = _summary(tmp_path, PSNR, "table_metrics=[psnr,sharpness]")
    assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and "sharpness" in proc.stderr


def test_ranking_by_a_lower_is_better_metric(tmp_path):
    """FLIP (lower is better) = 1 / PSNR here, so the ranking matches PSNR's."""
    assert _summary(tmp_path, PSNR, "rank_metric=flip").returncode == 0
    notes = _section((tmp_path / "report" / "summary.md").read_text(), _tables()[0].title)[1]
    assert "baselines: NPPD > ONND > WS: yes (FLIP ↓)" in notes
    assert "student (ours) ranks above ONND, WS, NPPD; below none (FLIP ↓, mean over seeds)" in notes
