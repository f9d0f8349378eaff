"""Data benchmark: frames/s of the data module, decoding EXR (cold) vs from the frame cache (warm).

``python -m denoiser.commands.bench_data [--size 512 --crop 128 --window 8 --sequences 2 --frames 16]``

Writes synthetic native-layout sequences (:mod:`denoiser.data.synthetic`, all buffers plus
reference, float32, zip) into a temporary directory, composes ``conf/data/default.yaml`` with
Hydra (root, cache and worker overrides) and times whole training epochs of the real
``SequenceDataModule.train_dataloader()`` (random crops, default augmentation):

* ``cold``: ``cache_dir=null``, every frame read decodes its EXR;
* ``fill``: first epoch with an empty cache (decode + write the float32 .npy entries);
* ``warm``: later epochs (median of ``--repeat``), every frame read fetches only its crop's rows
  from the cache.

frames/s counts frames delivered (windows x T). Each loader uses persistent workers; the
timed epoch includes worker start-up only for its first epoch (``cold``, ``fill``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from tqdm.auto import tqdm

from denoiser.commands.app import report_user_error
from denoiser.conf import CONF_DIR
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import UserError


def make_dataset(root: Path, sequences: int, frames: int, size: int) -> None:
    for i in tqdm(range(sequences), desc="write sequences", unit="seq"):
        write_synthetic_sequence(root / "train" / f"seq{i:02d}", frames=frames, width=size, height=size, seed=i)


def build(root: Path, cache: Path | None, workers: int, window: int, crop: int, batch: int):
    overrides = ["+data=default", f"data.root={root}", f"data.num_workers={workers}",
                 f"data.persistent_workers={workers > 0}", f"data.window={window}", f"data.crop={crop}",
                 f"data.batch_size={batch}", "data.val_split=null", "data.test_split=null",
                 f"data.cache_dir={cache if cache else 'null'}"]
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(overrides=overrides)
    dm = instantiate(cfg.data)
    dm.setup("fit")
    return dm.train_dataloader()


def epoch(loader) -> tuple[int, float]:
    """Frames delivered by one pass over ``loader`` and the seconds it took."""
    t0 = time.perf_counter()
    frames = 0
    for batch in loader:
        frames += batch["color"].shape[0] * batch["color"].shape[1]
    return frames, time.perf_counter() - t0


def run(size: int, crop: int, window: int, sequences: int, frames: int, workers: list[int], batch: int,
        repeat: int = 3) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="denoiser-bench-") as tmp:
        root = Path(tmp) / "data"
        make_dataset(root, sequences, frames, size)
        for w in workers:
            loader = build(root, None, w, window, crop, batch)
            n, s = epoch(loader)
            rows.append({"mode": "cold (decode EXR)", "workers": w, "frames": n, "seconds": s})
            cold = n / s
            loader = build(root, Path(tmp) / f"cache{w}", w, window, crop, batch)
            n, s = epoch(loader)
            rows.append({"mode": "fill (decode + write cache)", "workers": w, "frames": n, "seconds": s})
            runs = [epoch(loader) for _ in range(repeat)]
            n, s = sorted(runs, key=lambda r: r[1])[len(runs) // 2]
            rows.append({"mode": f"warm (from cache, median of {repeat})", "workers": w, "frames": n, "seconds": s})
            for r in rows[-3:]:
                r["speedup"] = (r["frames"] / r["seconds"]) / cold
            del loader
    return rows


def table(rows: list[dict], args) -> str:
    head = (f"data module, {args.sequences} seq x {args.frames} frames of {args.size}x{args.size}, "
            f"windows of {args.window} frames, {args.crop}x{args.crop} crops, batch {args.batch}\n")
    lines = ["| mode | workers | frames | seconds | frames/s | vs cold |", "|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['mode']} | {r['workers']} | {r['frames']} | {r['seconds']:.2f} | "
                     f"{r['frames'] / r['seconds']:.1f} | {r['speedup']:.1f}x |")
    return head + "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--size", type=int, default=512)
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--window", type=int, default=8)
    p.add_argument("--sequences", type=int, default=2)
    p.add_argument("--frames", type=int, default=16)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--workers", type=int, nargs="+", default=[0, 2])
    p.add_argument("--repeat", type=int, default=3, help="warm epochs timed (the median is shown)")
    args = p.parse_args(argv)
    try:
        rows = run(args.size, args.crop, args.window, args.sequences, args.frames, args.workers, args.batch, args.repeat)
    except UserError as exc:
        report_user_error(exc)
    print(table(rows, args))


if __name__ == "__main__":
    main()
