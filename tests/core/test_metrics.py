"""Tests of denoiser.metrics: tonemapper, per-frame metrics, HDR-FLIP exposure, aggregation."""

import math

import numpy as np
import pytest
import torch

from denoiser import metrics as M


def _pair(n=3, size=32, noise=0.1, seed=0):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(n, 3, size, size, generator=g) ** 2 * 4.0
    out = (ref + noise * torch.randn(ref.shape, generator=g)).clamp_min(0)
    return out, ref


def test_tonemap_is_aces_then_srgb():
    x = torch.tensor([0.0, 0.001, 0.18, 1.0, 1e6, -5.0])
    y = M.tonemap(x)
    a = x.clamp_min(0)
    aces = ((a * (2.51 * a + 0.03)) / (a * (2.43 * a + 0.59) + 0.14)).clamp(0, 1)
    srgb = torch.where(aces <= 0.0031308, 12.92 * aces, 1.055 * aces.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
    assert torch.allclose(y, srgb, atol=1e-6)
    assert y[0] == 0 and y[-1] == 0 and abs(float(y[4]) - 1.0) < 1e-6
    assert torch.all(y[1:5].diff() > 0)


def test_psnr_matches_formula_and_caps_identical():
    out, ref = _pair()
    mse = ((M.tonemap(out) - M.tonemap(ref)) ** 2).mean(dim=(1, 2, 3))
    assert torch.allclose(M.psnr(out, ref), 10 * torch.log10(1 / mse), atol=1e-4)
    assert torch.all(M.psnr(ref, ref) == 100.0)
    worse = M.psnr(*_pair(noise=0.5))
    assert torch.all(worse < M.psnr(out, ref))


def test_ssim_identical_is_one_and_noise_lowers_it():
    out, ref = _pair()
    assert torch.allclose(M.ssim(ref, ref), torch.ones(3), atol=1e-5)
    s = M.ssim(out, ref)
    assert s.shape == (3,) and torch.all(s < 0.99)


def test_relmse_and_smape_values():
    ref = torch.ones(2, 3, 4, 4)
    out = 2 * ref
    assert torch.allclose(M.relmse(out, ref), torch.full((2,), 1 / 1.01))
    assert torch.allclose(M.smape(out, ref), torch.full((2,), 1 / 3.01))
    assert torch.all(M.relmse(ref, ref) == 0) and torch.all(M.smape(ref, ref) == 0)


def test_shape_mismatch_is_an_error():
    out, ref = _pair()
    with pytest.raises(ValueError):
        M.psnr(out[:, :, :16], ref)
    with pytest.raises(ValueError):
        M.relmse(out[:, :1], ref[:, :1])


def test_tpsnr_measures_temporal_change():
    _, ref = _pair(n=4, noise=0)
    assert torch.isnan(M.tpsnr(ref, ref)[0])
    assert torch.all(M.tpsnr(ref, ref)[1:] == 100.0)
    frozen = ref[:1].expand_as(ref)  # output that never changes while the reference does
    t = M.tpsnr(frozen, ref)
    assert torch.all(t[1:] < 40) and torch.isfinite(t[1:]).all()
    reset = torch.tensor([False, False, True, False])
    assert torch.isnan(M.tpsnr(ref, ref, reset)[2])


def test_flip_exposure_matches_flip_own_rule():
    import flip_evaluator

    _, ref = _pair(n=1, size=48, seed=3)
    ours = M.flip_exposure(ref)
    img = ref[0].permute(1, 2, 0).contiguous().numpy()
    _, _, params = flip_evaluator.evaluate(img, img, "HDR", applyMagma=False)
    assert abs(ours.start - params["startExposure"]) < 1e-3
    assert abs(ours.stop - params["stopExposure"]) < 0.02
    assert ours.num == params["numExposures"]


def test_flip_exposure_is_per_sequence_not_per_frame():
    _, ref = _pair(n=2, size=16)
    ref[1] *= 10  # a brighter second frame changes the sequence's range
    seq = M.flip_exposure(ref)
    first = M.flip_exposure(ref[:1])
    assert seq.start < first.start - 1.0
    assert M.flip_exposure(torch.zeros(1, 3, 8, 8)) == M.FlipExposure(0.0, 0.0, 2)


def test_flip_values_and_validation():
    out, ref = _pair(n=2, size=24)
    f = M.flip(out, ref)
    assert f.shape == (2,) and torch.all(f > 0) and torch.all(f < 1)
    assert torch.all(M.flip(ref, ref) == 0)
    bad = out.clone()
    bad[0, 0, 0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        M.flip(bad, ref)
    with pytest.raises(ValueError):
        M.flip(out[:, :, :8], ref)


def test_accumulator_warmup_and_mean_over_sequences():
    out, ref = _pair(n=5)
    acc = M.MetricAccumulator(metrics=("psnr", "smape", "tpsnr"), warmup=2)
    acc.update(out, ref, "a")
    acc.update(out[:3], ref[:3], "b")
    seqs = acc.per_sequence()
    psnr = M.psnr(out, ref)
    assert seqs["a"]["frames"] == 3 and seqs["b"]["frames"] == 1
    assert math.isclose(seqs["a"]["psnr"], float(psnr[2:].mean()), rel_tol=1e-5)
    assert math.isclose(seqs["b"]["psnr"], float(psnr[2]), rel_tol=1e-5)
    overall = acc.compute()
    assert math.isclose(overall["psnr"], (seqs["a"]["psnr"] + seqs["b"]["psnr"]) / 2, rel_tol=1e-6)
    assert len(acc.frame_rows()) == 8 and len(acc.frame_rows(include_warmup=False)) == 4


def test_accumulator_streaming_matches_whole_sequence_tpsnr():
    out, ref = _pair(n=4)
    whole = M.MetricAccumulator(metrics=("tpsnr",))
    whole.update(out, ref, "s")
    streamed = M.MetricAccumulator(metrics=("tpsnr",))
    for t in range(4):
        streamed.update(out[t:t + 1], ref[t:t + 1], "s")
    expected = M.tpsnr(out, ref)
    got = [r["tpsnr"] for r in streamed.frame_rows()]
    assert math.isnan(got[0])
    assert np.allclose(got[1:], expected[1:].numpy(), atol=1e-4)
    assert math.isclose(whole.compute()["tpsnr"], streamed.compute()["tpsnr"], rel_tol=1e-5)


def test_accumulator_batch_of_windows_with_resets():
    out, ref = _pair(n=4)
    batch_out = torch.stack([out, out.flip(0)])
    batch_ref = torch.stack([ref, ref.flip(0)])
    reset = torch.tensor([[True, False, True, False], [True, False, False, False]])
    acc = M.MetricAccumulator(metrics=("psnr", "tpsnr", "flip"), warmup=1)
    acc.update(batch_out, batch_ref, ["x", "y"], frame_index=torch.arange(4).expand(2, 4), reset=reset)
    rows = {(r["sequence"], r["frame"]): r for r in acc.frame_rows()}
    assert rows[("x", 2)]["warmup"] and not rows[("x", 3)]["warmup"]
    assert math.isnan(rows[("x", 2)]["tpsnr"]) and not math.isnan(rows[("y", 2)]["tpsnr"])
    assert "flip" not in rows[("x", 0)] and rows[("x", 1)]["flip"] > 0
    assert acc.per_sequence()["x"]["frames"] == 2 and acc.per_sequence()["y"]["frames"] == 3


def test_unknown_metric_is_rejected():
    with pytest.raises(ValueError, match="unknown metric"):
        M.MetricAccumulator(metrics=("psnr", "lpips"))
