"""denoiser-eval reports the flicker without a reference (``warp``) for every method beside tPSNR,
the reference's own value (``warp_ref``) as the floor, in every table; the summaries' paired claims
take it."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command
from helpers.eval_data import write_dataset

from denoiser.data.exr import read_frame
from denoiser.report.flicker import warp_error
from denoiser.report.seed_groups import claim_lines, group_sequences, sequence_values
from denoiser.tables import read_csv

NAMES = {"color": ["color.R", "color.G", "color.B"], "reference": ["reference.R", "reference.G", "reference.B"],
         "motion": ["motion.X", "motion.Y"], "albedo": ["albedo.R", "albedo.G", "albedo.B"],
         "normal": ["normal.X", "normal.Y", "normal.Z"], "depth": ["depth.Z"]}


def test_eval_reports_warp_error_and_the_reference_floor(tmp_path):
    from denoiser.commands.evaluate import run

    root = write_dataset(tmp_path / "data", sequences=2, frames=4, size=24)
    ckpt = tiny_checkpoint(tmp_path / "s.ckpt")
    out = tmp_path / "out"
    run(compose_command("eval", ["data=tiny", f"data.root={root}", f"ckpt={{student: {ckpt}}}", f"out_dir={out}",
                                 "~baselines.oidn_balanced", "~baselines.oidn_high", "metrics=[psnr,tpsnr,warp]",
                                 "warmup=0", "images.frame=null"], threads=1))
    rows = [r for r in read_csv(out / "metrics.csv") if r["sequence"] != "mean"]
    assert {r["method"] for r in rows} == {"noisy input", "OIDN-fast", "student"}
    for seq in ("test/seq_000", "test/seq_001"):
        per = {r["method"]: r for r in rows if r["sequence"] == seq}
        assert len({per[m]["warp_ref"] for m in per}) == 1  # one floor per sequence, whatever the method
        assert per["noisy input"]["warp"] > per["OIDN-fast"]["warp"] > per["noisy input"]["warp_ref"] >= 0
    # the noisy input's value is the measure of its frames as read back from the files
    items = [read_frame(root / "test/seq_000" / f"frame_{t:04d}.exr", NAMES)[0] for t in range(4)]
    stack = {k: torch.stack([torch.from_numpy(it[k].transpose(2, 0, 1).copy()) for it in items]) for k in NAMES}
    noisy = next(r for r in rows if r["method"] == "noisy input" and r["sequence"] == "test/seq_000")
    assert noisy["warp"] == pytest.approx(warp_error(stack["color"], stack["motion"], aux=stack).mean, rel=1e-5)
    assert noisy["warp_ref"] == pytest.approx(warp_error(stack["reference"], stack["motion"], aux=stack).mean,
                                              rel=1e-5)
    frames = read_csv(out / "frames.csv")
    assert math.isnan(frames[0]["warp"]) and not math.isnan(frames[1]["warp_ref"])
    md = (out / "metrics.md").read_text()
    assert md.count("warp err ×1e3 ↓") == 3 and md.count("warp err of reference ×1e3 ↓") == 3  # overall, scene, seq
    lines = claim_lines([{"network": "student", "baseline": "OIDN-fast", "metrics": ["warp"]}],
                        group_sequences(sequence_values(read_csv(out / "metrics.csv"))))
    sentence = next(line for line in lines if line.startswith("- student"))
    assert "on warp err ×1e3:" in sentence and "2 sequences" in sentence
    row = next(line for line in "\n".join(lines).splitlines() if line.startswith("| student"))
    assert np.isfinite(float(row.split("|")[4].split()[0]))
