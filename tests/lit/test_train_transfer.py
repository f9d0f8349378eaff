"""Parameter transfer teacher -> student (denoiser.lit.transfer): the L1 rule for hidden layers, the
meaning of the head channels and U-Net inputs, and data-flow consistency."""

from __future__ import annotations

import pytest
import torch

from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.lit.transfer import L1ChannelTransfer, plan_transfer, transfer_parameters
from denoiser.nn.filters import SingleKernelFilter
from denoiser.nn.inputs import GUIDE_CHANNELS
from denoiser.nn.kernels import kernel_weights
from denoiser.nn.pyramid import PyramidFilter
from denoiser.recurrent import RecurrentRunner

STUDENT = ["net.embed.hidden=4", "net.embed.out_channels=4", "net.unet.encoder=[4,6,8]",
           "net.unet.bottleneck=8", "net.unet.decoder=[6,4]"]
#: a logit whose softmax weight is exactly 0 next to the logits a network predicts
DEAD_LOGIT = -1e4


@pytest.fixture(scope="module")
def nets():
    torch.manual_seed(0)
    teacher = build_net(compose_net_config("tiny"))
    student_cfg = compose_net_config("tiny", overrides=STUDENT)
    return teacher, student_cfg


def head_names(net) -> set[str]:
    return {n for n, p in net.named_parameters() if n.startswith("unet.heads.") and p.dim() == 4}


def test_hidden_layers_keep_the_top_l1_filters(nets):
    teacher, student_cfg = nets
    student = build_net(student_cfg)
    plan = plan_transfer(teacher, student)
    report = transfer_parameters(teacher, student)
    t_params, s_params = dict(teacher.named_parameters()), dict(student.named_parameters())
    convs = [n for n, p in s_params.items() if p.dim() == 4]
    assert convs and all(report[n] == "selected" for n in convs)
    hidden = [n for n in convs if n not in head_names(student)]
    assert hidden and len(hidden) == len(convs) - len(head_names(student))
    for name in hidden:
        out_idx, in_idx = plan.convs[name]
        assert (in_idx >= 0).all()
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
            dead[out_idx[out_idx >= 0]] = False
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


# --- the meaning of the head channels and of the U-Net inputs -------------------------------------
# Written out here from the documented layouts (denoiser.nn.pyramid, filters, temporal), independently
# of denoiser.lit.transfer: level-0 head = [partition logits (pyramid only), k0*k0 taps, h_in, h_out,
# F state features]; level i >= 1 = k_i*k_i taps; U-Net input = [embed, history output (3),
# history color (3), guide, F state features, valid].


def window(k_t: int, k_s: int) -> list[int]:
    """Row-major indices, in a k_t x k_t kernel, of its centred k_s x k_s window (k_t >= k_s)."""
    d = (k_t - k_s) // 2
    return [(i + d) * k_t + j + d for i in range(k_s) for j in range(k_s)]


def partitions(net) -> int:
    return net.filter.levels if isinstance(net.filter, PyramidFilter) else 0


def kernels(net) -> dict[int, tuple[int, int]]:
    """``{level: (kernel size k, row of tap 0 in that level's head)}``."""
    if isinstance(net.filter, SingleKernelFilter):
        return {0: (net.filter.kernel_size, 0)}
    return {i: (k, net.filter.levels if i == 0 else 0) for i, k in enumerate(net.filter.kernel_sizes)}


def blend_rows(net) -> list[int]:
    """Level-0 head rows of h_in, h_out."""
    return [net.filter_head0, net.filter_head0 + 1]


def feature_rows(net) -> list[int]:
    start = net.filter_head0 + 2
    return list(range(start, start + net.temporal.state_features))


def feature_columns(net) -> list[int]:
    """U-Net input channels that read the warped state features back."""
    start = net.embed.out_channels + 3 + 3 + GUIDE_CHANNELS
    return list(range(start, start + net.temporal.state_features))


def build(kernel: str, overrides: list[str], seed: int = 0):
    """A tiny net with raw softmax logits: "dead" taps (logit -1e4) and the exact restriction of
    a kernel to a window exist only there (scaled logits couple every tap through their spread)."""
    torch.manual_seed(seed)
    return build_net(compose_net_config("tiny", kernel=kernel, overrides=["net.filter.logit_scale=null", *overrides]))


