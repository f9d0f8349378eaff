"""Scenes and checks shared by the tests of the temporal levers (the disocclusion gate, the
history clamp, the guide disagreement): frames are dicts of ``[B, C, H, W]`` tensors."""

from __future__ import annotations

import torch


def moving_object_sequence(count=6, size=32, step=3):
    """A red square (albedo (0.9, 0.1, 0.1), colour (20, 2, 2), depth 2) sliding right by ``step``
    pixels per frame over a grey checker background (depth 10), exact backward motion.

    Returns ``(frames, object masks [count] of bool [H, W])``.
    """
    h = w = size
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    checker = (0.3 + 0.4 * (((xs // 2) + (ys // 2)) % 2)).float()
    frames, masks = [], []
    for t in range(count):
        x0 = 2 + step * t
        obj = (ys >= 12) & (ys < 20) & (xs >= x0) & (xs < x0 + 8)
        albedo = torch.where(obj, torch.tensor([0.9, 0.1, 0.1]).view(3, 1, 1), checker)
        color = torch.where(obj, torch.tensor([20.0, 2.0, 2.0]).view(3, 1, 1), checker)
        normal = torch.zeros(3, h, w)
        normal[2] = 1
        depth = torch.where(obj, 2.0, 10.0).view(1, h, w)
        motion = torch.zeros(2, h, w)
        motion[0] = torch.where(obj, -float(step), 0.0)
        frames.append({"color": color[None], "albedo": albedo[None], "normal": normal[None],
                       "depth": depth[None], "motion": motion[None]})
        masks.append(obj)
    return frames, masks


def max_blend_identity_filter(net, monkeypatch):
    """Force the learned history blends to their maximum (sigmoid = 1) and make the spatial
    filter the identity, so the output is exactly what the temporal rule lets through."""
    start = net.filter_head0

    def force(module, args, output):
        heads, features = output
        h0 = heads[0].clone()
        h0[:, start: start + 2] = 40.0
        return [h0] + list(heads[1:]), features

    net.unet.register_forward_hook(force)
    monkeypatch.setattr(net.filter, "forward", lambda x, heads, scale: (x.float(), {}))
    return net


def two_steps_stay_finite(net, f0, f1, dtype):
    """``net.step`` over ``f0`` then ``f1`` (under ``dtype`` autocast unless float32): both
    outputs finite float32, and the gradients of their means finite for ``f1``'s colour and for
    every parameter."""
    f1["color"].requires_grad_(True)
    with torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32):
        out0, state, _ = net.step(f0, None)
        out1, _, _ = net.step(f1, state)
    assert torch.isfinite(out0).all() and torch.isfinite(out1).all() and out1.dtype == torch.float32
    (out0.mean() + out1.mean()).backward()
    assert torch.isfinite(f1["color"].grad).all()
    assert all(torch.isfinite(p.grad).all() for p in net.parameters() if p.grad is not None)
