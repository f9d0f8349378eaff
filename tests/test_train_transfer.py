"""Parameter transfer teacher -> student (denoiser.transfer): the L1 rule and data-flow consistency."""

from __future__ import annotations

import pytest
import torch

from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.transfer import L1ChannelTransfer, plan_transfer, transfer_parameters

STUDENT = ["net.embed.hidden=4", "net.embed.out_channels=4", "net.unet.encoder=[4,6,8]",
           "net.unet.bottleneck=8", "net.unet.decoder=[6,4]"]


@pytest.fixture(scope="module")
def nets():
    torch.manual_seed(0)
    teacher = build_net(compose_net_config("tiny"))
    student_cfg = compose_net_config("tiny", overrides=STUDENT)
    return teacher, student_cfg


def test_selected_weights_are_the_teacher_slices_of_the_top_l1_filters(nets):
    teacher, student_cfg = nets
    student = build_net(student_cfg)
    plan = plan_transfer(teacher, student)
    report = transfer_parameters(teacher, student)
    t_params, s_params = dict(teacher.named_parameters()), dict(student.named_parameters())
    convs = [n for n, p in s_params.items() if p.dim() == 4]
    assert convs and all(report[n] == "selected" for n in convs)
    for name in convs:
        out_idx, in_idx = plan.convs[name]
        assert torch.equal(s_params[name], t_params[name][out_idx][:, in_idx])
        # rule 1-2: the kept output channels are the largest L1 filters, in ascending index order
        l1 = t_params[name].abs().flatten(1).sum(1)
        k = s_params[name].shape[0]
        assert sorted(out_idx.tolist()) == out_idx.tolist()
        assert set(out_idx.tolist()) == set(torch.topk(l1, k).indices.tolist())
    # the first EmbedNet layer reads the (unchanged) input features: all input channels, in order
    first = "embed.layers.0.weight"
    assert plan.convs[first][1].tolist() == list(range(t_params[first].shape[1]))
    # the second reads exactly the outputs the first kept
    assert torch.equal(plan.convs["embed.layers.2.weight"][1], plan.convs[first][0])


def test_student_computes_the_teacher_function_when_discarded_channels_are_dead(nets):
    """Zero the teacher channels the rule discards: the transferred student then equals the teacher."""
    teacher, student_cfg = nets
    teacher = build_net(compose_net_config("tiny"))
    teacher.load_state_dict(nets[0].state_dict())
    student = build_net(student_cfg)
    plan = plan_transfer(teacher, student)
    params = dict(teacher.named_parameters())
    with torch.no_grad():
        for name, (out_idx, _) in plan.convs.items():
            dead = torch.ones(params[name].shape[0], dtype=torch.bool)
            dead[out_idx] = False
            params[name][dead] = 0
            params[name[: -len("weight")] + "bias"][dead] = 0
    L1ChannelTransfer(probe_size=32)(teacher, student)
    g = torch.Generator().manual_seed(3)
    frames = {k: torch.stack([v, v * 1.1, v * 0.9], dim=1) + 0.05 * torch.rand(1, 3, *v.shape[1:], generator=g)
              for k, v in random_frame(1, 24, 24, seed=5, kind="probe").items()}
    teacher.eval()
    student.eval()
    with torch.no_grad():
        out_t = teacher(frames)[0]
        out_s = student(frames)[0]
    assert torch.allclose(out_t, out_s, atol=1e-5), (out_t - out_s).abs().max()
    # and the check is not vacuous: a student with its own random init differs
    with torch.no_grad():
        assert not torch.allclose(build_net(student_cfg).eval()(frames)[0], out_t, atol=1e-3)


def test_kernel_size_and_architecture_variants_transfer_by_name(nets):
    teacher = build_net(compose_net_config("tiny", kernel="teacher"))  # kernels 5, 7, 9
    for overrides in ([], ["net.temporal=null"], ["net.filter._target_=denoiser.nn.filters.SingleKernelFilter"]):
        student = build_net(compose_net_config("tiny", overrides=STUDENT + overrides))
        report = transfer_parameters(teacher, student)
        convs = [n for n, p in student.named_parameters() if p.dim() == 4]
        assert all(report[n] == "selected" for n in convs), overrides


class Wrapped(torch.nn.Module):
    """The same network under other parameter names (``inner.*``)."""

    def __init__(self, inner):
        super().__init__()
        self.inner = inner

    def step(self, frame, state=None, reset=None):
        return self.inner.step(frame, state, reset)


def test_other_architectures_are_refused():
    teacher = build_net(compose_net_config("tiny"))
    other = Wrapped(build_net(compose_net_config("tiny", overrides=STUDENT)))
    with pytest.raises(ConfigError, match="param_transfer"):
        plan_transfer(teacher, other)
