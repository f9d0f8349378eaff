"""Long sequences: peak memory of ``denoiser-denoise`` at N and 10 N frames (it must stay flat).

::

    python -m denoiser.commands.bench_longseq                              # 100 and 1000 frames at 64x64, net=student
    python -m denoiser.commands.bench_longseq --frames 100 1000 --size 64 --net student --threads 2

What it does:

1. writes ``max(frames)`` synthetic 64x64 frames once into a temporary directory (real EXR
   files with every buffer and a ``sequence.json``, :mod:`denoiser.data.synthetic`); the
   shorter runs read directories holding symbolic links to the first N of them;
2. saves a checkpoint of ``net`` (randomly initialized: memory and time do not depend on
   the weights) with :func:`denoiser.checkpoint.save_checkpoint`;
3. runs the real ``denoiser-denoise`` command once per length, each in its own process, and
   reads that process's peak resident set size from the kernel (``os.wait4`` ->
   ``ru_maxrss``): the whole command, Python, torch, the network, every read and write;
4. prints a Markdown table: frames, peak RSS, wall time, ms per frame, and the growth of the
   peak from the shortest to the longest run.

Flat means the peak does not grow with the number of frames: the command streams one frame at
a time (state ``[1, C, H, W]`` carried, nothing accumulated). The exit status is 1 when the
growth exceeds ``--tolerance-mb`` (default 32 MiB), so the script doubles as a check.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from tqdm import tqdm


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


def make_checkpoint(path: Path, net: str) -> Path:
    """A checkpoint of ``conf/net/<net>.yaml`` with random weights."""
    import torch

    from denoiser.checkpoint import build_net, compose_net_config, save_checkpoint

    cfg = compose_net_config(net)
    torch.manual_seed(0)
    return save_checkpoint(path, build_net(cfg), cfg)


def measure(ckpt: Path, source: Path, output: Path, threads: int | None) -> dict:
    """Run ``denoiser-denoise`` on ``source``; its peak RSS (MiB) and wall seconds."""
    argv = [sys.executable, "-m", "denoiser.commands.denoise", f"ckpt={ckpt}", f"input={source}", f"output={output}",
            f"hydra.run.dir={output.parent / (output.name + '_run')}"]
    if threads:
        argv.append(f"threads={threads}")
    start = time.perf_counter()
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    stderr = proc.stderr.read()  # drained while it runs (progress bars), so the pipe never blocks
    _, status, usage = os.wait4(proc.pid, 0)
    seconds = time.perf_counter() - start
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise RuntimeError(f"denoiser-denoise failed ({proc.returncode}): {stderr.decode()[-2000:]}")
    written = len(list(output.glob("frame_*.exr")))
    return {"peak_rss_mib": usage.ru_maxrss / 1024.0, "seconds": seconds, "written": written}


def run(frames: list[int], size: int, net: str, threads: int | None, workdir: Path | None = None) -> list[dict]:
    """Measure every length in ``frames``; returns one row per length."""
    with tempfile.TemporaryDirectory(prefix="longseq-", dir=workdir) as tmp:
        tmp = Path(tmp)
        longest = max(frames)
        tic = time.perf_counter()
        source = write_frames(tmp / f"frames_{longest}", longest, size)
        print(f"wrote {longest} frames of {size}x{size} in {time.perf_counter() - tic:.1f} s", file=sys.stderr)
        ckpt = make_checkpoint(tmp / f"{net}.ckpt", net)
        rows = []
        for n in tqdm(sorted(frames), desc="longseq", unit="run"):
            src = source if n == longest else prefix_view(source, tmp / f"frames_{n}", n)
            result = measure(ckpt, src, tmp / f"out_{n}", threads)
            if result["written"] != n:
                raise RuntimeError(f"expected {n} output frames, found {result['written']}")
            rows.append({"frames": n, **result, "ms_per_frame": 1000.0 * result["seconds"] / n})
        return rows


def table(rows: list[dict], size: int, net: str) -> str:
    lines = [f"denoiser-denoise, net={net}, {size}x{size} frames, peak RSS of the whole process (ru_maxrss)", "",
             "| frames | peak RSS MiB | wall s | ms/frame (incl. start-up) |", "|---:|---:|---:|---:|"]
    lines += [f"| {r['frames']} | {r['peak_rss_mib']:.1f} | {r['seconds']:.1f} | {r['ms_per_frame']:.1f} |" for r in rows]
    growth = rows[-1]["peak_rss_mib"] - rows[0]["peak_rss_mib"]
    lines += ["", f"peak RSS growth from {rows[0]['frames']} to {rows[-1]['frames']} frames: {growth:+.1f} MiB"]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m denoiser.commands.bench_longseq", description=__doc__.split("\n\n")[0])
    parser.add_argument("--frames", type=int, nargs="+", default=[100, 1000], help="sequence lengths to measure")
    parser.add_argument("--size", type=int, default=64, help="frame width and height in pixels")
    parser.add_argument("--net", default="student", help="conf/net/<name>.yaml of the checkpoint")
    parser.add_argument("--threads", type=int, default=None, help="torch threads of denoiser-denoise")
    parser.add_argument("--tolerance-mb", type=float, default=32.0, help="allowed peak RSS growth (MiB)")
    parser.add_argument("--workdir", type=Path, default=None, help="where the temporary frames go")
    args = parser.parse_args(argv)
    if len(args.frames) < 2 or min(args.frames) < 1:
        parser.error("--frames needs at least two positive lengths")
    rows = run(args.frames, args.size, args.net, args.threads, args.workdir)
    print(table(rows, args.size, args.net))
    growth = rows[-1]["peak_rss_mib"] - rows[0]["peak_rss_mib"]
    if growth > args.tolerance_mb:
        print(f"error: peak RSS grew by {growth:.1f} MiB > {args.tolerance_mb} MiB", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
