"""The history clamp (denoiser.nn.temporal, ``history_clamp``): a plain loop over pixels checks
the fast box, history that the current frame explains passes unchanged, history it cannot is
pulled into its box even where the learned blend keeps all of it, and hard inputs stay finite."""

from __future__ import annotations

import math

import pytest
import torch
from helpers.levers import (
    max_blend_identity_filter,
    moving_object_sequence,
    two_steps_stay_finite,
)

from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.nn.temporal import TemporalRecurrence, neighbourhood_clamp


def tiny(history_clamp=None, reject_threshold=None, seed=0):
    cfg = compose_net_config("tiny")
    cfg["temporal"]["reject_threshold"] = reject_threshold
    cfg["temporal"]["history_clamp"] = history_clamp
    torch.manual_seed(seed)
    return build_net(cfg).eval()


def clamp_loop(history, current, k):
    """Reference: per pixel and channel, mean and population std over the 3x3 neighbourhood with
    the edge replicated (indices clamped into the image), then clamp."""
    b, c, h, w = current.shape
    out = torch.empty_like(history, dtype=torch.float64)
    for n in range(b):
        for ch in range(c):
            for y in range(h):
                for x in range(w):
                    vals = [float(current[n, ch, min(max(y + dy, 0), h - 1), min(max(x + dx, 0), w - 1)])
                            for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
                    mu = sum(vals) / 9.0
                    sd = math.sqrt(max(sum(v * v for v in vals) / 9.0 - mu * mu, 0.0) + 1e-12)
                    out[n, ch, y, x] = min(max(float(history[n, ch, y, x]), mu - k * sd), mu + k * sd)
    return out


@pytest.mark.parametrize("k", [0.5, 1.0, 3.0])
def test_clamp_matches_a_plain_loop(k):
    g = torch.Generator().manual_seed(1)
    current = torch.rand(2, 3, 7, 9, generator=g) * 4.0
    history = torch.rand(2, 3, 7, 9, generator=g) * 6.0 - 1.0
    fast = neighbourhood_clamp(history, current, k)
    assert fast.dtype == torch.float32
    torch.testing.assert_close(fast.double(), clamp_loop(history, current, k), rtol=1e-5, atol=1e-5)


def test_history_the_current_frame_explains_passes_unchanged():
    current = torch.rand(1, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    # the current value itself lies within mu +- k sd for k >= sqrt(8) (at most 8/9 of the mass
    # can sit on one side), so history equal to the current frame is never moved
    assert torch.equal(neighbourhood_clamp(current, current, 3.0), current)
    flat = torch.full((1, 3, 8, 8), 0.7)
    assert torch.equal(neighbourhood_clamp(flat, flat, 1.0), flat)
    # a constant neighbourhood leaves (almost) no room: foreign history is pulled to it
    assert (neighbourhood_clamp(flat + 5.0, flat, 1.0) - flat).abs().max() < 1e-5
    bright = torch.full((1, 3, 8, 8), 3000.0)  # no float32 cancellation in a bright, flat box
    assert (neighbourhood_clamp(bright + 5.0, bright, 1.0) - bright).abs().max() < 1e-3


def test_off_by_default_on_in_the_demo_student_and_validated():
    assert TemporalRecurrence().history_clamp is None
    for name in ("tiny", "demo_teacher", "student", "teacher"):
        assert compose_net_config(name)["temporal"].get("history_clamp") is None
    assert compose_net_config("demo_student")["temporal"]["history_clamp"] == 1.0  # the demo recipe (issue 33)
    assert compose_net_config("tiny", lever="history_clamp")["temporal"]["history_clamp"] == 1.0
    with pytest.raises(ConfigError, match="history_clamp"):
        TemporalRecurrence(4, history_clamp=0.0)


def test_clamp_off_is_the_network_without_it():
    """The same weights with ``history_clamp`` None and the key absent give the same outputs
    bit for bit (stored configs without the key keep their behaviour)."""
    with_key = tiny(history_clamp=None, seed=3)
    cfg = compose_net_config("tiny")
    cfg["temporal"].pop("history_clamp", None)
    without = build_net(cfg).eval()
    without.load_state_dict(with_key.state_dict())
    state_a = state_b = None
    with torch.no_grad():
        for s in range(3):
            f = random_frame(2, 16, 16, seed=s)
            a, state_a, _ = with_key.step(f, state_a)
            b, state_b, _ = without.step(f, state_b)
            assert torch.equal(a, b)


@pytest.mark.parametrize("k", [1.0, None])
def test_clamp_removes_a_turning_objects_stale_history(k, monkeypatch):
    """The object of ``moving_object_sequence`` keeps its history (the gate off, the blend
    forced to keep all of it). Its colour changes every frame, as a turning object's shading
    does: with the clamp the output follows the current frame; without it (the control, which
    proves the check can fail) the stale colour stays."""
    net = max_blend_identity_filter(tiny(history_clamp=k, seed=9), monkeypatch)
    frames, masks = moving_object_sequence()
    for t, f in enumerate(frames):  # the object's colour jumps by 2 (linear) each frame
        f["color"] = torch.where(masks[t], f["color"] + 2.0 * t, f["color"])
    state, errors = None, []
    with torch.no_grad():
        for t, (f, obj) in enumerate(zip(frames, masks)):
            out, state, extras = net.step(f, state)
            inner = obj & torch.roll(obj, 2, -1) & torch.roll(obj, -2, -1) & torch.roll(obj, 2, -2) & torch.roll(obj, -2, -2)
            if t > 0 and inner.any():
                assert extras["weights"]["history_out"][0, 0][inner].min() > 0.99  # the blend keeps history
                errors.append(float((out[0, :, inner] - f["color"][0, :, inner]).abs().max()))
    assert errors
    if k is not None:
        assert max(errors) < 1e-4
    else:
        assert min(errors) > 1.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_clamp_on_hard_inputs_stays_finite_with_finite_gradients(dtype):
    """Fireflies, NaN/Inf buffers, a constant (zero-variance) frame, autocast."""
    net = tiny(history_clamp=1.0, reject_threshold=0.1, seed=11).train()
    f0, f1 = random_frame(2, 13, 11, seed=1, kind="hard"), random_frame(2, 13, 11, seed=2, kind="hard")
    f1["color"][:, 0, 0, 0] = float("nan")
    f1["color"][:, 1, 4, 4] = float("inf")
    f1["color"][1] = 0.25  # one item constant: the box has zero width there
    two_steps_stay_finite(net, f0, f1, dtype)


def test_clamp_exports_to_onnx(tmp_path):
    from denoiser.inference.step_graph import check_export, export_onnx

    net = tiny(history_clamp=1.0, reject_threshold=0.1, seed=8)
    path = tmp_path / "net.onnx"
    export_onnx(net, path, trace_size=(13, 21))
    errors = check_export(net, path, size=(16, 24), steps=3)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors
