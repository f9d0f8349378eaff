"""The per-CPU speed record: ``add`` is idempotent whatever the commit hash looks like."""

import json

import pytest

from denoiser.report.cpu_speed import add, render
from denoiser.tables import read_csv


def _bench(path, commit: str, caps: dict | None = None) -> None:
    """A minimal ``bench.json``: one student-vs-OIDN-fast ratio at 64x32."""
    path.write_text(json.dumps({
        "machine": {"cpu": "Test CPU", "cpu_id": "Vendor family 1 model 2", "isa": {"avx2": True},
                    "threads_requested": 2, "date": "2026-12-02", "commit": commit, "versions": {"torch": "2.13.0"},
                    "isa_caps": caps or {}},
        "speedups": [{"size": "64x32", "student": "student (eager fp32)", "dtype": "fp32", "student_ms": 10.04,
                      "baseline": "OIDN-fast", "baseline_ms": 20.0, "ratio": 2.0, "ratio_lo": 1.9, "ratio_hi": 2.1}],
        "rows": [{"method": "student", "backend": "eager fp32", "width": 64, "height": 32, "peak_fraction": 0.5}],
    }))


# hashes a number parser would change: leading zero (0496959 -> 496959), exponent (12e4567 -> inf)
@pytest.mark.parametrize("commit", ["0496959", "12e4567", "1234567", "abc1234"])
def test_add_twice_keeps_one_row_and_the_commit_as_written(tmp_path, commit):
    bench, csv = tmp_path / "bench.json", tmp_path / "cpu_speed.csv"
    _bench(bench, commit)
    assert add([bench], csv) == 1
    assert add([bench], csv) == 0  # the same run again: nothing added
    rows = read_csv(csv, text=("commit",))
    assert len(rows) == 1 and rows[0]["commit"] == commit
    assert f"| {commit} |" in render(csv)


def test_a_capped_run_is_not_added(tmp_path, capsys):
    """A bench run under an instruction-set cap (ONEDNN_MAX_CPU_ISA=AVX2 on an AVX-512 CPU) timed
    OIDN at the CPU's own ISA: its ratio belongs to no CPU, so add refuses it in one line."""
    from denoiser.report.cpu_speed import main

    bench, csv = tmp_path / "bench.json", tmp_path / "cpu_speed.csv"
    _bench(bench, "abc1234", caps={"ONEDNN_MAX_CPU_ISA": "AVX2"})
    code = main(["add", str(bench), "--csv", str(csv), "--out", str(tmp_path / "cpu_speed.md")])
    assert code != 0 and not csv.exists() and not (tmp_path / "cpu_speed.md").exists()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ran with instruction sets capped ($ONEDNN_MAX_CPU_ISA=AVX2)" in err[0], err


def test_read_csv_keeps_names_that_look_like_numbers(tmp_path):
    from denoiser.tables import write_csv

    path = tmp_path / "metrics.csv"
    write_csv(path, [{"sequence": "0001", "method": "007", "psnr": 30.5, "frames": 8}])
    (row,) = read_csv(path)
    assert row == {"sequence": "0001", "method": "007", "psnr": 30.5, "frames": 8}
