"""The history diagnosis (denoiser/report/history_diagnosis.py, denoiser/commands/tools/diagnose_history.py) and the
temporal probe it reads (denoiser/nn/temporal.py): the probe changes nothing, the captured
weights are the network's, the regions and statistics match a plain per-pixel computation."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from denoiser.checkpoint import load_denoiser, save_checkpoint
from denoiser.configs import build_net, compose_net_config
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import ConfigError, UserError
from denoiser.frames import random_frame
from denoiser.recurrent import RecurrentRunner
from denoiser.report.history_diagnosis import EDGE_PX, Capture, diagnose, regions, statistics

ROOT = Path(__file__).resolve().parents[2]
FIXTURE = ROOT / "tests" / "fixtures" / "student_v0.ckpt"
SIZE = 32


def gated_net():
    """The tiny net with the disocclusion gate on (the fixture checkpoint predates the gate)."""
    torch.manual_seed(0)
    cfg = compose_net_config("tiny", overrides=["+net.temporal.reject_threshold=0.1"])
    return build_net(cfg).eval(), cfg


def run(net, frames, probe: bool):
    net.temporal.probe = {} if probe else None
    runner = RecurrentRunner(net.step)
    recorded = []
    with torch.no_grad():
        for out in runner.run((f, i == 0) for i, f in enumerate(frames)):
            recorded.append((out, dict(runner.state), runner.extras[0]["weights"],
                             dict(net.temporal.probe) if probe else None))
    net.temporal.probe = None
    return recorded


@pytest.mark.parametrize("which", ["fixture", "gated"])
def test_probe_changes_nothing_and_records_the_factors_of_valid(which):
    net = load_denoiser(FIXTURE) if which == "fixture" else gated_net()[0]
    frames = [random_frame(1, SIZE, SIZE, seed=s, kind="hard") for s in range(3)]
    for f in frames[1:]:
        f["motion"] = torch.full_like(f["motion"], 3.0)  # every pixel moves: partial coverage at the border
    off, on = run(net, frames, probe=False), run(net, frames, probe=True)
    for (out0, state0, w0, _), (out1, state1, w1, probe) in zip(off, on):
        assert torch.equal(out0, out1)
        assert all(torch.equal(state0[k], state1[k]) for k in state0)
        assert all(torch.equal(w0[k], w1[k]) for k in w0)
        for key in ("cover", "gate"):
            assert probe[key].shape == (1, 1, SIZE, SIZE)
            assert float(probe[key].min()) >= 0.0 and float(probe[key].max()) <= 1.0
        torch.testing.assert_close(w1["valid"], probe["cover"] * probe["gate"], rtol=0, atol=1e-7)
    last = on[-1][3]
    assert 0.0 < float(last["cover"].mean()) < 1.0          # the 3 px shift leaves the border uncovered
    if which == "fixture":
        assert torch.equal(last["gate"], torch.ones_like(last["gate"]))   # no gate in that config
    else:
        assert float(last["gate"].min()) < 1.0               # random guides disagree: the gate rejects
    assert net.temporal.probe is None


def test_diagnose_writes_the_grid_and_the_table(tmp_path):
    seq = tmp_path / "seq"
    write_synthetic_sequence(seq, frames=4, width=SIZE, height=SIZE, seed=3)
    net, cfg = gated_net()
    ckpt = save_checkpoint(tmp_path / "gated.ckpt", net, cfg)
    result = diagnose(ckpt, seq, "native", tmp_path / "out", progress=False)
    assert result["frame"] >= 2
    cap = result["capture"]
    for name in ("history_in", "history_out", "gate", "cover"):
        w = cap.weights[name]
        assert w.shape == (1, 1, SIZE, SIZE) and bool(torch.isfinite(w).all())
        assert float(w.min()) >= 0.0 and float(w.max()) <= 1.0
    assert float(cap.weights["history_out"].max()) > 0.0     # history is used on this frame
    for name in ("noisy", "output", "reference", "warped history"):
        assert cap.images[name].shape == (1, 3, SIZE, SIZE)
    with Image.open(result["png"]) as im:
        assert im.format == "PNG" and im.width > 4 * SIZE and im.height > 3 * SIZE
    text = result["markdown"].read_text()
    for region in ("all", "background", "edge", "interior", "uncovered", "warped right", "warped wrong", "gate < 1"):
        assert f"| {region} |" in text
    everything = next(r for r in result["rows"] if r["region"] == "all")
    assert everything["pixels"] == SIZE * SIZE and np.isfinite(everything["psnr_output"])


def test_script_runs_with_the_fixture_checkpoint_and_reports_bad_input(tmp_path):
    seq = tmp_path / "seq"
    write_synthetic_sequence(seq, frames=3, width=SIZE, height=SIZE, seed=1)
    command = [sys.executable, "-m", "denoiser.commands.tools.diagnose_history"]
    ok = subprocess.run([*command, f"ckpt={FIXTURE}", f"sequence={seq}", "frame=1",
                         f"out={tmp_path / 'out'}"], check=False, capture_output=True, text=True, cwd=ROOT)
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "out" / "seq_f1.png").is_file() and (tmp_path / "out" / "seq_f1.md").is_file()
    bad = subprocess.run([*command, "--ckpt", str(FIXTURE), "--sequence", str(seq),
                          "--layout", "exr"], check=False, capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 2 and bad.stderr.strip().count("\n") == 0 and "layout" in bad.stderr


def test_a_network_without_recurrence_is_refused(tmp_path):
    seq = tmp_path / "seq"
    write_synthetic_sequence(seq, frames=3, width=SIZE, height=SIZE, seed=1)
    cfg = compose_net_config("tiny", overrides=["net.temporal=null"])
    with pytest.raises(UserError, match="no temporal recurrence"):
        diagnose(None, seq, "native", tmp_path, net=build_net(cfg).eval(), progress=False)
    with pytest.raises(ConfigError, match="layout: unknown"):
        diagnose(None, seq, "exr", tmp_path, net=build_net(cfg).eval(), progress=False)


def _plain_regions(moving: np.ndarray, prev_moving: np.ndarray, r: int):
    """Per-pixel loops: edge = a moving and a still pixel both within Chebyshev distance r."""
    h, w = moving.shape
    edge = np.zeros_like(moving)
    for y in range(h):
        for x in range(w):
            win = moving[max(0, y - r):y + r + 1, max(0, x - r):x + r + 1]
            edge[y, x] = win.any() and not win.all()
    return {"edge": edge, "interior": moving & ~edge, "background": ~moving & ~edge,
            "uncovered": ~moving & prev_moving}


def test_regions_and_statistics_against_a_plain_computation():
    h = w = 20
    motion = torch.zeros(1, 2, h, w)
    motion[:, 0, 6:12, 8:14] = 3.0                # an object 6x6 px moving left by 3 px per frame
    previous = torch.zeros(1, 2, h, w)
    previous[:, 0, 6:12, 11:17] = 3.0             # where it was at t-1
    reference = torch.full((1, 3, h, w), 0.5)
    noisy = reference + 0.05 * torch.from_numpy(np.indices((h, w)).sum(0) % 2 * 2 - 1.0).float()
    warped = reference.clone()
    warped[..., 6:12, 14:17] = 4.0                # stale object colour left on the uncovered background
    a = torch.full((1, 1, h, w), 0.7)
    a[..., 6:12, 14:17] = 0.2
    cap = Capture(frame=2, images={"noisy": noisy, "output": reference.clone(), "reference": reference,
                                   "warped history": warped},
                  weights={"history_in": a, "history_out": a.clone(), "gate": torch.ones(1, 1, h, w),
                           "cover": torch.ones(1, 1, h, w)},
                  motion=motion, previous_motion=previous)
    got = {k: v[0, 0].numpy() for k, v in regions(cap).items()}
    expected = _plain_regions(motion[0].norm(dim=0).numpy() > 0.5, previous[0].norm(dim=0).numpy() > 0.5, EDGE_PX)
    for name, mask in expected.items():
        np.testing.assert_array_equal(got[name], mask, err_msg=name)
    stale = np.zeros((h, w), bool)
    stale[6:12, 14:17] = True
    np.testing.assert_array_equal(got["warped wrong"], stale)
    np.testing.assert_array_equal(got["uncovered"], stale)
    rows = {r["region"]: r for r in statistics(cap)}
    assert rows["warped wrong"]["pixels"] == 18 and rows["warped wrong"]["a"] == pytest.approx(0.2)
    assert rows["warped right"]["a"] == pytest.approx(0.7) and rows["warped right"]["keep_b"] == 1.0
    assert rows["gate < 1"]["pixels"] == 0
    assert rows["uncovered"]["psnr_warped"] < rows["interior"]["psnr_warped"]
