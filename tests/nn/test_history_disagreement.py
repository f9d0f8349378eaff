"""The history disagreement input (denoiser.nn.temporal, ``history_disagreement``): a plain loop
over pixels checks the fast statistic, it is 0 without history and where the history agrees, near
1 on a turning object's stale history, off by default bit for bit, finite on hard inputs, exported
to ONNX, and transferred from a teacher without it as a zero-weight input."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.levers import moving_object_sequence, two_steps_stay_finite

from denoiser.configs import build_net, compose_net_config
from denoiser.frames import random_frame
from denoiser.nn.temporal import DISAGREEMENT_EPS, TemporalRecurrence, history_disagreement


def tiny(disagreement=True, seed=0, **temporal):
    cfg = compose_net_config("tiny")
    cfg["temporal"]["history_disagreement"] = disagreement
    cfg["temporal"].update(temporal)
    torch.manual_seed(seed)
    return build_net(cfg).eval()


def disagreement_loop(history, current):
    """Reference: per pixel, the 3x3 mean and population std of each channel of ``current`` (edges
    replicated), z = |h - mu| / (sd + eps (|mu| + 1e-3)), max over channels, z / (1 + z)."""
    b, c, h, w = current.shape
    out = torch.empty(b, 1, h, w, dtype=torch.float64)
    for n in range(b):
        for y in range(h):
            for x in range(w):
                zs = []
                for ch in range(c):
                    vals = [float(current[n, ch, min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)])
                            for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
                    mu = sum(vals) / 9.0
                    sd = math.sqrt(max(sum(v * v for v in vals) / 9.0 - mu * mu, 0.0) + 1e-12)
                    zs.append(abs(float(history[n, ch, y, x]) - mu) / (sd + DISAGREEMENT_EPS * (abs(mu) + 1e-3)))
                z = max(zs)
                out[n, 0, y, x] = z / (1.0 + z)
    return out


def test_disagreement_matches_a_plain_loop():
    g = torch.Generator().manual_seed(1)
    current = torch.rand(2, 3, 7, 9, generator=g) * 4.0
    history = torch.rand(2, 3, 7, 9, generator=g) * 6.0 - 1.0
    fast = history_disagreement(history, current)
    assert fast.shape == (2, 1, 7, 9) and fast.dtype == torch.float32
    torch.testing.assert_close(fast.double(), disagreement_loop(history, current), rtol=1e-5, atol=1e-5)
    # a flat neighbourhood: the relative floor keeps z finite, history equal to it gives 0
    flat = torch.full((1, 3, 5, 5), 2.0)
    assert history_disagreement(flat, flat).abs().max() == 0
    z = 5.0 / (1e-6 + DISAGREEMENT_EPS * (2.0 + 1e-3))  # 5 off a flat 2: the floor is the only spread
    torch.testing.assert_close(history_disagreement(flat + 5.0, flat), torch.full((1, 1, 5, 5), z / (1 + z)))


def test_off_by_default_bit_for_bit_and_one_more_input_when_on():
    assert TemporalRecurrence().history_disagreement is False
    for name in ("tiny", "demo_student", "demo_teacher", "student", "teacher"):
        assert not compose_net_config(name)["temporal"].get("history_disagreement")
    assert compose_net_config("tiny", lever="history_disagreement")["temporal"]["history_disagreement"] is True
    assert TemporalRecurrence(4, history_disagreement=True).input_channels == TemporalRecurrence(4).input_channels + 1
    with_key = tiny(disagreement=False, seed=3)
    cfg = compose_net_config("tiny")
    cfg["temporal"].pop("history_disagreement", None)
    without = build_net(cfg).eval()
    without.load_state_dict(with_key.state_dict())
    state_a = state_b = None
    with torch.no_grad():
        for s in range(3):
            f = random_frame(2, 16, 16, seed=s)
            a, state_a, _ = with_key.step(f, state_a)
            b, state_b, _ = without.step(f, state_b)
            assert torch.equal(a, b)


@pytest.mark.parametrize("turning", [True, False])
def test_it_marks_a_turning_objects_stale_history_and_nothing_without_history(turning):
    """The object of ``moving_object_sequence`` slides with exact vectors over a static
    background; when its colour also changes every frame (a turning object's shading: the
    vectors cannot line up its history), its interior's disagreement is near 1, else (the
    control) it is small there too. On the static background the history is the current frame,
    and a value of the neighbourhood lies at most sqrt(8) of its standard deviations from its
    mean, so z <= sqrt(8) there. Frame 0 (no history) gives exactly 0. The disocclusion gate is
    on (the demo's), so the uncovered background has no history."""
    net = tiny(seed=9, reject_threshold=0.1)
    probe = net.temporal.probe = {}
    frames, masks = moving_object_sequence()
    for t, f in enumerate(frames):
        if turning:
            f["color"] = torch.where(masks[t], f["color"] + 4.0 * t, f["color"])
    state, inside, background = None, [], []
    with torch.no_grad():
        for t, (f, obj) in enumerate(zip(frames, masks)):
            _, state, _ = net.step(f, state)
            d = probe["history"]["disagreement"][0, 0]
            if t == 0:
                assert torch.equal(d, torch.zeros_like(d))
                continue
            inner = obj & torch.roll(obj, 2, -1) & torch.roll(obj, -2, -1) & torch.roll(obj, 2, -2) & torch.roll(obj, -2, -2)
            still = ~obj & ~torch.roll(obj, 3, -1) & ~torch.roll(obj, -3, -1) & ~torch.roll(obj, 3, -2) \
                & ~torch.roll(obj, -3, -2) & ~masks[t - 1] & ~torch.roll(masks[t - 1], 3, -1) & ~torch.roll(masks[t - 1], -3, -1)
            inside.append(float(d[inner].min()))
            background.append(float(d[still].max()))
    bound = math.sqrt(8) / (1 + math.sqrt(8))
    assert max(background) <= bound + 1e-6  # the static background's history is the current frame's
    if turning:
        assert min(inside) > 0.8  # z > 4: at least 4 standard deviations (the floor: 5% of the colour) off
    else:
        assert max(inside) < 0.05


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_hard_inputs_stay_finite_with_finite_gradients(dtype):
    """Fireflies, NaN/Inf buffers, a constant (zero-variance) frame, autocast."""
    net = tiny(seed=11, reject_threshold=0.1, history_clamp=1.0).train()
    f0, f1 = random_frame(2, 13, 11, seed=1, kind="hard"), random_frame(2, 13, 11, seed=2, kind="hard")
    f1["color"][:, 0, 0, 0] = float("nan")
    f1["color"][:, 1, 4, 4] = float("inf")
    f1["color"][1] = 0.25
    two_steps_stay_finite(net, f0, f1, dtype)


def test_it_exports_to_onnx(tmp_path):
    from denoiser.inference.step_graph import check_export, export_onnx

    net = tiny(seed=8, reject_threshold=0.1, history_clamp=1.0)
    path = tmp_path / "net.onnx"
    export_onnx(net, path, trace_size=(13, 21))
    errors = check_export(net, path, size=(16, 24), steps=3)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


def test_a_teacher_without_it_transfers_a_zero_weight_input():
    """Distilling a student with the input from today's teacher: its U-Net input channel has no
    counterpart, so it starts at zero weights (the student reads it only once it learns to), and
    the other inputs map by meaning as before."""
    from denoiser.lit.transfer import plan_transfer, transfer_parameters

    torch.manual_seed(0)
    teacher = build_net(compose_net_config("tiny"))
    student = tiny(seed=1)
    plan = plan_transfer(teacher, student)
    in_idx = plan.convs["unet.encoder.0.0.weight"][1]
    assert int(in_idx[-1]) < 0 and in_idx[-2] == teacher.unet.encoder[0][0].in_channels - 1  # valid -> valid
    transfer_parameters(teacher, student)
    first = student.unet.encoder[0][0].weight
    assert first.shape[1] == teacher.unet.encoder[0][0].in_channels + 1
    assert torch.equal(first[:, -1], torch.zeros_like(first[:, -1]))
