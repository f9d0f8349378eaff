"""Training callbacks of our own (Lightning's ModelCheckpoint, LearningRateMonitor and progress
bar are used as they are, see conf/callbacks/default.yaml)."""

from __future__ import annotations

import os
from pathlib import Path

import lightning.pytorch as pl


class FinalCheckpoint(pl.Callback):
    """Write ``<dirpath>/<filename>`` when training ends (``max_steps``, ``max_time``, Ctrl-C).

    Lightning's ModelCheckpoint saves only at its intervals, so a run stopped by ``max_time``
    between two intervals would lose its last steps. The file is written under a temporary
    name and renamed into place, so an interrupted write never leaves a broken ``last.ckpt``.
    """

    def __init__(self, dirpath: str, filename: str = "last.ckpt"):
        self.path = Path(dirpath) / filename

    def _save(self, trainer: pl.Trainer) -> None:
        if trainer.sanity_checking or getattr(trainer, "fast_dev_run", False):
            return
        tmp = self.path.with_name(f".{self.path.name}.tmp")
        trainer.save_checkpoint(str(tmp), weights_only=False)
        if trainer.is_global_zero:
            os.replace(tmp, self.path)
        trainer.strategy.barrier("final_checkpoint")

    def on_train_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self._save(trainer)

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException) -> None:
        if isinstance(exception, KeyboardInterrupt):
            self._save(trainer)
