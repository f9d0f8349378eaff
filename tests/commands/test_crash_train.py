"""Crash safety of ``train.py``: SIGKILL after the first checkpoint appeared, rerun, continue.

The run is killed (SIGKILL: no exception handler, no final checkpoint) as soon as
``checkpoints/last.ckpt`` exists. Every checkpoint under a final name must then load, and the
same command with ``ckpt_path=last`` in the same run directory must continue from the saved
``global_step`` (its TensorBoard steps start there, not at 0) up to ``max_steps``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.kill import kill_when

REPO = Path(__file__).resolve().parents[2]
MAX_STEPS = 12
TRAIN = ["data=tiny", "net=tiny", "threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null",
         "trainer.enable_model_summary=false", f"trainer.max_steps={MAX_STEPS}", "trainer.val_check_interval=6",
         "trainer.limit_val_batches=1", "trainer.log_every_n_steps=1", "model.image_interval=0",
         "callbacks.last.every_n_train_steps=4", "final_validation=false"]


def train_argv(data: Path, run: Path, *extra: str) -> list[str]:
    return [sys.executable, str(REPO / "train.py"), *TRAIN, f"data.root={data}", f"hydra.run.dir={run}", *extra]


def loss_steps(path: Path) -> list[int]:
    acc = EventAccumulator(str(path), size_guidance={"scalars": 0})
    acc.Reload()
    return sorted({e.step for e in acc.Scalars("train/loss")}) if "train/loss" in acc.Tags()["scalars"] else []


def resume(data: Path, run: Path) -> None:
    """``train.py <TRAIN> hydra.run.dir=<run> ckpt_path=last``, run through train.train in this process."""
    from hydra import compose, initialize_config_dir

    from denoiser.conf import CONF_DIR

    sys.path.insert(0, str(REPO))
    from denoiser.commands import train as train_script

    threads = torch.get_num_threads()
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("train", overrides=[*TRAIN, f"data.root={data}", f"output_dir={run}", "ckpt_path=last"])
        train_script.train(cfg)
    finally:
        torch.set_num_threads(threads)


def test_training_killed_resumes_from_last_checkpoint(tmp_path):
    from denoiser.data.synthetic import write_synthetic_sequence

    data = tmp_path / "data"
    for split, seed in (("train", 1), ("val", 2)):
        write_synthetic_sequence(data / split / "seq0", frames=4, width=32, height=32, seed=seed)
    run = tmp_path / "run"
    last = run / "checkpoints" / "last.ckpt"
    env = {**os.environ, "PYTHONPATH": str(REPO)}

    assert kill_when(train_argv(data, run), last.exists, env=env)
    for ckpt in (run / "checkpoints").glob("*.ckpt"):  # nothing broken under a final name
        torch.load(ckpt, map_location="cpu", weights_only=True)
    saved = torch.load(last, map_location="cpu", weights_only=True)["global_step"]
    assert 0 < saved < MAX_STEPS, saved
    first_events = set((run / "tb").glob("events.out.tfevents.*"))

    resume(data, run)  # the same command with ckpt_path=last (in this process: saves a start-up)
    assert torch.load(last, map_location="cpu", weights_only=True)["global_step"] == MAX_STEPS
    resumed = [f for f in (run / "tb").glob("events.out.tfevents.*") if f not in first_events]
    assert resumed  # (the final hparams/metrics may go to a second event file of the same process)
    steps = sorted({s for f in resumed for s in loss_steps(f)})
    # Lightning logs train/loss at global_step - 1 of the step that produced it
    assert steps and steps[0] == saved and steps[-1] == MAX_STEPS - 1, (saved, steps[:3], steps[-3:])


def test_checkpoint_writes_stay_beside_the_target(tmp_path, monkeypatch):
    """Checkpoints are written to a temporary file in their own directory (never the system temp
    directory, which may be another filesystem: then a rename is a copy and a kill leaves a broken
    file), and a failed write leaves nothing behind."""
    import tempfile

    import pytest
    from lightning.pytorch.plugins.io import TorchCheckpointIO

    from denoiser.lit.checkpoint_io import AtomicCheckpointIO

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "no_such_tmpdir"))  # system temp unusable
    target = tmp_path / "checkpoints" / "last.ckpt"
    with pytest.raises(FileNotFoundError):  # Lightning's default goes through the system temp dir
        TorchCheckpointIO().save_checkpoint({"global_step": 1}, target)
    AtomicCheckpointIO().save_checkpoint({"global_step": 3, "w": torch.ones(2)}, target)
    assert torch.load(target, weights_only=True)["global_step"] == 3

    with pytest.raises(Exception):  # noqa: B017 - torch.save of a lambda fails (pickling)
        AtomicCheckpointIO().save_checkpoint({"global_step": 4, "bad": lambda: 0}, target)
    assert torch.load(target, weights_only=True)["global_step"] == 3  # the previous file is intact
    assert sorted(p.name for p in target.parent.iterdir()) == ["last.ckpt"]  # no temporary left


def test_trainer_presets_use_atomic_checkpoint_io():
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from denoiser.conf import CONF_DIR
    from denoiser.lit.checkpoint_io import AtomicCheckpointIO

    for preset in ("cpu", "ddp"):
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("train", overrides=[f"trainer={preset}", "trainer.accelerator=cpu", "trainer.devices=1",
                                              "trainer.precision=32-true", "output_dir=/tmp/unused"])
        trainer = instantiate(cfg.trainer, logger=False, enable_checkpointing=False)
        assert isinstance(trainer.strategy.checkpoint_io, AtomicCheckpointIO), preset
