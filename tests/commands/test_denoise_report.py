"""``denoiser-denoise``'s report: report.json and report.md with the flicker (warp error) of the
input and the output frame by frame, frames/s, backend and precision, and the plot flicker.png."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command
from helpers.eval_data import write_sequence
from helpers.flicker_data import write_blender_sequence

from denoiser.data import exr
from denoiser.report.flicker import warp_error


def denoise(overrides):
    from denoiser.commands.denoise import run

    return run(compose_command("denoise", [*overrides, "precision=f32", "backend=eager"], threads=1))


def test_report_and_plot_of_a_native_sequence(tmp_path):
    seq = write_sequence(tmp_path / "shot", frames=5, size=(24, 31), cuts=(3,), seed=2)
    ckpt = tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "out"
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={out}"])
    record = json.loads((out / "report.json").read_text())
    assert record["backend"] == "eager" and record["precision"] == "fp32" and record["frames"] == 5
    assert record["frames_per_second"] > 0 and 0 < record["measure_share"] < 1
    assert record["frame_numbers"] == [1, 2, 3, 4, 5] and record["stride"] == 1  # a small frame: every pixel
    fl = record["flicker"]
    assert fl["mask"] == "guide"
    assert fl["input"]["per_frame"][0] is None and fl["input"]["per_frame"][3] is None  # first frame, the cut
    # the input's values are the in-memory measure of the frames as read back from the files
    names = {"color": ["color.R", "color.G", "color.B"], "motion": ["motion.X", "motion.Y"],
             "albedo": ["albedo.R", "albedo.G", "albedo.B"], "normal": ["normal.X", "normal.Y", "normal.Z"],
             "depth": ["depth.Z"]}
    items = [exr.read_frame(seq / f"frame_{t:04d}.exr", names)[0] for t in range(5)]
    stack = {k: torch.stack([torch.from_numpy(it[k].transpose(2, 0, 1).copy()) for it in items]) for k in names}
    expected = warp_error(stack["color"], stack["motion"], aux=stack, reset=[t == 3 for t in range(5)])
    got = [math.nan if v is None else v for v in fl["input"]["per_frame"]]
    np.testing.assert_allclose(got, expected.per_frame, rtol=1e-5)
    assert fl["input"]["mean"] == pytest.approx(expected.mean, rel=1e-5) and fl["output"]["mean"] > 0
    md = (out / "report.md").read_text()
    assert "warp err ×1e3" in md and "| 5 |" in md and "flicker.png" in md and "frames/s" in md
    assert (out / "flicker.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_blender_input_uses_both_motion_directions(tmp_path):
    seq = write_blender_sequence(tmp_path / "cycles", frames=3, reference=False)
    ckpt = tiny_checkpoint(tmp_path / "tiny.ckpt")
    out = tmp_path / "out"
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={out}", "layout=blender", "write=rgb"])
    record = json.loads((out / "report.json").read_text())
    assert record["flicker"]["mask"] == "forward-backward" and record["flicker"]["output"]["mean"] is not None
    assert sorted(p.name for p in out.glob("*.exr")) == ["0001.exr", "0002.exr", "0003.exr"]


def test_the_report_stride_keeps_the_cost_per_frame_bounded():
    from denoiser.commands.denoise import auto_stride

    assert auto_stride(24, 31) == 1 and auto_stride(181, 181) == 1 and auto_stride(1080, 1920) == 8
    assert auto_stride(2160, 3840) == 16
