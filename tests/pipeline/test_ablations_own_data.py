"""make ablations on a user's own data (conf/pipeline/ablations.yaml's data=, layout=, data.<key>=,
runs=, oidn=): a tiny two-ablation sweep, for real (denoiser-train, -eval, -bench and the summary), on
a 32x32 dataset against a teacher and full-recipe students trained here first; the summary has the
paired intervals and the OIDN-fast row and column. The demo's command lines with the defaults are
those of before these keys (tests/pipeline/test_pipeline.py composes them)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.train_args import NARROW

from denoiser.data.synthetic import write_synthetic_sequence

pytest.importorskip("pyoidn")

BIN = Path(sys.executable).parent
#: the data every command reads: the tiny data config at the test's root, none of the demo's extra roots
DATA = ["data=tiny", "data.extra_roots=[]", "data.extra_share=null"]
#: short quiet trainings of a student narrower than the tiny teacher
STUDENT = ["net=tiny", *NARROW, "trainer.max_steps=2", "trainer.val_check_interval=2", "trainer.limit_val_batches=1",
           "trainer.log_every_n_steps=1", "trainer.enable_model_summary=false", "model.image_interval=0",
           "callbacks.last.every_n_train_steps=2"]
QUIET = ["threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null"]


def train(tmp_path: Path, run_dir: Path, *overrides: str) -> None:
    proc = subprocess.run([str(BIN / "denoiser-train"), *overrides, *QUIET, f"hydra.run.dir={run_dir}"], cwd=tmp_path,
                          capture_output=True, text=True, timeout=600, check=False)
    assert proc.returncode == 0 and (run_dir / "DONE").is_file(), proc.stderr[-3000:]


@pytest.mark.slow
def test_a_two_ablation_sweep_on_own_data_gets_the_paired_summary_with_oidn(tmp_path):
    root = tmp_path / "renders"
    for split, count, labeled in (("train", 2, True), ("val", 1, True), ("test", 4, True), ("unlabeled", 1, False)):
        for i in range(count):
            write_synthetic_sequence(root / split / f"{split}{i}", frames=4, width=32, height=32, labeled=labeled,
                                     seed=100 * len(split) + i)
    data = [*DATA, f"data.root={root}"]
    runs = tmp_path / "runs"   # what make demo leaves, here trained on the user's data
    train(tmp_path, runs / "teacher", "model=teacher", "net=tiny", *data, "trainer.max_steps=2",
          "trainer.val_check_interval=2", "trainer.limit_val_batches=1", "model.image_interval=0")
    teacher = runs / "teacher" / "checkpoints" / "best.ckpt"
    train(tmp_path, runs / "student_distilled_s0", "experiment=demo_distill", *data, f"model.teacher_ckpt={teacher}",
          "seed=0", *STUDENT)
    train(tmp_path, runs / "student_no_kd_s0", "experiment=demo", *data, "seed=0",
          *(a for a in STUDENT if not a.startswith("model.critic")))   # no critic without a teacher

    report, ledger = tmp_path / "report", tmp_path / "ledger.csv"
    train_args = "train_args=[" + ",".join(f'"{a}"' for a in STUDENT) + "]"
    proc = subprocess.run(
        [sys.executable, "-m", "denoiser.commands.pipeline", "pipeline=ablations", *data, f"runs={runs}",
         f"report={report}", "seeds=[0]", "variants=[no_pyramid,direct]", "oidn=true", train_args, "threads=1",
         "bench_size=[32,32]", "use_backends=[eager]", "repeats=1", f"ledger={ledger}", "cores=2"],
        cwd=tmp_path, capture_output=True, text=True, timeout=900, check=False,
        env={**os.environ, "DENOISER_DATA": str(tmp_path / "no_demo_data")})
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    check_summary((report / "summary.md").read_text(), root)
    # the commands read the user's data and wrote their look into the given ledger
    assert str(root) in ledger.read_text()
    assert (report / "runs" / "no_pyramid_s0" / "DONE").is_file() and (report / "runs" / "direct_s0" / "DONE").is_file()


def check_summary(text: str, root: Path) -> None:
    """The summary of the sweep: its test split, and in the figure's table every variant's paired
    interval against none and against OIDN-fast, OIDN-fast's own row, and the sentence on OIDN."""
    assert f"held-out scenes of `{root / 'test'}`" in text
    lines = text.splitlines()
    top = lines.index(next(line for line in lines if line.startswith("| variant | seeds |")))
    header, table = lines[top], lines[top + 2: lines.index("", top)]
    assert "Δ PSNR dB vs none [95%]" in header and "Δ PSNR dB vs OIDN-fast [95%]" in header
    rows = {line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]] for line in table}
    assert list(rows) == ["none", "no_pyramid", "direct", "OIDN-fast"]
    interval = re.compile(r"^[+-]\d+\.\d+ \[[+-]\d+\.\d+, [+-]\d+\.\d+\] (ahead|tied|behind)$")
    for name in ("no_pyramid", "direct"):   # against none (PSNR, SSIM, FLIP, tPSNR) and against OIDN-fast
        assert all(interval.match(c) for c in rows[name][5:10]), rows[name]
    assert interval.match(rows["none"][9]) and all(interval.match(c) for c in rows["OIDN-fast"][5:9])
    assert re.search(r"^- The full recipe \(none\) is (ahead of|tied with|behind) OIDN-fast on PSNR dB: [+-]\d", text,
                     re.MULTILINE)
    assert "4 sequences" in text
