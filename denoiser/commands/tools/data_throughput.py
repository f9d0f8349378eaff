"""Data benchmark: frames/s of the data module, decoding EXR (cold) vs from the frame cache (warm).

::

    python -m denoiser.commands.tools.data_throughput
    python -m denoiser.commands.tools.data_throughput size=512 crop=128 window=8 sequences=2 frames=16 workers=[0,2]

A Hydra app over ``conf/data_throughput.yaml``. Writes synthetic native-layout sequences
(:mod:`denoiser.data.synthetic`, all buffers plus reference, float32, zip) into a temporary
directory, composes ``conf/data/default.yaml`` (root, cache and worker overrides) and times
whole training epochs of the real ``SequenceDataModule.train_dataloader()`` (random crops,
default augmentation):

* ``cold``: ``cache_dir=null``, every frame read decodes its EXR;
* ``fill``: first epoch with an empty cache (decode + write the float32 .npy entries);
* ``warm``: later epochs (median of ``repeat``), every frame read fetches only its crop's rows
  from the cache.

frames/s counts frames delivered (windows x T). Each loader uses persistent workers; the
timed epoch includes worker start-up only for its first epoch (``cold``, ``fill``).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

from omegaconf import DictConfig
from tqdm.auto import tqdm

from denoiser.configs import compose_config, instantiate_config
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.measure import Clock, summarize
from denoiser.tables import markdown_table


def make_dataset(root: Path, sequences: int, frames: int, size: int) -> None:
    for i in tqdm(range(sequences), desc="write sequences", unit="seq"):
        write_synthetic_sequence(root / "train" / f"seq{i:02d}", frames=frames, width=size, height=size, seed=i)


def build(root: Path, cache: Path | None, workers: int, window: int, crop: int, batch: int):
    """The training loader of ``conf/data/default.yaml`` over ``root``."""
    overrides = ["+data=default", f"data.root={root}", f"data.num_workers={workers}",
                 f"data.persistent_workers={workers > 0}", f"data.window={window}", f"data.crop={crop}",
                 f"data.batch_size={batch}", "data.val_split=null", "data.test_split=null",
                 f"data.cache_dir={cache if cache else 'null'}"]
    dm = instantiate_config(compose_config(overrides).data, "data")
    dm.setup("fit")
    return dm.train_dataloader()


def epoch(loader) -> tuple[int, float]:
    """Frames delivered by one pass over ``loader`` and the seconds it took."""
    frames = 0
    with Clock() as clock:
        for batch in loader:
            frames += batch["color"].shape[0] * batch["color"].shape[1]
    return frames, clock.wall


def measure_loader(size: int, crop: int, window: int, sequences: int, frames: int, workers: list[int], batch: int,
                   repeat: int = 3) -> list[dict]:
    """Rows ``{mode, workers, frames, seconds, speedup}``: cold, fill and warm for every worker count."""
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
            runs = [epoch(loader) for _ in range(repeat)]  # every epoch delivers the same frames
            rows.append({"mode": f"warm (from cache, median of {repeat})", "workers": w, "frames": runs[0][0],
                         "seconds": summarize([s for _, s in runs])["median"]})
            for r in rows[-3:]:
                r["speedup"] = (r["frames"] / r["seconds"]) / cold
            del loader
    return rows


def table(rows: list[dict], cfg) -> str:
    """The Markdown report of :func:`measure_loader`'s rows (``cfg``: the sizes measured)."""
    head = (f"data module, {cfg.sequences} seq x {cfg.frames} frames of {cfg.size}x{cfg.size}, "
            f"windows of {cfg.window} frames, {cfg.crop}x{cfg.crop} crops, batch {cfg.batch}\n")
    shown = [{**r, "rate": r["frames"] / r["seconds"], "vs_cold": f"{r['speedup']:.1f}x"} for r in rows]
    return head + markdown_table(shown, ["mode", "workers", "frames", "seconds", "rate", "vs_cold"],
                                 {"seconds": ".2f", "rate": ".1f"}, {"rate": "frames/s", "vs_cold": "vs cold"})


def run(cfg: DictConfig) -> list[dict]:
    """The ``data_throughput`` task: measure and print the table; returns the rows."""
    rows = measure_loader(int(cfg.size), int(cfg.crop), int(cfg.window), int(cfg.sequences), int(cfg.frames),
                          [int(w) for w in cfg.workers], int(cfg.batch), int(cfg.repeat))
    print(table(rows, cfg), end="")
    return rows


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "data_throughput")()


if __name__ == "__main__":
    main()
