"""Quality levers of the denoiser (issue 12): albedo demodulation and the disocclusion gate.

Shapes: frames are dicts of ``[B, C, H, W]`` tensors (``denoiser.frames.random_frame``).
"""

from __future__ import annotations

import copy

import pytest
import torch
from helpers.kernels import reference_apply
from helpers.levers import max_blend_identity_filter, moving_object_sequence, two_steps_stay_finite

from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.nn.inputs import ALBEDO_MAX, DEMOD_MIN, demodulation_albedo, sanitize
from denoiser.nn.temporal import TemporalRecurrence, guide_disagreement


def tiny(demodulate=False, reject_threshold=None, seed=0):
    """The tiny net config with the levers set: ``Denoiser``."""
    cfg = compose_net_config("tiny")
    cfg["demodulate"] = demodulate
    cfg["temporal"]["reject_threshold"] = reject_threshold
    torch.manual_seed(seed)
    return build_net(cfg).eval()


def frames_with_albedo(albedo_fn, count=3, size=16, samples=0):
    """``count`` random frames (batch 2, ``size`` x ``size``) whose albedo is ``albedo_fn(frame)``."""
    out = []
    for s in range(count):
        f = random_frame(2, size, size, seed=s, samples=samples)
        f["albedo"] = albedo_fn(f)
        out.append(f)
    return out


def run(net, frames, transform=None):
    """Outputs ``[B, 3, H, W]`` of ``net.step`` over ``frames`` (each through ``transform``), and states."""
    outs, states, state = [], [], None
    with torch.no_grad():
        for f in frames:
            out, state, _ = net.step(transform(f) if transform else f, state)
            outs.append(out)
            states.append(state)
    return outs, states


# ----------------------------------------------------------------------------- demodulation


def test_config_defaults_keep_old_behaviour():
    net = build_net(compose_net_config("tiny"))  # tiny.yaml has neither key: like an old checkpoint
    assert net.demodulate is False and net.temporal.reject_threshold is None
    assert TemporalRecurrence().reject_threshold is None
    for name in ("student", "teacher", "demo_student", "demo_teacher"):
        cfg = compose_net_config(name)
        # no net config demodulates: on the sample-averaged albedo renderers give, it cost ~1 dB on
        # val (docs/results_log.md); lever=demodulation switches it on
        assert cfg["demodulate"] is False and cfg["temporal"]["reject_threshold"] == 0.1
        # the demo nets' softmaxes may sharpen further: at 2.5 a small bright lamp glowed (docs/results_log.md)
        assert cfg["filter"]["logit_scale"] == (5 if name.startswith("demo") else 2.5)
        assert compose_net_config(name, lever="demodulation")["demodulate"] is True
        assert compose_net_config(name, ablation="no_demodulation")["demodulate"] is False
        assert compose_net_config(name, ablation="no_disocclusion")["temporal"]["reject_threshold"] is None


def test_demodulation_albedo_rule():
    a = torch.tensor([0.0, 0.005, DEMOD_MIN, 0.5, 1.0, 3.0, 1e4, float("nan"), float("inf"), -float("inf"), -2.0])
    got = demodulation_albedo(a.view(1, 1, 1, -1).expand(1, 3, 1, -1))[0, 0, 0]
    want = torch.tensor([1.0, 1.0, DEMOD_MIN, 0.5, 1.0, 3.0, ALBEDO_MAX, 1.0, ALBEDO_MAX, 1.0, 1.0])
    torch.testing.assert_close(got, want)


def test_albedo_one_equals_the_network_without_demodulation():
    plain = tiny(seed=3)
    demod = copy.deepcopy(plain)
    demod.demodulate = True
    frames = frames_with_albedo(lambda f: torch.ones_like(f["albedo"]), samples=2)
    for a, b in zip(run(plain, frames)[0], run(demod, frames)[0]):
        assert torch.equal(a, b)


def test_zero_albedo_passes_through():
    """Emitters and the sky (albedo 0): demodulation is the identity there."""
    plain = tiny(seed=4)
    demod = copy.deepcopy(plain)
    demod.demodulate = True
    frames = frames_with_albedo(lambda f: torch.zeros_like(f["albedo"]))
    for a, b in zip(run(plain, frames)[0], run(demod, frames)[0]):
        assert torch.equal(a, b) and torch.isfinite(b).all()


