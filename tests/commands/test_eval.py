"""Tests of denoiser-eval on tiny real EXR sequences with a checkpoint built in the test."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.eval_data import write_dataset

from denoiser.errors import UserError
from denoiser.tables import read_csv

VENV_BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    write_dataset(root / "data", sequences=2, frames=4, size=32, cuts=(2,))
    a, b = tiny_checkpoint(root / "a.ckpt", seed=0), tiny_checkpoint(root / "b.ckpt", seed=1)
    return root, a, b


def compose_eval(overrides):
    return compose_command("eval", overrides, threads=1)


def test_eval_tables_images_and_values(setup, tmp_path):
    from denoiser.commands.evaluate import run

    root, a, b = setup
    out = tmp_path / "out"
    cfg = compose_eval(["data=tiny", f"data.root={root / 'data'}", f"ckpt={{teacher: {a}, student: {b}}}",
                        f"out_dir={out}", "images.size=16", "warmup=1", "save_exr=true"])
    overall = run(cfg)
    assert list(overall) == ["noisy input", "OIDN-fast", "OIDN-balanced", "OIDN-high", "teacher", "student"]
    rows = read_csv(out / "metrics.csv")
    assert len(rows) == 6 * 3  # 2 sequences + mean per method
    noisy = {r["sequence"]: r for r in rows if r["method"] == "noisy input"}
    # the noisy input's PSNR recomputed from the EXR files (frames 1 and 3 are kept: warm-up 1 frame
    # after the resets at frames 0 and 2)
    from denoiser.data.exr import read_frame
    from denoiser.metrics import psnr

    values = {}
    for t in range(4):
        bufs, _ = read_frame(root / "data/test/seq_000" / f"frame_{t:04d}.exr",
                             {"color": ("color.R", "color.G", "color.B"),
                              "reference": ("reference.R", "reference.G", "reference.B")})
        to_t = {k: torch.from_numpy(v).permute(2, 0, 1)[None] for k, v in bufs.items()}
        values[t] = float(psnr(to_t["color"], to_t["reference"])[0])
    assert noisy["test/seq_000"]["frames"] == 2
    assert math.isclose(noisy["test/seq_000"]["psnr"], (values[1] + values[3]) / 2, rel_tol=1e-5)
    # frames 2+ (1-based): every frame but the first, the warm-up frame 2 after the cut included
    assert math.isclose(noisy["test/seq_000"]["psnr_f2"], (values[1] + values[2] + values[3]) / 3, rel_tol=1e-5)
    assert "PSNR dB frames 2+ ↑" in (out / "metrics.md").read_text()
    mean = noisy["mean"]["psnr"]
    assert math.isclose(mean, (noisy["test/seq_000"]["psnr"] + noisy["test/seq_001"]["psnr"]) / 2, rel_tol=1e-6)
    # OIDN really denoises; tPSNR is defined only where no cut precedes (frames 1 and 3)
    assert overall["OIDN-high"]["psnr"] > overall["noisy input"]["psnr"] + 3
    assert overall["OIDN-fast"]["flip"] < overall["noisy input"]["flip"]
    frames = read_csv(out / "frames.csv")
    cut = [r for r in frames if r["method"] == "student" and r["sequence"] == "test/seq_000" and r["frame"] == 2]
    assert math.isnan(cut[0]["tpsnr"]) and cut[0]["warmup"] == "True"
    md = (out / "metrics.md").read_text()
    assert "| teacher |" in md and "## Per scene" in md and "scene1" in md
    assert (out / "images" / "test_seq_000.png").stat().st_size > 1000
    assert len(list((out / "exr" / "student").rglob("*.exr"))) == 8


def test_networks_run_recurrently_over_the_sequence(setup, tmp_path):
    """Eval's per-frame outputs equal Denoiser.forward over the whole sequence (state carried)."""
    from denoiser.checkpoint import load_denoiser
    from denoiser.commands.evaluate import run
    from denoiser.data.evalset import open_test_split
    from denoiser.data.exr import read_channels

    root, a, _ = setup
    out = tmp_path / "out"
    cfg = compose_eval(["data=tiny", f"data.root={root / 'data'}", f"ckpt=[{a}]", "~baselines.oidn_fast",
                        "~baselines.oidn_balanced", "~baselines.oidn_high", "metrics=[psnr]",
                        f"out_dir={out}", "images.frame=null", "save_exr=true", "sequences=[seq_001]"])
    run(cfg)
    _, sources, dataset = open_test_split(cfg.data, "test", ["seq_001"])
    item = dataset.load(sources[0], 0, 4, None)
    item["reset"] = torch.tensor([True, False, True, False])
    net = load_denoiser(a)
    with torch.no_grad():
        expected, _, _ = net({k: v[None] for k, v in item.items() if isinstance(v, torch.Tensor)},
                             reset=item["reset"][None])
    for t in range(4):
        ch = read_channels(out / "exr" / "a" / "test" / "seq_001" / f"frame_{t:04d}.exr")
        got = np.stack([ch["denoised.R"], ch["denoised.G"], ch["denoised.B"]])
        assert np.allclose(got, expected[0, t].numpy(), atol=1e-5), t
    assert not (out / "images").exists()


