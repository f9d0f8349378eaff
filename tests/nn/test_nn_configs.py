"""Net/kernel/ablation configs: docs/design.md §2 numbers, composition, the netstats command, import rules."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from denoiser.conf import CONF_DIR
from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError
from denoiser.measure import count_flops
from denoiser.nn.critic import PatchCritic
from denoiser.nn.denoiser import Denoiser
from denoiser.nn.filters import DirectColor, SingleKernelFilter
from denoiser.nn.pyramid import PyramidFilter

CONF = Path(CONF_DIR)


def test_student_and_teacher_follow_design_table():
    student = compose_net_config("student", "student")
    teacher = compose_net_config("teacher", "teacher")
    assert student["embed"]["hidden"] == 32 and teacher["embed"]["hidden"] == 256
    assert student["unet"]["encoder"] == [32, 64, 128] and student["unet"]["bottleneck"] == 128
    assert student["unet"]["decoder"] == [64, 32]
    assert teacher["unet"]["encoder"] == [128, 256, 512] and teacher["unet"]["bottleneck"] == 512
    assert teacher["unet"]["decoder"] == [512, 256]
    assert student["filter"]["kernel_sizes"] == [5, 5, 5] and teacher["filter"]["kernel_sizes"] == [5, 7, 9]
    s, t = build_net(student), build_net(teacher)
    assert isinstance(s.filter, PyramidFilter) and t.filter.kernel_sizes == [5, 7, 9]
    assert s.unet.head_channels[1:] == [25, 25] and t.unet.head_channels[1:] == [49, 81]
    # same number of feature maps, so distillation can pair them through 1x1 adapters
    assert len(s.feature_channels) == len(t.feature_channels) == 3
    assert 10 * s.num_parameters() < t.num_parameters()


def test_net_config_alone_uses_default_kernel_sizes():
    """A net config instantiated without the kernel group (e.g. from a plain yaml file)."""
    cfg = OmegaConf.load(CONF / "net" / "teacher.yaml")
    net = instantiate(cfg)
    assert isinstance(net, Denoiser) and net.filter.kernel_sizes == [5, 7, 9]


@pytest.mark.parametrize("groups, check", [
    ({"ablation": "none"}, lambda n: isinstance(n.filter, PyramidFilter) and n.temporal is not None),
    ({"ablation": "no_pyramid"}, lambda n: isinstance(n.filter, SingleKernelFilter) and n.filter.kernel_size == 5),
    ({"kernel": "teacher", "ablation": "no_pyramid"}, lambda n: n.filter.kernel_size == 9),
    ({"ablation": "direct"}, lambda n: isinstance(n.filter, DirectColor)),
    ({"ablation": "no_temporal"}, lambda n: n.temporal is None),
    ({"ablation": "k3"}, lambda n: n.filter.kernel_sizes == [3, 3, 3]),
    ({"ablation": "k7"}, lambda n: n.filter.kernel_sizes == [7, 7, 7]),
    ({"kernel": "k3"}, lambda n: n.filter.kernel_sizes == [3, 3, 3]),
    ({"kernel": "k7"}, lambda n: n.filter.kernel_sizes == [7, 7, 7]),
])
def test_ablations_and_kernels_compose(groups, check):
    net = build_net(compose_net_config("tiny", **groups))
    assert check(net)
    out, _, _ = net.step({k: torch.rand(1, c, 8, 8) for k, c in
                          (("color", 3), ("albedo", 3), ("normal", 3), ("depth", 1), ("motion", 2))}, None)
    assert out.shape == (1, 3, 8, 8)


@pytest.mark.parametrize("net, overrides, message", [
    ("nope", [], "net/nope"),
    ("tiny", ["kernel.sizes=[4,4,4]"], "kernel.sizes"),
    ("tiny", ["kernel.sizes=[5,5,5,5]"], "kernel.sizes"),
    ("tiny", ["net.unet.decoder=[8]"], "net.unet.decoder"),
])
def test_config_mistakes_are_user_errors(net, overrides, message):
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        build_net(compose_net_config(net, overrides=overrides))


def test_netstats_prints_parameter_counts(capsys):
    from denoiser.commands.tools.netstats import run

    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        run(compose("netstats", overrides=["net=tiny", "kernel=k3", "flops_size=32"]))
    out = capsys.readouterr().out
    net = build_net(compose_net_config("tiny", "k3"))
    flops = count_flops(net, 32, 32)
    lines = dict(line.strip().rsplit(None, 1) for line in out.splitlines()[2:])
    assert lines["parameters"] == f"{net.num_parameters():,}"
    assert float(lines["GFLOP per 32x32 frame"]) == pytest.approx(flops / 1e9, abs=1e-3)
    assert flops > 2 * net.num_parameters() * 32 * 32 / 64  # at least the 1/8-scale convs


def test_nn_imports_neither_lightning_nor_hydra():
    code = ("import sys, denoiser.nn.denoiser, denoiser.nn.critic; "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('lightning', 'pytorch_lightning', 'hydra')]; "
            "sys.exit(bool(bad))")
    assert subprocess.run([sys.executable, "-c", code], check=False).returncode == 0


@pytest.mark.parametrize("spectral_norm", [True, False])
def test_patch_critic_shapes_and_gradients(spectral_norm):
    critic = PatchCritic(in_channels=3, widths=(8, 16), spectral_norm=spectral_norm)
    x = torch.rand(2, 3, 37, 53, requires_grad=True)
    logits = critic(x)
    assert logits.shape == (2, 1, 9, 13)
    logits.mean().backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() > 0
