"""The reference-free flicker measure (``warp`` of denoiser.metrics, denoiser.report.flicker) on
sequences whose answer is known: a static sequence, gain jitter, a camera pan with exact motion,
a moving object that disoccludes its background, non-finite pixels, odd sizes.

The pan's reference is a plain loop over pixels (the warp error of Lai et al. written out), not
the code under test."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from denoiser.metrics import WARP_UNIT, masked_warp_error, tonemap
from denoiser.report.flicker import FlickerMeter, align, warp_error
from denoiser.report.flicker_report import ordering_agreement

H, W, T = 32, 32, 5


def texture(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """[3, h, w] HDR texture in (0.05, 4)."""
    return torch.from_numpy(np.random.default_rng(seed).uniform(0.05, 4.0, (3, h, w)).astype(np.float32))


def static(frames: int = T, h: int = H, w: int = W) -> tuple[torch.Tensor, torch.Tensor]:
    x = texture(h, w)[None].repeat(frames, 1, 1, 1)
    return x, torch.zeros(frames, 2, h, w)


def test_a_static_sequence_of_identical_frames_scores_zero():
    frames, motion = static()
    r = warp_error(frames, motion)
    assert math.isnan(r.per_frame[0]) and all(v == 0.0 for v in r.per_frame[1:])
    assert r.mean == 0.0 and all(k == 1.0 for k in r.kept[1:]) and r.mask == "in-frame"


def test_it_rises_monotonically_with_per_frame_gain_jitter():
    frames, motion = static(8)
    signs = torch.tensor([1, -1, 1, 1, -1, 1, -1, -1], dtype=torch.float32).view(-1, 1, 1, 1)
    means = [warp_error(frames * (1 + a * signs), motion).mean for a in (0.0, 0.01, 0.03, 0.1, 0.3)]
    assert means[0] == 0.0
    assert all(b > a for a, b in itertools.pairwise(means)), means


def pan(frames: int, h: int, w: int, dx: int, gains=None) -> tuple[torch.Tensor, torch.Tensor]:
    """A static scene seen by a camera panning right by ``dx`` px per frame: frame t shows the
    columns ``dx * t ...`` of a wide texture, so the surface at p was at p + (dx, 0) in t-1."""
    big = texture(h, w + dx * frames, seed=3)
    x = torch.stack([big[:, :, dx * t:dx * t + w] for t in range(frames)])
    if gains is not None:
        x = x * torch.as_tensor(gains, dtype=torch.float32).view(-1, 1, 1, 1)
    motion = torch.zeros(frames, 2, h, w)
    motion[1:, 0] = dx
    return x, motion


def reference_loop(x: torch.Tensor, dx: int) -> list[float]:
    """The warp error of a pan by ``dx`` written out: per frame, the mean over the pixels whose
    previous position lies inside the image of the squared distance summed over channels."""
    o = tonemap(x).double().numpy()
    t_count, _, h, w = o.shape
    out = [math.nan]
    for t in range(1, t_count):
        total, n = 0.0, 0
        for y in range(h):
            for xx in range(w - dx):
                total += sum((o[t, c, y, xx] - o[t - 1, c, y, xx + dx]) ** 2 for c in range(3))
                n += 1
        out.append(total / n / WARP_UNIT)
    return out


@pytest.mark.parametrize("size", [(H, W), (17, 23)])
def test_a_camera_pan_with_exact_motion_is_the_static_value_and_the_written_out_formula(size):
    h, w = size
    gains = [1.0, 1.1, 0.95, 1.05]
    x, motion = pan(4, h, w, dx=3)
    r = warp_error(x, motion)
    assert r.mean == pytest.approx(0.0, abs=1e-9)  # nothing changes but the view: no flicker
    assert r.kept[1] == pytest.approx((w - 3) / w)  # the border the camera brings in is masked
    jittered = warp_error(*pan(4, h, w, dx=3, gains=gains))
    expected = reference_loop(pan(4, h, w, dx=3, gains=gains)[0], 3)
    np.testing.assert_allclose(jittered.per_frame[1:], expected[1:], rtol=1e-4)
    # the same jitter on a uniform image: the pan changes nothing, the masked border included
    flat = torch.full((4, 3, h, w), 0.7) * torch.tensor(gains).view(-1, 1, 1, 1)
    assert warp_error(flat, motion).mean == pytest.approx(warp_error(flat, torch.zeros_like(motion)).mean, rel=1e-6)


def moving_square(count: int = 4, h: int = H, w: int = W, step: int = 2, size: int = 8):
    """A bright square moving right by ``step`` px per frame over a static textured background
    (depth 10); the square at depth 1. Noise-free, so every change is a disocclusion.
    Returns frames [T, 3, h, w], motion, aux {normal [T, 3, h, w], depth [T, 1, h, w]} and next
    motion [T, 2, h, w]."""
    bg = texture(h, w, seed=5)
    sq = texture(size, size, seed=6) * 4
    frames, motion, normals, depths, nxt = [], [], [], [], []
    for t in range(count):
        x0 = 4 + step * t
        img, m, depth = bg.clone(), torch.zeros(2, h, w), torch.full((1, h, w), 10.0)
        img[:, 10:10 + size, x0:x0 + size] = sq
        if t > 0:
            m[0, 10:10 + size, x0:x0 + size] = -step
        depth[:, 10:10 + size, x0:x0 + size] = 1.0
        n = torch.zeros(2, h, w)
        n[0, 10:10 + size, x0:x0 + size] = -step  # position in t minus position in t+1
        normal = torch.zeros(3, h, w)
        normal[2] = -1.0
        frames.append(img)
        motion.append(m)
        nxt.append(n)
        normals.append(normal)
        depths.append(depth)
    aux = {"normal": torch.stack(normals), "depth": torch.stack(depths)}
    return torch.stack(frames), torch.stack(motion), aux, torch.stack(nxt)


def test_disoccluded_pixels_are_excluded_by_either_test():
    x, motion, guide, nxt = moving_square()
    unmasked = warp_error(x, motion)
    assert unmasked.mean > 0.5  # the revealed background samples the square it was behind
    revealed = 8 * 2 / (H * W)
    for r, mask in ((warp_error(x, motion, aux=guide), "guide"), (warp_error(x, motion, next_motion=nxt),
                                                                    "forward-backward")):
        assert r.mask == mask
        assert r.mean == pytest.approx(0.0, abs=1e-9), mask
        assert r.kept[1] == pytest.approx(1.0 - revealed, abs=1.0 / (H * W)), mask


def test_non_finite_pixels_are_masked_never_a_nan_result():
    frames, motion = static()
    frames[2, 0, 3, 4] = float("nan")
    frames[3, 1, 5, 6] = float("inf")
    motion[4, 0, 7, 7] = float("nan")
    r = warp_error(frames, motion)
    assert all(v == 0.0 for v in r.per_frame[1:]) and r.mean == 0.0
    assert r.kept[2] < 1.0 and r.kept[3] < 1.0 and r.kept[4] < 1.0  # the bad pixel (and its neighbour) dropped
    error, kept = masked_warp_error(tonemap(frames[2:3]), tonemap(frames[1:2]), torch.ones(1, 1, H, W, dtype=bool))
    assert torch.isfinite(error).all() and kept[0] == pytest.approx(1 - 1 / (H * W))


def test_nothing_visible_is_a_clear_error_and_cuts_restart():
    frames, motion = static(3)
    motion[1:] = 1000.0  # everything comes from outside the previous frame
    r = warp_error(frames, motion)
    assert all(math.isnan(v) for v in r.per_frame)
    with pytest.raises(ValueError, match="no frame has a previous frame"):
        _ = r.mean
    meter = FlickerMeter(["a", "b"])
    x, m = static(3)
    for t in range(3):
        meter.update({"a": x[t:t + 1], "b": x[t:t + 1] * (1 + 0.1 * t)}, m[t:t + 1], reset=t in (0, 2))
    assert math.isnan(meter.values["a"][2]) and meter.values["a"][1] == 0.0 and meter.values["b"][1] > 0.0


@pytest.mark.parametrize("stride", [1, 3])
def test_the_alignment_is_the_networks_warp(stride):
    """Frame t-1 aligned by the measure is what denoiser.nn.warp gives the network, at the measured
    pixels whose footprint is inside (every pixel at stride 1, every 3rd with stride 3)."""
    from denoiser.nn.warp import coverage, sample_positions, warp_to_current

    x, motion, _, _ = moving_square()
    frac = motion[2:3] + torch.linspace(-1.7, 2.3, W).view(1, 1, 1, W)
    a = align(frac, stride=stride)
    full = warp_to_current(x[1:2], frac).reshape(3, -1)[:, a.points]
    inside = (coverage(*sample_positions(frac)) > 1 - 1e-6).reshape(-1)[a.points]
    assert a.visible.equal(inside) and a.points.numel() == len(range(stride // 2, H, stride)) ** 2
    np.testing.assert_allclose(a.warp(x[1:2])[:, a.visible].numpy(), full[:, a.visible].numpy(), rtol=1e-5,
                               atol=1e-6)


def test_a_stride_estimates_the_every_pixel_value():
    frames, motion = pan(5, 40, 44, dx=2, gains=[1.0, 1.1, 0.9, 1.05, 1.0])
    full, strided = warp_error(frames, motion), warp_error(frames, motion, stride=4)
    assert strided.mean == pytest.approx(full.mean, rel=0.1) and strided.mean != full.mean


def test_ordering_agreement_from_per_sequence_rows():
    """Synthetic denoiser-eval rows: warp error agrees with tPSNR's order on 4 of 5 sequences."""
    rows = []
    for s in range(5):
        for rank, method in enumerate(["student", "OIDN-fast", "noisy"]):
            warp = 1.0 + rank + 0.1 * s
            tpsnr = 40.0 - 5 * rank
            if s == 4 and method == "OIDN-fast":
                warp = 0.5  # flickers less than the student here, yet worse tPSNR
            rows.append({"method": method, "sequence": f"seq{s}", "warp": warp, "tpsnr": tpsnr})
        rows.append({"method": "student", "sequence": "mean", "warp": 9, "tpsnr": 9})
    res = ordering_agreement(rows, ["noisy", "OIDN-fast", "student"], resamples=300)
    assert res["sequences"] == 5 and res["agreement"] == pytest.approx(0.8)
    assert res["per_sequence"]["seq4"] is False and res["per_sequence"]["seq0"] is True
    assert 0.5 < res["spearman"] < 1.0 and res["lo"] <= res["spearman"] <= res["hi"]
    with pytest.raises(ValueError, match="no sequence"):
        ordering_agreement(rows, ["noisy", "ONND"])
