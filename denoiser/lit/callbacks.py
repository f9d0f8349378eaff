"""Training callbacks of our own (Lightning's ModelCheckpoint, LearningRateMonitor and progress
bar are used as they are, see conf/callbacks/default.yaml)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import lightning.pytorch as pl


class FinalCheckpoint(pl.Callback):
    """Write ``<dirpath>/<filename>`` when training ends (``max_steps``, ``max_time``, Ctrl-C, and
    in a one-process job a SLURM/submitit preemption or timeout).

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
        # Ctrl-C; or submitit's preemption/timeout handler (SIGUSR2), which requeues the job and exits
        # (SystemExit) in rank 0 only: with several ranks the save (a collective) could hang, so there
        # the periodic last.ckpt is what the requeued job resumes from.
        if isinstance(exception, KeyboardInterrupt) or (isinstance(exception, SystemExit) and trainer.world_size == 1):
            self._save(trainer)


class CollapseDetector(pl.Callback):
    """Detect a collapsed run: the network returns its noisy input, or its training broke down.

    After every validation (sanity checks excluded) it reads ``val/psnr`` and the noisy
    input's ``val/input_psnr`` (both logged by :class:`~denoiser.lit.common.DenoiserModule`).
    Two rules, each over ``patience`` validations in a row:

    * identity: val PSNR within ``margin_db`` of the noisy input's (the run has collapsed to
      about the identity);
    * breakdown: val PSNR more than ``drop_db`` below the best val PSNR of the run so far (the
      run had learned and lost it, e.g. the runaway of the head outputs in docs/training.md;
      ``drop_db: null`` turns the rule off).

    When one fires it says so in one line on stderr, logs ``val/collapsed = 1`` and the same
    line as TensorBoard text, writes ``<run dir>/COLLAPSED`` holding that line (``make demo``
    fails when it finds one), and stops training when ``stop``. A run whose output merely has
    low partition entropy is not a collapse; only the output is judged.
    """

    def __init__(self, margin_db: float = 0.5, patience: int = 3, stop: bool = True, marker: str | None = None,
                 drop_db: float | None = 3.0):
        self.margin_db = float(margin_db)
        self.patience = int(patience)
        self.stop = bool(stop)
        self.marker = Path(marker) if marker else None
        self.drop_db = None if drop_db is None else float(drop_db)
        self.streak = 0
        self.drop_streak = 0
        self.best = float("-inf")
        self.fired = False

    def state_dict(self) -> dict:
        return {"streak": self.streak, "fired": self.fired, "drop_streak": self.drop_streak, "best": self.best}

    def load_state_dict(self, state_dict: dict) -> None:
        self.streak = int(state_dict.get("streak", 0))
        self.fired = bool(state_dict.get("fired", False))
        self.drop_streak = int(state_dict.get("drop_streak", 0))
        self.best = float(state_dict.get("best", float("-inf")))

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking:
            return
        metrics = trainer.callback_metrics
        if "val/psnr" not in metrics or "val/input_psnr" not in metrics:
            return
        psnr, noisy = float(metrics["val/psnr"]), float(metrics["val/input_psnr"])
        self.streak = self.streak + 1 if abs(psnr - noisy) < self.margin_db else 0
        dropped = self.drop_db is not None and psnr < self.best - self.drop_db
        self.drop_streak = self.drop_streak + 1 if dropped else 0
        self.best = max(self.best, psnr)
        if self.fired:
            return
        if self.streak >= self.patience:
            line = (f"collapse: val PSNR {psnr:.2f} dB has stayed within {self.margin_db:g} dB of the noisy input's "
                    f"{noisy:.2f} dB for {self.streak} validations (step {trainer.global_step}): the network returns its input")
        elif self.drop_streak >= self.patience:
            line = (f"collapse: val PSNR {psnr:.2f} dB has stayed more than {self.drop_db:g} dB below the run's best "
                    f"{self.best:.2f} dB for {self.drop_streak} validations (step {trainer.global_step}): the training broke down")
        else:
            return
        self.fired = True
        print(line, file=sys.stderr, flush=True)
        if trainer.logger is not None:  # self.log is not allowed after the epoch: write to the logger itself
            trainer.logger.log_metrics({"val/collapsed": 1.0}, step=trainer.global_step)
            experiment = getattr(trainer.logger, "experiment", None)
            if hasattr(experiment, "add_text"):
                experiment.add_text("collapse", line, global_step=trainer.global_step)
        marker = self.marker or Path(trainer.default_root_dir) / "COLLAPSED"
        if trainer.is_global_zero:
            marker.write_text(line + "\n")
        if self.stop:
            trainer.should_stop = True
