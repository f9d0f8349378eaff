"""Long sequences: peak memory of ``denoiser-denoise`` at N and 10 N frames (it must stay flat).

::

    python -m denoiser.commands.tools.memory_longseq                       # 100 and 1000 frames at 64x64, net=student
    python -m denoiser.commands.tools.memory_longseq frames=[100,1000] size=64 net=student threads=2

A Hydra app over ``conf/memory_longseq.yaml``. What it does:

1. writes ``max(frames)`` synthetic 64x64 frames once into a temporary directory (real EXR
   files with every buffer and a ``sequence.json``, :mod:`denoiser.data.synthetic`); the
   shorter runs read directories holding symbolic links to the first N of them;
2. saves a checkpoint of the composed ``net`` (randomly initialized: memory and time do not
   depend on the weights) with :func:`denoiser.checkpoint.save_checkpoint`;
3. runs the real ``denoiser-denoise`` command once per length, each in its own process, and
   reads that process's peak resident set size from the kernel
   (:func:`denoiser.measure.run_process`: ``os.wait4`` -> ``ru_maxrss``): the whole command,
   Python, torch, the network, every read and write;
4. prints a Markdown table: frames, peak RSS, wall time, ms per frame, and the growth of the
   peak from the shortest to the longest run.

Flat means the peak does not grow with the number of frames: the command streams one frame at
a time (state ``[1, C, H, W]`` carried, nothing accumulated). The exit status is 1 when the
growth exceeds ``tolerance_mb`` (default 32 MiB), so the tool doubles as a check.
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path

from omegaconf import DictConfig
from tqdm import tqdm

from denoiser.commands.app import hydra_runtime
from denoiser.configs import plain
from denoiser.errors import ConfigError
from denoiser.measure import run_process
from denoiser.tables import markdown_table


def write_frames(directory: Path, frames: int, size: int, seed: int = 0) -> Path:
    """``frames`` synthetic frames ``size`` x ``size`` in ``directory`` (native layout)."""
    from denoiser.data.synthetic import write_synthetic_sequence

    write_synthetic_sequence(directory, frames=frames, width=size, height=size, seed=seed)
    return directory


def prefix_view(source: Path, directory: Path, frames: int) -> Path:
    """A sequence directory holding links to the first ``frames`` frames of ``source``."""
    from denoiser.data.sequence import load_sequence_json, write_sequence_json

    meta = load_sequence_json(source).to_json()
    meta.update(frames=frames, cameras=meta["cameras"][:frames], cuts=[c for c in meta["cuts"] if c < frames])
    directory.mkdir(parents=True, exist_ok=True)
    for t in range(frames):
        name = f"frame_{t:04d}.exr"
        os.symlink(source / name, directory / name)
    write_sequence_json(directory, meta)
    return directory


def make_checkpoint(path: Path, net: str | Mapping) -> Path:
    """A checkpoint with random weights of ``net``: a ``conf/net`` name or a resolved net config."""
    import torch

    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config

    cfg = compose_net_config(net) if isinstance(net, str) else dict(net)
    torch.manual_seed(0)
    return save_checkpoint(path, build_net(cfg), cfg)


def denoise_run(ckpt: Path, source: Path, output: Path, threads: int | None) -> dict:
    """Run ``denoiser-denoise`` on ``source``; its peak RSS (MiB) and wall seconds."""
    argv = [sys.executable, "-m", "denoiser.commands.denoise", f"ckpt={ckpt}", f"input={source}", f"output={output}",
            f"hydra.run.dir={output.parent / (output.name + '_run')}"]
    if threads:
        argv.append(f"threads={threads}")
    proc = run_process(argv)
    if proc.returncode != 0:
        raise RuntimeError(f"denoiser-denoise failed ({proc.returncode}): {proc.stderr[-2000:]}")
    written = len(list(output.glob("frame_*.exr")))
    return {"peak_rss_mib": proc.peak_mb, "seconds": proc.wall, "written": written}


def measure_lengths(frames: list[int], size: int, net: str | Mapping, threads: int | None,
                    workdir: Path | None = None) -> list[dict]:
    """Measure every length in ``frames``; returns one row per length."""
    with tempfile.TemporaryDirectory(prefix="longseq-", dir=workdir) as tmp:
        tmp = Path(tmp)
        longest = max(frames)
        tic = time.perf_counter()
        source = write_frames(tmp / f"frames_{longest}", longest, size)
        print(f"wrote {longest} frames of {size}x{size} in {time.perf_counter() - tic:.1f} s", file=sys.stderr)
        ckpt = make_checkpoint(tmp / "net.ckpt", net)
        rows = []
        for n in tqdm(sorted(frames), desc="longseq", unit="run"):
            src = source if n == longest else prefix_view(source, tmp / f"frames_{n}", n)
            result = denoise_run(ckpt, src, tmp / f"out_{n}", threads)
            if result["written"] != n:
                raise RuntimeError(f"expected {n} output frames, found {result['written']}")
            rows.append({"frames": n, **result, "ms_per_frame": 1000.0 * result["seconds"] / n})
        return rows


def table(rows: list[dict], size: int, net: str) -> str:
    """The Markdown report: one row per length, then the growth of the peak."""
    growth = rows[-1]["peak_rss_mib"] - rows[0]["peak_rss_mib"]
    return "\n".join([
        f"denoiser-denoise, net={net}, {size}x{size} frames, peak RSS of the whole process (ru_maxrss)", "",
        markdown_table(rows, ["frames", "peak_rss_mib", "seconds", "ms_per_frame"],
                       {"peak_rss_mib": ".1f", "seconds": ".1f", "ms_per_frame": ".1f"},
                       {"peak_rss_mib": "peak RSS MiB", "seconds": "wall s", "ms_per_frame": "ms/frame (incl. start-up)"}),
        f"peak RSS growth from {rows[0]['frames']} to {rows[-1]['frames']} frames: {growth:+.1f} MiB"])


def run(cfg: DictConfig) -> list[dict]:
    """The ``memory_longseq`` task: prints the table; exit status 1 when the peak grew by more than
    ``tolerance_mb``. Returns the rows."""
    frames = [int(n) for n in cfg.frames]
    if len(frames) < 2 or min(frames) < 1:
        raise ConfigError(f"frames: needs at least two positive lengths, got {frames}")
    rows = measure_lengths(frames, int(cfg.size), plain(cfg.net), cfg.get("threads"),
                           Path(cfg.workdir) if cfg.get("workdir") else None)
    print(table(rows, int(cfg.size), hydra_runtime()[1].get("net", "(composed)")))
    growth = rows[-1]["peak_rss_mib"] - rows[0]["peak_rss_mib"]
    if growth > float(cfg.tolerance_mb):
        print(f"error: peak RSS grew by {growth:.1f} MiB > {cfg.tolerance_mb} MiB", file=sys.stderr)
        sys.exit(1)
    return rows


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "memory_longseq")()


if __name__ == "__main__":
    main()