def mixed_albedo(f):
    """Albedo in [0, 3] (above 1 on some pixels), an emitter block (0) and a near-black block."""
    a = torch.rand(f["albedo"].shape, generator=torch.Generator().manual_seed(int(f["color"].sum()) % 1000)) * 3
    a[..., :4, :4] = 0.0
    a[..., -3:, -3:] = 0.004
    return a


@pytest.mark.parametrize("gate", [None, 0.1])
def test_demodulation_matches_divide_filter_multiply(gate):
    """Reference: the same network without demodulation fed ``color / a'`` (and samples / a'),
    its output times ``a'``; over three recurrent frames, so the history is checked too."""
    plain = tiny(reject_threshold=gate, seed=5)
    demod = copy.deepcopy(plain)
    demod.demodulate = True
    frames = frames_with_albedo(mixed_albedo, samples=2)

    def divide(f):
        a = demodulation_albedo(f["albedo"])
        return dict(f, color=sanitize(f["color"]) / a, samples=f["samples"] / a.unsqueeze(1))

    ref, ref_states = run(plain, frames, divide)
    got, states = run(demod, frames)
    for f, r, g, rs, s in zip(frames, ref, got, ref_states, states):
        torch.testing.assert_close(g, r * demodulation_albedo(f["albedo"]), rtol=1e-6, atol=1e-6)
        for k in rs:  # the state holds irradiance
            torch.testing.assert_close(s[k], rs[k], rtol=1e-6, atol=1e-6)


def test_demodulated_output_is_convex_in_irradiance():
    """First frame (no history): output / a' within the per-channel range of the irradiance;
    albedo above 1 included."""
    net = tiny(demodulate=True, seed=6)
    f = frames_with_albedo(mixed_albedo, count=1)[0]
    a = demodulation_albedo(f["albedo"])
    out = run(net, [f])[0][0]
    irr = f["color"] / a
    lo, hi = irr.amin(dim=(2, 3), keepdim=True), irr.amax(dim=(2, 3), keepdim=True)
    q = out / a
    assert (q >= lo - 1e-5 * hi).all() and (q <= hi * (1 + 1e-5)).all()


def test_non_finite_albedo_gives_finite_output():
    net = tiny(demodulate=True, reject_threshold=0.1, seed=7)

    def bad(f):
        a = f["albedo"].clone()
        a[:, 0, 0] = float("nan")
        a[:, 1, 1] = float("inf")
        a[:, 2, 2] = -float("inf")
        a[:, :, 5] = 1e30
        return a

    for out in run(net, frames_with_albedo(bad, samples=2))[0]:
        assert torch.isfinite(out).all()


def test_demodulation_and_gate_export_to_onnx(tmp_path):
    from denoiser.inference.step_graph import check_export, export_onnx

    net = tiny(demodulate=True, reject_threshold=0.1, seed=8)
    path = tmp_path / "net.onnx"
    export_onnx(net, path, trace_size=(13, 21))
    errors = check_export(net, path, size=(16, 24), steps=3)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


# ----------------------------------------------------------------------------- disocclusion gate


def test_gate_threshold_must_be_positive():
    with pytest.raises(ConfigError, match="reject_threshold"):
        TemporalRecurrence(4, reject_threshold=0.0)


def guide(albedo, normal, depth_feature):
    """``[B, 7, H, W]`` from albedo feature ``[B, 3, H, W]``, normal, depth feature ``[B, 1, H, W]``."""
    return torch.cat([albedo, normal, depth_feature], dim=1)


