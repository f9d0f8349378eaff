"""Fine-tuning: ``model.init_ckpt`` starts supervised training, or distillation, from a checkpoint's weights."""

import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command

from denoiser.checkpoint import load_weights, read_checkpoint
from denoiser.configs import compose_net_config, instantiate_config
from denoiser.errors import ConfigError, UserError
from denoiser.lit.distill import DistillationModule
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


def test_an_experiment_with_init_ckpt_is_that_recipe_from_a_start(tmp_path):
    """A fine-tune is an experiment plus model.init_ckpt (steps and lr overridden as wanted): the
    demo teacher's network and data, trained from the checkpoint's weights."""
    cfg = compose_command("train", ["experiment=demo_teacher", "model.init_ckpt=t.ckpt", "trainer.max_steps=400",
                                    "model.optimizer.lr=5e-4"])
    teacher = compose_command("train", ["experiment=demo_teacher"])
    assert cfg.model.init_ckpt == "t.ckpt" and teacher.model.init_ckpt is None
    assert cfg.trainer.max_steps == 400 and cfg.model.optimizer.lr == 5e-4
    assert cfg.net == teacher.net and cfg.data == teacher.data


def student(tmp_path, init_ckpt=None, **kw):
    torch.manual_seed(123)
    teacher = tiny_checkpoint(tmp_path / "teacher.ckpt", seed=3)
    return DistillationModule(net=compose_net_config("tiny", "student"), optimizer=OPTIMIZER,
                              teacher_ckpt=str(teacher), init_ckpt=init_ckpt, **kw)


def test_distillation_starts_from_init_ckpt_not_from_the_teacher(tmp_path):
    path = tiny_checkpoint(tmp_path / "student.ckpt", seed=7)
    saved = {k.removeprefix("net."): v for k, v in read_checkpoint(path)["state_dict"].items()}
    tuned, fresh = student(tmp_path, str(path)).net.state_dict(), student(tmp_path).net.state_dict()
    assert all(torch.equal(tuned[k], saved[k]) for k in saved)
    assert any(not torch.equal(fresh[k], saved[k]) for k in saved)
    assert student(tmp_path, str(path)).hparams["init_ckpt"] == str(path)


def test_distillation_refuses_init_ckpt_with_param_transfer(tmp_path):
    path = tiny_checkpoint(tmp_path / "student.ckpt", seed=7)
    transfer = {"_target_": "denoiser.lit.transfer.L1ChannelTransfer", "probe_size": 8}
    with pytest.raises(ConfigError, match=r"model.init_ckpt and model.param_transfer: give one"):
        student(tmp_path, str(path), param_transfer=transfer)


def test_demo_distill_from_a_student_composes_and_starts_from_it(tmp_path):
    """experiment=demo_distill model.init_ckpt=<student> model.param_transfer=null: the distillation
    recipe (teacher, data, losses) from the student's weights; without param_transfer=null one error
    line; experiment=demo model.init_ckpt=<student>: its no-KD comparison."""
    start = tiny_checkpoint(tmp_path / "student.ckpt", seed=7)
    teacher = tiny_checkpoint(tmp_path / "teacher.ckpt", seed=3)
    tiny = ["net=tiny", "kernel=student", f"model.teacher_ckpt={teacher}"]
    cfg = compose_command("train", ["experiment=demo_distill", *tiny, f"model.init_ckpt={start}", "model.param_transfer=null"])
    recipe = compose_command("train", ["experiment=demo_distill", *tiny])
    assert cfg.model.init_ckpt == str(start) and recipe.model.init_ckpt is None
    assert cfg.model.param_transfer is None and recipe.model.param_transfer is not None
    assert cfg.net == recipe.net and cfg.data == recipe.data and cfg.model.loss == recipe.model.loss
    assert cfg.trainer == recipe.trainer and cfg.model.optimizer == recipe.model.optimizer
    saved = {k.removeprefix("net."): v for k, v in read_checkpoint(start)["state_dict"].items()}
    tuned = instantiate_config(cfg.model, "model").net.state_dict()
    assert all(torch.equal(tuned[k], saved[k]) for k in saved)
    with pytest.raises(ConfigError, match=r"model.init_ckpt and model.param_transfer: give one"):
        instantiate_config(compose_command("train", ["experiment=demo_distill", *tiny, f"model.init_ckpt={start}"]).model,
                           "model")
    no_kd = compose_command("train", ["experiment=demo", f"model.init_ckpt={start}"])
    assert no_kd.model.init_ckpt == str(start) and no_kd.data == compose_command("train", ["experiment=demo"]).data
