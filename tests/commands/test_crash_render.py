"""Crash safety of ``denoiser-render``: SIGKILL after the first frame appeared, rerun, same pixels.

An uninterrupted render and a render killed (SIGKILL, no chance to clean up) and then rerun with
the same command must give identical EXR pixels in every channel of every frame, because every
pass has a deterministic seed. After the kill, every file under a final name must be complete
(frames readable in full, ``sequence.json`` valid): writes go to a temporary name first.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
from helpers.kill import kill_when

BIN = Path(sys.executable).parent
FRAMES = 6
#: small but not instant frames (scalar_rgb: no JIT compile at start-up)
RENDER = ["scene=cornell", "split=train", f"frames={FRAMES}", "width=24", "height=24", "spp=2", "ref_spp=24",
          "variant=scalar_rgb", "seed=3"]


def render(root: Path) -> None:
    proc = subprocess.run([str(BIN / "denoiser-render"), *RENDER, f"root={root}"], check=False, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]


def frames_of(seq: Path) -> list[Path]:
    return sorted(seq.glob("frame_*.exr"))


def test_render_killed_and_resumed_is_identical(tmp_path):
    from denoiser.data.exr import read_channels
    from denoiser.data.sequence import load_sequence_json

    full, killed = tmp_path / "full", tmp_path / "killed"
    seq_full, seq_killed = full / "train" / "cornell_000", killed / "train" / "cornell_000"
    render(full)

    assert kill_when([str(BIN / "denoiser-render"), *RENDER, f"root={killed}"],
                     lambda: (seq_killed / "frame_0000.exr").exists())
    done = frames_of(seq_killed)
    assert 1 <= len(done) < FRAMES, f"the kill came too late to test anything: {len(done)} frames"
    print(f"killed after {len(done)} of {FRAMES} frames")
    for f in done:  # everything under a final name is complete
        channels = read_channels(f)
        assert all(np.isfinite(v).all() for v in channels.values())
    if (seq_killed / "sequence.json").exists():
        load_sequence_json(seq_killed / "sequence.json")

    render(killed)  # the same command resumes
    a, b = frames_of(seq_full), frames_of(seq_killed)
    assert [p.name for p in a] == [p.name for p in b] == [f"frame_{t:04d}.exr" for t in range(FRAMES)]
    for fa, fb in zip(a, b):
        ca, cb = read_channels(fa), read_channels(fb)
        assert sorted(ca) == sorted(cb)
        for name in ca:
            np.testing.assert_array_equal(ca[name], cb[name], err_msg=f"{fb.name} {name}")
    ja, jb = (json.loads((s / "sequence.json").read_text()) for s in (seq_full, seq_killed))
    for volatile in ("render_seconds", "frame_seconds"):
        ja.pop(volatile), jb.pop(volatile)
    assert ja == jb
    assert jb["frames_done"] == FRAMES
