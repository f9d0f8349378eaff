"""Tests of denoiser.checkpoint: load_denoiser round trip and its user errors."""

import pytest
import torch

from denoiser.checkpoint import load_denoiser, save_checkpoint
from denoiser.configs import build_net, compose_net_config
from denoiser.errors import UserError


@pytest.fixture(scope="module")
def tiny_cfg():
    return compose_net_config("tiny", "student")


def _frame(h=20, w=28, seed=0):
    g = torch.Generator().manual_seed(seed)
    return {
        "color": torch.rand(1, 3, h, w, generator=g) * 4,
        "albedo": torch.rand(1, 3, h, w, generator=g),
        "normal": torch.nn.functional.normalize(torch.randn(1, 3, h, w, generator=g), dim=1),
        "depth": torch.rand(1, 1, h, w, generator=g) * 10,
        "motion": torch.zeros(1, 2, h, w),
    }


def test_round_trip_gives_same_outputs(tmp_path, tiny_cfg):
    torch.manual_seed(1)
    net = build_net(tiny_cfg).eval()
    path = save_checkpoint(tmp_path / "tiny.ckpt", net, tiny_cfg)
    loaded = load_denoiser(path)
    assert type(loaded) is type(net) and not loaded.training
    with torch.no_grad():
        a, sa, _ = net.step(_frame(), None)
        b, sb, _ = loaded.step(_frame(), None)
        a2, _, _ = net.step(_frame(seed=1), sa)
        b2, _, _ = loaded.step(_frame(seed=1), sb)
    assert torch.equal(a, b) and torch.equal(a2, b2)


def test_lightning_style_checkpoint_with_other_modules(tmp_path, tiny_cfg):
    """A distillation checkpoint also holds teacher.* and critic.* weights: only net.* is loaded."""
    net = build_net(tiny_cfg)
    path = save_checkpoint(tmp_path / "d.ckpt", net, tiny_cfg)
    ckpt = torch.load(path, weights_only=True)
    ckpt["state_dict"].update({"teacher." + k: v for k, v in net.state_dict().items()})
    ckpt["state_dict"]["critic.w"] = torch.zeros(3)
    ckpt["hyper_parameters"]["teacher_ckpt"] = "x.ckpt"
    torch.save(ckpt, path)
    assert load_denoiser(path).num_parameters() == net.num_parameters()


def test_missing_file(tmp_path):
    with pytest.raises(UserError, match="nope.ckpt: checkpoint file does not exist"):
        load_denoiser(tmp_path / "nope.ckpt")


def test_not_a_checkpoint(tmp_path):
    p = tmp_path / "text.ckpt"
    p.write_text("hello")
    with pytest.raises(UserError, match="text.ckpt: not a checkpoint"):
        load_denoiser(p)
    q = tmp_path / "tensor.ckpt"
    torch.save(torch.zeros(2), q)
    with pytest.raises(UserError, match="tensor.ckpt: not a Lightning checkpoint"):
        load_denoiser(q)
    r = tmp_path / "nohp.ckpt"
    torch.save({"state_dict": {}}, r)
    with pytest.raises(UserError, match="nohp.ckpt: not a Lightning checkpoint"):
        load_denoiser(r)


def test_other_architecture(tmp_path, tiny_cfg):
    other = compose_net_config("tiny", "student", ["net.unet.encoder=[8,12,20]", "net.unet.bottleneck=20"])
    path = save_checkpoint(tmp_path / "a.ckpt", build_net(tiny_cfg), other)
    with pytest.raises(UserError, match="a.ckpt: checkpoint weights do not fit") as info:
        load_denoiser(path)
    assert "other shapes" in str(info.value) and "\n" not in str(info.value)


def test_no_net_weights_or_config(tmp_path, tiny_cfg):
    net = build_net(tiny_cfg)
    p = tmp_path / "m.ckpt"
    torch.save({"state_dict": {"model." + k: v for k, v in net.state_dict().items()},
                "hyper_parameters": {"net": tiny_cfg}}, p)
    with pytest.raises(UserError, match="no weights under 'net.'.*model"):
        load_denoiser(p)
    q = tmp_path / "n.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {"lr": 1e-3}}, q)
    with pytest.raises(UserError, match="n.ckpt: checkpoint has no net config"):
        load_denoiser(q)
    bad = dict(tiny_cfg, _target_="denoiser.nn.nothing.Here")
    path = save_checkpoint(tmp_path / "b.ckpt", net, bad)
    with pytest.raises(UserError, match="b.ckpt: net config cannot be instantiated"):
        load_denoiser(path)
