"""Crash safety of ``denoiser-denoise``: SIGKILL after the first output frame, rerun, same pixels.

The killed-and-rerun output must equal an uninterrupted run bit for bit (the rerun replays the
recurrent history from the last reset without writing), and after the kill every file under a
final name must be a complete EXR.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.kill import kill_when

BIN = Path(sys.executable).parent
FRAMES = 24


def denoise_argv(ckpt: Path, src: Path, out: Path) -> list[str]:
    return [str(BIN / "denoiser-denoise"), f"ckpt={ckpt}", f"input={src}", f"output={out}", "threads=1",
            f"hydra.run.dir={out.parent / (out.name + '_run')}"]


def uninterrupted(ckpt: Path, src: Path, out: Path, precision: str) -> None:
    """The reference run at ``precision``, through denoiser.commands.denoise.run in this process (same
    task, saves a start-up)."""
    from hydra import compose, initialize_config_dir

    from denoiser.commands.denoise import run
    from denoiser.conf import CONF_DIR

    threads = torch.get_num_threads()
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("denoise", overrides=[*denoise_argv(ckpt, src, out)[1:-1], f"precision={precision}"])
        assert run(cfg)["written"] == FRAMES
    finally:
        torch.set_num_threads(threads)


def test_denoise_killed_and_resumed_is_identical(tmp_path):
    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config
    from denoiser.data.exr import read_channels
    from denoiser.data.synthetic import write_synthetic_sequence

    src = tmp_path / "shot"
    write_synthetic_sequence(src, frames=FRAMES, width=48, height=48, seed=5, cuts=(15,))
    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(0)
    ckpt = save_checkpoint(tmp_path / "tiny.ckpt", build_net(cfg), cfg)

    full, killed = tmp_path / "full", tmp_path / "killed"
    assert kill_when(denoise_argv(ckpt, src, killed), lambda: (killed / "frame_0000.exr").exists())
    done = sorted(killed.glob("frame_*.exr"))
    assert 1 <= len(done) < FRAMES, f"the kill came too late to test anything: {len(done)} frames"
    for f in done:  # complete files only under final names
        assert all(np.isfinite(v).all() for v in read_channels(f).values())

    proc = subprocess.run(denoise_argv(ckpt, src, killed), check=False, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    # the default precision (auto where OpenVINO is installed) was measured by the killed run and kept
    # by the resumed one; the reference runs at that precision (two fresh measurements may differ)
    record = killed / "denoise_precision.json"
    precision = json.loads(record.read_text())["precision"] if record.exists() else "f32"
    uninterrupted(ckpt, src, full, precision)
    a, b = sorted(full.glob("frame_*.exr")), sorted(killed.glob("frame_*.exr"))
    assert [p.name for p in a] == [p.name for p in b] and len(a) == FRAMES
    for fa, fb in zip(a, b):
        ca, cb = read_channels(fa), read_channels(fb)
        assert sorted(ca) == sorted(cb)
        for name in ca:
            np.testing.assert_array_equal(ca[name], cb[name], err_msg=f"{fb.name} {name}")
