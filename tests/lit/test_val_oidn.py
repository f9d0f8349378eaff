"""OIDN in TensorBoard (denoiser/lit/common.py): a tiny training run logs val/oidn_fast_psnr beside
val/psnr, the OIDN-fast PSNR of the val frames computed once and cached; it is the PSNR that
OidnDenoiser and the project's metric give on the same frames."""

from __future__ import annotations

import pytest
import torch
from helpers.train_args import FAST
from hydra import compose, initialize_config_dir
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from denoiser.conf import CONF_DIR
from denoiser.data.synthetic import write_synthetic_sequence

pytest.importorskip("pyoidn")


def test_a_training_run_logs_the_val_splits_oidn_fast_psnr_once_computed(tmp_path, monkeypatch):
    from denoiser.commands import train as train_script
    from denoiser.lit import common
    from denoiser.methods.baselines import OidnDenoiser
    from denoiser.metrics import MetricAccumulator

    root = tmp_path / "data"
    for split in ("train", "val"):
        write_synthetic_sequence(root / split / "seq0", frames=4, width=32, height=32, labeled=True, seed=len(split))
    calls = []
    original = common.DenoiserModule.oidn_outputs
    monkeypatch.setattr(common.DenoiserModule, "oidn_outputs",
                        lambda self, oidn, batch: calls.append(1) or original(self, oidn, batch))
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("train", overrides=[*FAST, f"data.root={root}", f"output_dir={tmp_path / 'run'}",
                                          "model=student", "trainer.max_steps=4", "trainer.val_check_interval=2"])
    train_script.train(cfg)
    acc = EventAccumulator(str(tmp_path / "run" / "tb"), size_guidance={"scalars": 0})
    acc.Reload()
    assert {"val/psnr", "val/input_psnr", "val/oidn_fast_psnr"} <= set(acc.Tags()["scalars"])
    logged = [e.value for e in acc.Scalars("val/oidn_fast_psnr")]
    assert len(logged) >= 2 and len(set(logged)) == 1, logged   # every validation, the same cached value
    assert len(calls) == 1                                       # computed at the first validation only

    # the value: OIDN-fast on the val frames (whole 32x32 frames, warm-up 2), the project's PSNR
    from denoiser.configs import instantiate_config
    from denoiser.data.dataset import SequenceDataset, index_split

    layout = instantiate_config(cfg.data.layout, "layout")
    item = SequenceDataset(index_split(layout, root, "val"), layout, list(cfg.data.buffers))[0]
    oidn = OidnDenoiser("fast")
    out = torch.stack([oidn({k: item[k][t][None] for k in ("color", "albedo", "normal")})[0]
                       for t in range(item["color"].shape[0])])
    metric = MetricAccumulator(("psnr",), warmup=int(cfg.model.warmup_frames))
    metric.update(out[None], item["reference"][None], [item["sequence"]], reset=item["reset"][None])
    assert logged[0] == pytest.approx(metric.compute()["psnr"], abs=1e-4)
