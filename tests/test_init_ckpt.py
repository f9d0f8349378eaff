"""Fine-tuning: ``model.init_ckpt`` starts supervised training from a checkpoint's weights."""

import pytest
import torch
from conftest import compose_command, tiny_checkpoint

from denoiser.checkpoint import load_weights, read_checkpoint
from denoiser.configs import compose_net_config
from denoiser.errors import UserError
from denoiser.lit.supervised import SupervisedModule

LOSS = {"_target_": "denoiser.lit.losses.DenoiseLoss"}
OPTIMIZER = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 1e-3}


def module(init_ckpt=None, net="tiny"):
    torch.manual_seed(123)  # the random draw the checkpoint's weights must replace
    return SupervisedModule(net=compose_net_config(net, "student"), loss=LOSS, optimizer=OPTIMIZER, init_ckpt=init_ckpt)


def test_init_ckpt_loads_every_weight(tmp_path):
    path = tiny_checkpoint(tmp_path / "start.ckpt", seed=7)
    saved = {k.removeprefix("net."): v for k, v in read_checkpoint(path)["state_dict"].items()}
    tuned, fresh = module(str(path)).net.state_dict(), module().net.state_dict()
    assert set(tuned) == set(saved)
    assert all(torch.equal(tuned[k], saved[k]) for k in saved)
    assert any(not torch.equal(fresh[k], saved[k]) for k in saved)  # without it: the seed's own draw
    assert module(str(path)).hparams["init_ckpt"] == str(path)


def test_another_architecture_is_one_error_naming_the_file(tmp_path):
    path = tiny_checkpoint(tmp_path / "tiny.ckpt")
    other = SupervisedModule(net=compose_net_config("demo_student", "student"), loss=LOSS, optimizer=OPTIMIZER).net
    with pytest.raises(UserError, match=r"tiny\.ckpt: its weights do not fit the network being trained"):
        load_weights(other, path)
    with pytest.raises(UserError, match=r"missing\.ckpt: checkpoint file does not exist"):
        load_weights(other, tmp_path / "missing.ckpt")  # the missing file is named, not a traceback


def test_demo_motion_tune_composes_the_teacher_recipe_with_a_start(tmp_path):
    cfg = compose_command("train", ["experiment=demo_motion_tune", "model.init_ckpt=t.ckpt"])
    teacher = compose_command("train", ["experiment=demo_motion_teacher"])
    assert cfg.model.init_ckpt == "t.ckpt" and teacher.model.init_ckpt is None
    assert cfg.trainer.max_steps == 400 and cfg.model.optimizer.lr == 5e-4
    assert cfg.net == teacher.net and cfg.data == teacher.data  # the motion recipe's data, the teacher's network
