"""Long sequences: the peak RSS of ``denoiser-denoise`` does not grow with the number of frames.

A small version of ``python -m denoiser.commands.tools.memory_longseq`` (which measures 100 vs 1000 frames at 64x64
with the student): 20 vs 150 frames at 64x64 with ``net=tiny``, each run a real
``denoiser-denoise`` process whose peak RSS comes from the kernel. Keeping every frame's input
buffers (15 float32 channels, 240 KiB a frame) would add about 35 MiB over 150 frames, far
above the tolerance; so would keeping outputs with their autograd graphs.
"""

from __future__ import annotations

import pytest

from denoiser.commands.tools.memory_longseq import measure_lengths, table

TOLERANCE_MIB = 16.0


@pytest.mark.slow
def test_peak_memory_is_flat_over_sequence_length(tmp_path):
    rows = measure_lengths([20, 150], size=64, net="tiny", threads=1, workdir=tmp_path)
    print("\n" + table(rows, 64, "tiny"))
    assert [r["frames"] for r in rows] == [20, 150]
    assert [r["written"] for r in rows] == [20, 150]
    assert rows[0]["peak_rss_mib"] > 50  # a real measurement of a process that imported torch
    assert rows[1]["peak_rss_mib"] - rows[0]["peak_rss_mib"] < TOLERANCE_MIB, rows
