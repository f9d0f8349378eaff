"""``denoiser-adapt`` (issue 67): a tiny student adapted toward a tiny teacher on a 32x32 sequence's
noisy frames comes closer to it on the held-out frames, the result loads with ``denoiser-denoise``
and a run goes on from its last.ckpt; a bad learning rate keeps the start student and says so; bad
input is one line and no checkpoint; 1080p frames are cropped (the batches' shapes)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command
from helpers.eval_data import write_sequence

from denoiser.data.exr import write_frame
from denoiser.errors import UserError


def adapt(overrides):
    from denoiser.commands.adapt import run

    return run(compose_command("adapt", overrides))  # torch threads: the worker's share (tests/conftest.py)


def nets(tmp_path: Path) -> list[str]:
    student = tiny_checkpoint(tmp_path / "student0.ckpt", seed=0)
    teacher = tiny_checkpoint(tmp_path / "teacher.ckpt", seed=1)
    return [f"student={student}", f"teacher={teacher}", "mix=0", "window=2", "crop=32", "checkpoint_every=2"]


def net_weights(path: Path) -> dict[str, torch.Tensor]:
    from denoiser.checkpoint import net_state_dict, read_checkpoint

    return net_state_dict(read_checkpoint(path), path)


def test_adapt_closes_the_gap_resumes_and_denoise_takes_the_result(tmp_path, capsys):
    seq = write_sequence(tmp_path / "shot", frames=8, size=32)
    out = tmp_path / "adapted"
    record = adapt([f"input={seq}", f"out={out}", *nets(tmp_path), "steps=6", "optimizer.lr=3e-3"])
    printed = capsys.readouterr()
    assert record["kept"] == "adapted" and record["steps"] == 6
    assert record["gap_after_db"] > record["gap_before_db"], record
    assert json.loads((out / "adapt.json").read_text())["gap_after_db"] == pytest.approx(record["gap_after_db"])
    assert "gap before" in printed.out and "gap after 6 step(s)" in printed.out
    assert record["train_frames"] == 6 and record["heldout_frames"] == 2  # the last frames held out
    assert (out / "run" / "checkpoints" / "last.ckpt").is_file()
    adapted = net_weights(out / "student.ckpt")
    start = net_weights(tmp_path / "student0.ckpt")
    assert any(not torch.equal(adapted[k], start[k]) for k in start)

    # the same command with a larger budget goes on from run/checkpoints/last.ckpt
    again = adapt([f"input={seq}", f"out={out}", *nets(tmp_path), "steps=8", "optimizer.lr=3e-3"])
    assert again["steps"] == 8 and "resuming from" in capsys.readouterr().err

    from denoiser.commands.denoise import run as denoise

    counts = denoise(compose_command("denoise", [f"ckpt={out / 'student.ckpt'}", f"input={seq}",
                                                 f"output={tmp_path / 'denoised'}", "backend=eager", "report=false"]))
    assert counts["written"] == 8 and len(list((tmp_path / "denoised").glob("frame_*.exr"))) == 8


def test_a_bad_learning_rate_keeps_the_start_student_and_says_so(tmp_path, capsys):
    seq = write_sequence(tmp_path / "shot", frames=6, size=32)
    out = tmp_path / "adapted"
    record = adapt([f"input={seq}", f"out={out}", *nets(tmp_path), "steps=3", "optimizer.lr=50"])
    printed = capsys.readouterr().out
    assert record["kept"] == "start", record
    assert "kept the start student" in printed
    kept, start = net_weights(out / "student.ckpt"), net_weights(tmp_path / "student0.ckpt")
    assert all(torch.equal(kept[k], start[k]) for k in start)


def test_missing_passes_or_no_frames_is_one_line_and_no_checkpoint(tmp_path):
    flat = tmp_path / "color_only"
    flat.mkdir()
    color = np.ones((32, 32, 3), np.float32)
    for t in range(6):
        write_frame(flat / f"frame_{t:04d}.exr", {"color": color})
    empty = tmp_path / "empty"
    empty.mkdir()
    for folder, words in ((flat, "albedo"), (empty, "no frame")):
        out = tmp_path / f"out_{folder.name}"
        with pytest.raises(UserError) as err:
            adapt([f"input={folder}", f"out={out}", *nets(tmp_path), "steps=2"])
        assert words in str(err.value) and str(folder) in str(err.value) and "\n" not in str(err.value)
        assert not (out / "student.ckpt").exists()


def test_1080p_frames_are_cropped(tmp_path):
    """A 1920x1080 sequence trains and is checked on 96x96 crops: the batches are
    ``[B, window, C, 96, 96]`` and the held-out items ``[1, T, C, 96, 96]``."""
    from denoiser.configs import load_layout
    from denoiser.lit.adapt import crop_size, heldout_items, own_windows, split_frames, train_loader

    seq = write_sequence(tmp_path / "hd", frames=4, size=(1080, 1920))
    layout = load_layout("native")
    source = layout.open_sequence(seq)
    train, heldout = split_frames(source.frames, 2, 0.25)
    hw = crop_size(source, 96)
    assert hw == (96, 96) and (train, heldout) == (2, 2)
    own = own_windows(source, layout, 2, train, hw, fill_reference=False)
    batch = next(iter(train_loader(own, None, 0.0, 2)))
    assert tuple(batch["color"].shape) == (2, 2, 3, 96, 96) and tuple(batch["depth"].shape) == (2, 2, 1, 96, 96)
    items = heldout_items(own, source, train, hw, crops=4)
    assert len(items) == 4 and all(tuple(i["color"].shape) == (1, 2, 3, 96, 96) for i in items)
    assert len({float(i["color"].sum()) for i in items}) > 1  # four places of the frame, not one
    record = adapt([f"input={seq}", f"out={tmp_path / 'out'}", *nets(tmp_path), "crop=96", "steps=1"])
    assert record["crop"] == [96, 96] and record["size"] == [1080, 1920]