def test_heads_and_unet_inputs_map_by_meaning():
    teacher = build("teacher", ["net.temporal.state_features=8"])  # kernels 5, 7, 9
    student = build("student", STUDENT)  # kernels 5, 5, 5, 4 state features
    plan = plan_transfer(teacher, student)
    # 9 -> 5 and 7 -> 5: the centred window, centre tap to centre tap
    out2, out1 = plan.convs["unet.heads.2.weight"][0], plan.convs["unet.heads.1.weight"][0]
    assert out2.tolist() == window(9, 5) and out2[12] == 40
    assert out1.tolist() == window(7, 5) and out1[12] == 24
    out0 = plan.convs["unet.heads.0.weight"][0].tolist()
    levels = partitions(student)
    assert out0[:levels] == list(range(levels))  # partition logits by position
    assert out0[levels: levels + 25] == [levels + t for t in range(25)]  # 5 -> 5 taps: identity
    assert [out0[r] for r in blend_rows(student)] == blend_rows(teacher)  # h_in -> h_in, h_out -> h_out
    assert [out0[r] for r in feature_rows(student)] == feature_rows(teacher)[:4]  # feature f -> feature f
    # the U-Net input: feature f is read where the teacher reads feature f, valid where it reads valid
    in_idx = plan.convs["unet.encoder.0.0.weight"][1].tolist()
    assert [in_idx[c] for c in feature_columns(student)] == feature_columns(teacher)[:4]
    assert in_idx[-1] == teacher.unet.encoder[0][0].in_channels - 1
    e_s, e_t = student.embed.out_channels, teacher.embed.out_channels
    assert in_idx[e_s: feature_columns(student)[0]] == list(range(e_t, feature_columns(teacher)[0]))

    # a wider state and a larger kernel: what has no counterpart is marked (negative), the rest maps
    wide = build("k7", STUDENT + ["net.temporal.state_features=12"])
    plan = plan_transfer(teacher, wide)
    out0 = plan.convs["unet.heads.0.weight"][0]
    inner = [levels + t for t in window(7, 5)]  # the teacher's 5x5 taps sit in the centre of the 7x7
    assert out0[inner].tolist() == [levels + t for t in range(25)]
    outer = sorted(set(range(levels, levels + 49)) - set(inner))
    assert (out0[outer] < 0).all()
    assert out0[feature_rows(wide)[:8]].tolist() == feature_rows(teacher) and (out0[feature_rows(wide)[8:]] < 0).all()
    in_idx = plan.convs["unet.encoder.0.0.weight"][1]
    assert in_idx[feature_columns(wide)[:8]].tolist() == feature_columns(teacher)
    assert (in_idx[feature_columns(wide)[8:]] < 0).all()


def deaden(teacher, student) -> None:
    """Make dead, in place, the teacher channels and taps that the student cannot represent.

    Hidden channels the L1 rule discards get zero filters; kernel taps outside the student's
    window and partitions the student lacks get a logit of DEAD_LOGIT (weight exactly 0 after the
    softmax), state features the student lacks are written but never read (zero U-Net input
    columns). The dead head rows get *large* filters, so an L1 choice among the head rows would
    pick them.
    """
    params = dict(teacher.named_parameters())
    first, head0 = "unet.encoder.0.0.weight", "unet.heads.0"
    with torch.no_grad():
        f_t, f_s = teacher.temporal.state_features, student.temporal.state_features
        if f_t > f_s:
            params[first][:, feature_columns(teacher)[f_s:]] = 0
            params[head0 + ".weight"][feature_rows(teacher)[f_s:]] *= 3
        for level in range(max(partitions(student), 1), partitions(teacher)):
            params[head0 + ".weight"][level] *= 3
            params[head0 + ".bias"][level] = DEAD_LOGIT
        ks_t, ks_s = kernels(teacher), kernels(student)
        for level in ks_t.keys() & ks_s.keys():
            (k_t, start), k_s = ks_t[level], ks_s[level][0]
            if k_t > k_s:
                rows = [start + t for t in sorted(set(range(k_t * k_t)) - set(window(k_t, k_s)))]
                params[f"unet.heads.{level}.weight"][rows] *= 3
                params[f"unet.heads.{level}.bias"][rows] = DEAD_LOGIT
        plan = plan_transfer(teacher, student)
        for name, (out_idx, _) in plan.convs.items():
            if name not in head_names(teacher):
                dead = torch.ones(params[name].shape[0], dtype=torch.bool)
                dead[out_idx] = False
                params[name][dead] = 0
                params[name[: -len("weight")] + "bias"][dead] = 0