def test_guide_disagreement_terms():
    b, h, w = 1, 8, 8
    tex = (torch.arange(w).float().view(1, 1, 1, w).expand(b, 3, h, w) % 2) * 0.6
    n = torch.zeros(b, 3, h, w)
    n[:, 2] = 1
    d = torch.full((b, 1, h, w), 0.5)
    g = guide(tex, n, d)
    assert guide_disagreement(g, g).abs().max() == 0
    # sub-pixel motion over a sharp texture: the warp blends neighbouring texels -> inside the 3x3 box
    half = guide(0.5 * (tex + tex.roll(1, dims=-1)), n, d)
    assert guide_disagreement(half, g).max() <= 1e-6
    # depth: log depth ratio (feature 0.5 -> d = m; 0.25 -> d = m / 3)
    torch.testing.assert_close(guide_disagreement(guide(tex, n, d * 0.5), g), torch.full((b, 1, h, w), 3.0).log())
    # normal turned by 90 degrees -> 1; no normal on both sides -> 0, on one side -> 1
    n90 = torch.zeros_like(n)
    n90[:, 0] = 1
    assert torch.allclose(guide_disagreement(guide(tex, n90, d), g), torch.ones(b, 1, h, w))
    assert guide_disagreement(guide(tex, 0 * n, d), guide(tex, 0 * n, d)).max() == 0
    assert torch.allclose(guide_disagreement(guide(tex, 0 * n, d), g), torch.ones(b, 1, h, w))
    # albedo outside the current neighbourhood's range [0, 0.6]: by 0.3 on dark texels, 0.9 on bright ones
    assert torch.allclose(guide_disagreement(guide(tex + 0.9, n, d), g), tex[:, :1] + 0.3)


