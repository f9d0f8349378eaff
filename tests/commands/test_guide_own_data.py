"""docs/guide.md's "Your own renders" block, run line by line as the guide prints it: a tiny Cycles
dataset rendered with denoiser-render-blender from scenes built here with bpy (64x64: the recipe's
crop, 4 frames: its window), trained on (fast_dev_run, then a few steps), evaluated against the noisy
input and OIDN on val and test, swept (two ablations against a teacher and the full recipe's
students trained first, with OIDN: the paired-interval summary), and denoised, in a folder that also
holds the demo's ``data/demo_motion`` (as a checkout after ``make demo``: experiment=demo would join
it). The lines are read from the guide, so the guide and this test cannot drift; only the
placeholders are substituted, and the references' spp, the steps and the sweep's timing made smaller
(:data:`SMALLER`, :data:`SHORT_RUN`, :data:`SMALLER_SWEEP`)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
import time
from pathlib import Path

import pytest
from helpers.blender import blender_python_or_skip, build_scene
from helpers.eval_data import write_dataset

from denoiser.report import ledger
from denoiser.tables import read_csv

ROOT = Path(__file__).resolve().parents[2]
GUIDE = ROOT / "docs" / "guide.md"
SECTION = "## Your own renders"
VENV_BIN = Path(sys.executable).parent
#: what the test shrinks: (pattern in a command line, replacement), applied to every line
SMALLER = ((r"\bref_spp=1024\b", "ref_spp=16"),)
#: added to every training without debug= (its steps): the guide's, and the sweep's through train_args
SHORT_RUN = ["trainer.max_steps=2", "trainer.val_check_interval=2", "callbacks.last.every_n_train_steps=2"]
#: added to the sweep (denoiser-pipeline): its variants' steps, and the timing at 32x32, eager, one round
SMALLER_SWEEP = ["train_args=[" + ",".join(f'"{a}"' for a in SHORT_RUN) + "]", "bench_size=[32,32]",
                 "use_backends=[eager]", "repeats=1"]
#: the first table of the sweep's summary: the full recipe, the two variants, OIDN-fast
SWEPT = ["none", "no_pyramid", "direct", "OIDN-fast"]
#: a paired-interval cell of the summary: the mean difference, its interval, the verdict
INTERVAL = re.compile(r"^[+-]\d+\.\d+ \[[+-]\d+\.\d+, [+-]\d+\.\d+\] (ahead|tied|behind)$")


def guide_lines() -> list[str]:
    """The commands of the section's first bash block, continuation lines joined, comments dropped."""
    text = GUIDE.read_text()
    start = text.index(SECTION)
    end = text.find("\n## ", start + len(SECTION))
    block = re.search(r"```bash\n(.*?)```", text[start:end], re.DOTALL)
    assert block, f"{GUIDE}: no bash block under {SECTION!r}"
    joined = block[1].replace("\\\n", " ")
    return [line.strip() for line in joined.splitlines() if line.strip() and not line.strip().startswith("#")]


def test_the_guides_block_has_every_step():
    verbs = [shlex.split(line)[0] for line in guide_lines()]
    assert verbs.count("denoiser-render-blender") == 4 and verbs.count("denoiser-eval") == 2
    assert verbs.count("python") == 5 and "denoiser-denoise" in verbs
    assert any(line.startswith("denoiser-pipeline pipeline=ablations ") and "oidn=true" in line for line in guide_lines())


@pytest.mark.slow
def test_the_guides_own_data_commands_run_as_written(tmp_path):
    python = blender_python_or_skip()
    places = {f"<shot_{k}.blend>": str(build_scene(python, tmp_path / f"shot_{k}.blend", size=64, frames=4))
              for k in "abcd"}
    places |= {"<first>-<last>": "1-4", "<renders>": str(tmp_path / "renders"), "<run>": str(tmp_path / "run"),
               "<reports>": str(tmp_path / "reports"), "<denoised>": str(tmp_path / "denoised"), "<shot_c>": "shot_c",
               "<runs>": "runs", "<sweep>": "sweep"}   # the sweep's folders as typed: relative to where it runs
    env = {**os.environ, "DENOISER_BLENDER_PYTHON": str(python)}
    env.pop("DENOISER_DATA", None)
    for split in ("val", "unlabeled"):  # a checkout after make demo: the demo's data/demo_motion (native layout)
        write_dataset(tmp_path / "data" / "demo_motion", split, sequences=1, frames=4, size=32)
    project_ledger = ledger.LEDGER.read_bytes()
    took = []
    for line in guide_lines():
        for placeholder, value in places.items():
            line = line.replace(placeholder, value)
        for pattern, replacement in SMALLER:
            line = re.sub(pattern, replacement, line)
        assert "<" not in line, f"a placeholder the test does not know: {line}"
        argv = shlex.split(line)
        if argv[:2] == ["python", "train.py"]:
            argv = [sys.executable, str(ROOT / "train.py"), *argv[2:], "threads=1",
                    *([] if any(a.startswith("debug=") for a in argv) else SHORT_RUN)]
        else:
            argv = [str(VENV_BIN / argv[0]), *argv[1:], *(SMALLER_SWEEP if argv[0] == "denoiser-pipeline" else [])]
        start = time.monotonic()
        done = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True, check=False, timeout=600)
        took.append(f"{time.monotonic() - start:6.1f} s  {line[:100]}")
        assert done.returncode == 0, f"{line}\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    print("\n".join(took))   # each command's seconds (pytest -s shows them)
    renders = tmp_path / "renders"
    for split, shot in (("train", "shot_a"), ("val", "shot_b"), ("test", "shot_c")):
        assert len(list((renders / split / shot / "reference").glob("*.exr"))) == 4
    assert (tmp_path / "run" / "checkpoints" / "last.ckpt").is_file()
    for split in ("val", "test"):
        methods = {row["method"] for row in read_csv(tmp_path / "reports" / split / "metrics.csv")}
        assert {"noisy input", "OIDN-fast", "mine"} <= methods, methods
    rows = ledger.read(renders / "test_ledger.csv")
    assert [(r["split"], r["look"], r["purpose"]) for r in rows] == [
        ("test", "1", "final judgement of my recipe"), ("test", "2", "make ablations: the ablation report")]
    check_sweep((tmp_path / "sweep" / "summary.md").read_text(), renders / "test")
    assert ledger.LEDGER.read_bytes() == project_ledger
    assert sorted(p.name for p in (tmp_path / "denoised").glob("*.exr")) == [f"{f:04d}.exr" for f in range(1, 5)]


def check_sweep(text: str, test_split: Path) -> None:
    """The sweep's summary.md: read from the user's test split; its first table's rows the full
    recipe, both variants and OIDN-fast, each variant with a paired interval against the full recipe
    and against OIDN-fast; the sentence on the full recipe against OIDN; one teacher, equal steps."""
    assert f"held-out scenes of `{test_split}`" in text
    lines = text.splitlines()
    top = lines.index(next(line for line in lines if line.startswith("| variant | seeds |")))
    header = [c.strip() for c in lines[top].split("|")[1:-1]]
    rows = {cells[0]: dict(zip(header, cells, strict=True)) for cells in
            ([c.strip() for c in line.split("|")[1:-1]] for line in lines[top + 2: lines.index("", top)])}
    assert list(rows) == SWEPT, list(rows)
    for variant in ("no_pyramid", "direct"):
        for against in ("none", "OIDN-fast"):
            assert INTERVAL.match(rows[variant][f"Δ PSNR dB vs {against} [95%]"]), (variant, against, rows[variant])
    assert INTERVAL.match(rows["OIDN-fast"]["Δ PSNR dB vs none [95%]"]), rows["OIDN-fast"]
    assert re.search(r"^- The full recipe \(none\) is (ahead of|tied with|behind) OIDN-fast on PSNR dB: [+-]\d", text,
                     re.MULTILINE)
    assert "Not the same teacher" not in text and "Not at equal steps" not in text