@torch.no_grad()
def run(net, frames: list[dict]):
    """Step ``net`` over ``frames``: outputs, U-Net heads and states, one per frame."""
    heads = []
    hook = net.unet.register_forward_hook(lambda module, args, out: heads.append(out[0]))
    runner, outputs, states = RecurrentRunner(net.eval().step), [], []
    for frame in frames:
        outputs.append(runner(frame))
        states.append(runner.state)
    hook.remove()
    return outputs, heads, states


VARIANTS = {
    "kernels 9->5, 7->5": ("teacher", [], "student", []),
    "state features 8->4": ("student", ["net.temporal.state_features=8"], "student", []),
    "state features 2->4": ("student", ["net.temporal.state_features=2"], "student", []),
    "kernels 5->7 (student larger), 9->7": ("teacher", [], "k7", []),
    "3 -> 2 pyramid levels": ("teacher", [], "student", ["kernel.sizes=[5,5]"]),
    "pyramid -> single kernel": ("teacher", [], "student", ["net.filter._target_=denoiser.nn.filters.SingleKernelFilter"]),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_dead_teacher_channels_give_the_student_the_teacher_kernels_and_state(variant):
    kernel_t, over_t, kernel_s, over_s = VARIANTS[variant]
    teacher = build(kernel_t, over_t, seed=1)
    student = build(kernel_s, STUDENT + over_s, seed=2)
    deaden(teacher, student)
    transfer_parameters(teacher, student)
    frames = [random_frame(1, 24, 24, seed=5 + t, kind="probe") for t in range(3)]
    out_t, heads_t, states_t = run(teacher, frames)
    out_s, heads_s, states_s = run(student, frames)
    ks_t, ks_s = kernels(teacher), kernels(student)
    for step in range(len(frames)):
        # kernel weights: the student's renormalised kernel is the teacher's, restricted to the student's window
        for level in ks_s:
            (k_t, start_t), (k_s, start_s) = ks_t[level], ks_s[level]
            w_t = kernel_weights(heads_t[step][level][:, start_t: start_t + k_t * k_t])
            w_s = kernel_weights(heads_s[step][level][:, start_s: start_s + k_s * k_s])
            if k_t >= k_s:
                expected = w_t[:, window(k_t, k_s)]
                torch.testing.assert_close(w_s, expected / expected.sum(1, keepdim=True), atol=1e-6, rtol=1e-5)
            else:  # the teacher's kernel, zero outside its size
                expected = torch.zeros_like(w_s)
                expected[:, window(k_s, k_t)] = w_t
                torch.testing.assert_close(w_s, expected, atol=1e-6, rtol=1e-5)
        levels = partitions(student)
        if levels:
            p_t = torch.softmax(heads_t[step][0][:, :partitions(teacher)], 1)[:, :levels]
            p_s = torch.softmax(heads_s[step][0][:, :levels], 1)
            torch.testing.assert_close(p_s, p_t / p_t.sum(1, keepdim=True), atol=1e-6, rtol=1e-5)
        # blend logits and state features by index
        torch.testing.assert_close(heads_s[step][0][:, blend_rows(student)], heads_t[step][0][:, blend_rows(teacher)],
                                   atol=1e-5, rtol=1e-5)
        f = min(teacher.temporal.state_features, student.temporal.state_features)
        torch.testing.assert_close(states_s[step]["features"][:, :f], states_t[step]["features"][:, :f],
                                   atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(out_s[step], out_t[step], atol=1e-5, rtol=1e-5)


def test_outer_taps_keep_their_initialization_on_request():
    teacher = build("teacher", [])
    student = build("k7", STUDENT, seed=4)
    init = {n: p.clone() for n, p in student.named_parameters()}
    transfer_parameters(teacher, student, outer_tap_logit=None)
    levels = partitions(student)
    outer = [levels + t for t in sorted(set(range(49)) - set(window(7, 5)))]
    head = dict(student.named_parameters())
    assert torch.equal(head["unet.heads.0.weight"][outer], init["unet.heads.0.weight"][outer])
    assert torch.equal(head["unet.heads.0.bias"][outer], init["unet.heads.0.bias"][outer])
    transfer_parameters(teacher, student)  # default: the renormalised kernel is the teacher's
    assert (head["unet.heads.0.weight"][outer] == 0).all() and (head["unet.heads.0.bias"][outer] <= -1e3).all()