def test_gate_terms_match_plain_loops():
    """The fast forms of the gate (box max by shifted slices, one-log depth ratio) against a plain
    loop over pixels and the four-log formula, on random guides with odd sizes and extreme depths."""
    from denoiser.nn.temporal import DEPTH_LOGIT_EPS, _box_max, _log_depth_ratio

    g = torch.Generator().manual_seed(5)
    x = torch.randn(2, 3, 5, 7, generator=g)
    box = _box_max(x)
    ref = torch.empty_like(x)
    for y in range(5):
        for xx in range(7):
            ref[..., y, xx] = x[..., max(y - 1, 0): y + 2, max(xx - 1, 0): xx + 2].amax(dim=(-2, -1))
    assert torch.equal(box, ref)

    p, c = torch.rand(2, 1, 5, 7, generator=g), torch.rand(2, 1, 5, 7, generator=g)
    p[0, 0, 0, :3] = torch.tensor([0.0, 1.0, 1e-9])
    c[0, 0, 0, :3] = torch.tensor([1.0, 0.0, 0.5])

    def logit(f):
        f = f.clamp(DEPTH_LOGIT_EPS, 1 - DEPTH_LOGIT_EPS).double()  # clamped in float32, as the network does
        return f.log() - (-f).log1p()

    torch.testing.assert_close(_log_depth_ratio(p, c).double(), (logit(p) - logit(c)).abs(), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("gate", [0.1, None])
def test_no_ghost_trail_behind_a_moving_object(gate, monkeypatch):
    """With the gate, background uncovered by the object shows the background; without it
    (the control: proves the check can fail) the object's colour stays behind."""
    net = max_blend_identity_filter(tiny(reject_threshold=gate, seed=9), monkeypatch)
    frames, masks = moving_object_sequence()
    state, covered = None, torch.zeros_like(masks[0])
    ghost = []
    with torch.no_grad():
        for t, (f, obj) in enumerate(zip(frames, masks)):
            out, state, extras = net.step(f, state)
            uncovered = covered & ~obj
            if t > 0:
                assert extras["weights"]["history_out"][0, 0, 0, 0] == 1.0  # far background: full history
                assert extras["weights"]["history_out"][0, 0][obj].min() > 0.99  # the object keeps its history
            if uncovered.any():
                ghost.append((out[0, 0][uncovered] - f["color"][0, 0][uncovered]).abs().max())
            covered |= obj
    assert len(ghost) == len(frames) - 1
    if gate is not None:
        assert max(ghost) < 1e-5
    else:
        assert min(ghost) > 10.0


def test_gate_on_static_scene_keeps_history():
    net = tiny(reject_threshold=0.1, seed=10)
    f = random_frame(1, 16, 16)
    f["motion"].zero_()
    with torch.no_grad():
        _, state, _ = net.step(f, None)
        _, _, extras = net.step(f, state)
    assert extras["weights"]["valid"].min() == 1.0


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_levers_on_hard_inputs_stay_finite_with_finite_gradients(dtype):
    """Demodulation and the gate together, extreme weights, fireflies, non-finite buffers, autocast."""
    net = tiny(demodulate=True, reject_threshold=0.1, seed=11).train()
    with torch.no_grad():
        for p in net.parameters():
            p.mul_(3.0)
    f0, f1 = random_frame(2, 13, 11, seed=1, kind="hard"), random_frame(2, 13, 11, seed=2, kind="hard")
    f1["color"][:, 0, 0, 0] = float("nan")
    f1["albedo"][:, :, 3] = float("inf")
    f1["depth"][:, :, 5] = float("nan")
    two_steps_stay_finite(net, f0, f1, dtype)


# ----------------------------------------------------------------------------- filtered remodulation


def filtered(seed=0):
    """The tiny net, demodulating, with ``remodulate: filtered``, and the same net with plain
    remodulation sharing every weight (the extra level-0 head channels are the only difference)."""
    cfg = compose_net_config("tiny", lever="filtered_remodulation")
    cfg["demodulate"] = True
    torch.manual_seed(seed)
    net = build_net(cfg).eval()
    plain = build_net({**cfg, "remodulate": "input"}).eval()
    state = {k: (v[: plain.state_dict()[k].shape[0]] if k.startswith("unet.heads.0.") else v)
             for k, v in net.state_dict().items()}
    plain.load_state_dict(state)
    return net, plain


def test_filtered_remodulation_config_rules():
    assert compose_net_config("demo_student", lever="filtered_remodulation")["remodulate"] == "filtered"
    assert build_net(compose_net_config("tiny")).remodulate == "input"  # old configs: plain remodulation
    with pytest.raises(ConfigError, match="needs net.demodulate"):
        build_net({**compose_net_config("tiny"), "demodulate": False, "remodulate": "filtered"})
    with pytest.raises(ConfigError, match="net.remodulate"):
        build_net({**compose_net_config("tiny"), "demodulate": True, "remodulate": "blurred"})


def test_filtered_remodulation_is_the_kernel_filtered_albedo():
    """output = (irradiance output of the same weights) * (a' through the 3x3 kernels of the
    last 9 level-0 head channels), checked against a plain loop over pixels and taps."""

    from denoiser.nn.kernels import scale_logits

    net, plain = filtered(seed=6)
    frames = frames_with_albedo(mixed_albedo)
    captured = []
    hook = net.unet.heads[0].register_forward_hook(lambda m, i, o: captured.append(o))
    got, _ = run(net, frames)
    hook.remove()
    ref, _ = run(plain, frames)
    for f, g, r, head in zip(frames, got, ref, captured):
        a = demodulation_albedo(f["albedo"])
        h, w = a.shape[-2:]
        logits = scale_logits(head[:, -9:, :h, :w], net.filter.logit_scale)
        want = (r / a) * reference_apply(a, logits).float()
        torch.testing.assert_close(g, want, rtol=1e-5, atol=1e-6)


def test_filtered_remodulation_keeps_a_flat_albedo_and_starts_near_the_identity():
    """A constant albedo stays constant through any convex kernel, so the output equals plain
    remodulation's; an untrained kernel keeps about 99% on the centre tap."""
    net, plain = filtered(seed=7)
    frames = frames_with_albedo(lambda f: torch.full_like(f["albedo"], 0.4))
    for a, b in zip(run(net, frames)[0], run(plain, frames)[0]):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
    frames = frames_with_albedo(mixed_albedo)
    for a, b in zip(run(net, frames)[0], run(plain, frames)[0]):
        assert ((a - b).abs() / b.abs().clamp_min(1e-3)).median() < 0.05


def test_filtered_remodulation_exports_with_the_same_numbers(tmp_path):
    from denoiser.inference.step_graph import check_export, export_onnx

    net, _ = filtered(seed=8)
    path = export_onnx(net, tmp_path / "f.onnx")
    for name, (err, scale) in check_export(net, path or tmp_path / "f.onnx", size=(20, 28), threads=1).items():
        assert err <= 1e-4 * max(scale, 1.0), (name, err, scale)


def test_parameter_transfer_reads_the_remodulation_taps():
    """The remodulation logits are the last 9 level-0 head channels, row-major taps; a teacher
    without them transfers nothing into them (the student keeps its near-identity start)."""
    from denoiser.lit.transfer import head_meanings, transfer_parameters

    net, plain = filtered(seed=9)
    meanings = head_meanings(net)[0]
    assert meanings[-9:] == [("remodulation", 0, i, j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    before = net.unet.heads[0].bias[-9:].clone()
    transfer_parameters(plain, net)
    assert torch.equal(net.unet.heads[0].bias[-9:], before) and before[4] == 10.0


# ----------------------------------------------------------------------------- filter domain


def in_domain(domain, seed=0):
    """The tiny net config with ``filter_domain`` set: ``Denoiser``."""
    cfg = {**compose_net_config("tiny"), "filter_domain": domain}
    torch.manual_seed(seed)
    return build_net(cfg).eval()


def test_filter_domain_rules():
    assert build_net(compose_net_config("tiny")).filter_domain == "linear"  # old configs: linear
    with pytest.raises(ConfigError, match="net.filter_domain"):
        in_domain("gamma")
    from denoiser.nn.denoiser import compress, expand

    x = torch.tensor([-3.0, 0.0, 1e-6, 0.5, 250.0, 65504.0]).view(1, 1, 2, 3)
    s = torch.full((1, 1, 1, 1), 0.1)
    y = compress(x, s)
    assert (y.flatten().diff() > 0).all()  # monotone, sign kept
    torch.testing.assert_close(expand(y, s), x, rtol=1e-6, atol=1e-7)


def zero_heads(net):
    """Every U-Net head output 0: uniform kernels and partition, history blends at 1/2."""
    with torch.no_grad():
        for head in net.unet.heads:
            head.weight.zero_()
            head.bias.zero_()
    return net


def test_log_domain_keeps_a_small_bright_lamp_from_glowing():
    """A 2x2 lamp 3000 times brighter than a flat 0.1 room (64x64), the same uniform kernels:
    filtered in linear radiance the lamp spreads over its surroundings (the glow the demo
    networks showed on lamp_room); compressed, the pixels three rows off the lamp stay within
    twice the room's value."""
    frame = random_frame(1, 64, 64, seed=3)
    frame["color"] = torch.full_like(frame["color"], 0.1)
    frame["color"][..., 32:34, 32:34] = 300.0
    near = (slice(None), slice(None), 36, slice(32, 34))  # three rows below the lamp
    outs = {d: run(zero_heads(in_domain(d, seed=4)), [frame])[0][0] for d in ("linear", "log")}
    assert outs["linear"][near].min() > 2.0  # 20x the room
    assert outs["log"][near].max() < 0.2
    lamp = (slice(None), slice(None), 33, 33)
    assert (outs["log"][lamp] > outs["log"][near].max()).all()  # the lamp itself stays the brightest


def test_log_domain_output_is_convex_and_finite_on_hard_inputs():
    """First frame: output within the per-channel range of the input (both maps are monotone);
    fireflies up to 65504, negative values and non-finite inputs stay finite, gradients too."""
    net = in_domain("log", seed=5)
    f = random_frame(2, 13, 11, seed=1, kind="hard")
    out = run(net, [f])[0][0]
    x = sanitize(f["color"])
    lo, hi = x.amin(dim=(2, 3), keepdim=True), x.amax(dim=(2, 3), keepdim=True)
    assert (out >= lo - 1e-5 * hi.abs()).all() and (out <= hi * (1 + 1e-5)).all()
    net.train()
    f["color"][:, 0, 0, 0] = float("nan")
    f["color"].requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out, _, _ = net.step(f, None)
    assert torch.isfinite(out).all()
    out.mean().backward()
    assert torch.isfinite(f["color"].grad).all()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)


def test_log_domain_exports_with_the_same_numbers(tmp_path):
    from denoiser.inference.step_graph import check_export, export_onnx

    net = in_domain("log", seed=6)
    path = export_onnx(net, tmp_path / "log.onnx")
    for name, (err, scale) in check_export(net, path or tmp_path / "log.onnx", size=(20, 28), threads=1).items():
        assert err <= 1e-4 * max(scale, 1.0), (name, err, scale)