def test_eval_user_errors(setup, tmp_path):
    from denoiser.checkpoint import checkpoint_paths
    from denoiser.commands.evaluate import run

    root, _, _ = setup
    base = ["data=tiny", f"data.root={root / 'data'}", f"out_dir={tmp_path}"]
    with pytest.raises(UserError, match="missing.ckpt: checkpoint file does not exist"):
        run(compose_eval(base + [f"ckpt=[{tmp_path / 'missing.ckpt'}]"]))
    with pytest.raises(UserError, match="no sequence"):
        run(compose_eval(base + ["sequences=[nope]"]))
    with pytest.raises(UserError, match="unknown"):
        run(compose_eval(base + ["metrics=[psnr,lpips]"]))
    assert list(checkpoint_paths(["x/s.ckpt", "y/s.ckpt"])) == ["x/s", "y/s"]
    assert list(checkpoint_paths("x/s.ckpt")) == ["s"]


def test_eval_console_script_reports_one_line(tmp_path):
    command = [str(VENV_BIN / "denoiser-eval"), "data=tiny", f"data.root={tmp_path / 'nothing'}",
               f"hydra.run.dir={tmp_path / 'h'}", f"ledger={tmp_path / 'ledger.csv'}"]
    proc = subprocess.run([*command, "purpose=debug"], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 2
    assert proc.stderr.strip().startswith("error: ") and "nothing/test" in proc.stderr
    assert "Traceback" not in proc.stderr
    proc = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)  # a test split, no purpose
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0
    assert proc.stderr.startswith("error: split=test: purpose= is required") and "Traceback" not in proc.stderr
    assert not (tmp_path / "ledger.csv").exists()


def test_a_test_split_rendered_again_keeps_its_looks(setup, tmp_path):
    """A split is what was drawn, not the bytes of one render of it: the same sequences rendered
    again (a fresh clone's make demo: each sequence.json's render timings differ, and a frame's
    Monte Carlo bytes may too) keep the ledger's count, and the summary says which look it is.
    Another draw (a sequence's seeds changed) starts at 1. The make demo of 2026-11-29 from a fresh
    clone recorded look 1 of a split looked at five times before."""
    import shutil

    from denoiser.commands.evaluate import run
    from denoiser.data.sequence import SEQUENCE_JSON
    from denoiser.report import ledger

    root, a, _ = setup
    book = tmp_path / "ledger.csv"
    base = ["data=tiny", f"ckpt=[{a}]", "~baselines.oidn_balanced", "~baselines.oidn_high", "metrics=[psnr]",
            "images.frame=null", f"ledger={book}", "purpose=report"]
    run(compose_eval([*base, f"data.root={root / 'data'}", f"out_dir={tmp_path / 'first'}"]))
    again = tmp_path / "again"
    shutil.copytree(root / "data", again)
    for meta in sorted((again / "test").rglob(SEQUENCE_JSON)):  # the render timings of another run
        data = json.loads(meta.read_text())
        data["render_seconds"] = {"color": 12.5, "reference": 40.25}
        data["frame_seconds"] = [{"color": 3.0}] * 4
        meta.write_text(json.dumps(data, indent=2))
    frame = sorted((again / "test").rglob("*.exr"))[1]
    frame.write_bytes(frame.read_bytes() + b"\0")  # other bytes in one frame: MC noise of another run
    run(compose_eval([*base, f"data.root={again}", f"out_dir={tmp_path / 'again_out'}"]))
    rows = ledger.read(book)
    assert [r["look"] for r in rows] == ["1", "2"] and rows[0]["split_id"] == rows[1]["split_id"]
    assert rows[0]["split_sha256"] != rows[1]["split_sha256"]  # the files' bytes differ
    told = json.loads((tmp_path / "again_out" / "evaluation.json").read_text())
    assert told["look"] == 2 and told["split_id"] == rows[0]["split_id"]
    assert "has been evaluated 2 times" in ledger.looks_line(told, book)
    # an evaluation from before the column (no split_id): the draw its hash's rows name
    first = json.loads((tmp_path / "first" / "evaluation.json").read_text())
    del first["split_id"]
    assert "has been evaluated 2 times" in ledger.looks_line(first, book)
    # another draw: one sequence's seeds changed
    other = tmp_path / "other"
    shutil.copytree(again, other)
    meta = min((other / "test").rglob(SEQUENCE_JSON))
    data = json.loads(meta.read_text())
    data["seeds"] = {"sequence": 12345}
    meta.write_text(json.dumps(data, indent=2))
    run(compose_eval([*base, f"data.root={other}", f"out_dir={tmp_path / 'other_out'}"]))
    assert ledger.read(book)[-1]["look"] == "1"


def test_a_look_at_the_test_split_needs_a_purpose_and_is_recorded(setup, tmp_path):
    """``split=test`` without ``purpose=`` is one error line and evaluates nothing; with it, each
    complete evaluation appends one ledger row (UTC date, dataset, the split's content hash, run
    ids, commit, purpose, look number) and the report says which look it is. The val split is
    not recorded; a copy of the split keeps its count (the hash, not the folder, is the split)."""
    import shutil

    from denoiser.commands.evaluate import run
    from denoiser.report import ledger
    from denoiser.report.provenance import tree_hash

    root, a, _ = setup
    book = tmp_path / "ledger.csv"
    base = ["data=tiny", f"data.root={root / 'data'}", f"ckpt=[{a}]", "~baselines.oidn_balanced",
            "~baselines.oidn_high", "metrics=[psnr]", "images.frame=null", f"ledger={book}"]
    with pytest.raises(UserError, match=r"split=test: purpose= is required\. Every look at a test split is a row"):
        run(compose_eval([*base, "purpose=", f"out_dir={tmp_path / 'none'}"]))
    assert not book.exists() and not (tmp_path / "none" / "metrics.csv").exists()
    for k in range(2):
        run(compose_eval([*base, "purpose='final judgement of recipe X'", f"out_dir={tmp_path / str(k)}"]))
    digest = tree_hash(root / "data" / "test")
    rows = ledger.read(book)
    assert [r["look"] for r in rows] == ["1", "2"] and {r["split_sha256"] for r in rows} == {digest}
    assert rows[0]["purpose"] == "final judgement of recipe X" and rows[0]["split"] == "test"
    assert rows[0]["checkpoints"] == "a.ckpt" and rows[0]["baselines"] == "noisy input;OIDN-fast"
    assert rows[0]["sequences"] == "2" and rows[0]["date"].endswith("Z") and rows[0]["commit"]
    assert "this evaluation is look 2 of 2 recorded" in (tmp_path / "1" / "metrics.md").read_text()
    # beside the tables, the provenance: the ledger row's commit, date, split, hash and look
    for k, row in enumerate(rows):
        told = json.loads((tmp_path / str(k) / "evaluation.json").read_text())
        assert told == {"commit": row["commit"], "date": row["date"], "dataset": str(root / "data"), "split": "test",
                        "split_sha256": digest, "sequences": 2, "look": k + 1, "ledger": str(book.resolve()),
                        "split_id": ledger.split_id(root / "data" / "test"),
                        "split_ids": ledger.split_ids(root / "data" / "test")}
    copy = tmp_path / "copy"
    shutil.copytree(root / "data", copy)
    shutil.copytree(copy / "test", copy / "val")
    run(compose_eval([*base, f"data.root={copy}", "split=val", "purpose=", f"out_dir={tmp_path / 'val'}"]))
    assert len(ledger.read(book)) == 2  # val: no purpose needed, no row
    told = json.loads((tmp_path / "val" / "evaluation.json").read_text())
    assert told["split"] == "val" and told["split_sha256"] == digest and told["look"] is None and told["ledger"] is None
    run(compose_eval([*base, f"data.root={copy}", "purpose=debug", f"out_dir={tmp_path / 'copy_out'}"]))
    assert ledger.read(book)[-1]["look"] == "3" and ledger.looks(digest, book) == 3
    # the demo summary of the second evaluation: its commit, its look (2) and the looks now (3)
    from denoiser.commands.tools.eval_summary import run as summarize

    (tmp_path / "report").mkdir()
    (tmp_path / "report" / "eval").symlink_to(tmp_path / "1")
    summary = summarize(compose_command("demo_summary", [f"report={tmp_path / 'report'}", f"data_root={root / 'data'}",
                                                         f"ledger={book}", "extra_evals={}"])).read_text()
    assert f"\n- commit: {rows[1]['commit']} (the evaluation's)\n" in summary
    assert (f"<!-- results:begin -->\nTest ledger: this test split (SHA-256 {digest[:12]}) has been evaluated 3 times "
            f"({book}); this summary's evaluation is look 2;") in summary
    assert ledger.run_id(Path("runs/student_s0/checkpoints/best.ckpt")) == "student_s0"
