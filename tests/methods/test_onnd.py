"""ONND baseline (denoiser/methods/onnd.py): cross-regression against a loop, the online step, robustness."""

import itertools
import math

import numpy as np
import pytest
import torch

from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.methods.onnd import OnlineCrossRegression, cross_regression, half_buffers, half_variance


def loop_cross_regression(y, guide, var, feats, radius, ridge):
    """Plain per-pixel loop: weighted least squares with numpy, the intercept clamped to the window."""
    y, guide, var, feats = (t[0].double().numpy() for t in (y, guide, var, feats))
    _, h, w = y.shape
    out = np.zeros_like(y)
    for cy in range(h):
        for cx in range(w):
            xs, ys, ws = [], [], []
            for iy in range(cy - radius, cy + radius + 1):
                for ix in range(cx - radius, cx + radius + 1):
                    if 0 <= iy < h and 0 <= ix < w:
                        d = np.mean((guide[:, cy, cx] - guide[:, iy, ix]) ** 2) / (var[0, cy, cx] + var[0, iy, ix] + 1e-4)
                        ws.append(math.exp(-d))
                        xs.append(np.concatenate([[1.0], feats[:, iy, ix] - feats[:, cy, cx]]))
                        ys.append(y[:, iy, ix])
            x, yy, wt = np.array(xs), np.array(ys), np.array(ws)
            gram = (x * wt[:, None]).T @ x + np.diag([0.0] + [ridge] * (x.shape[1] - 1))
            beta = np.linalg.solve(gram, (x * wt[:, None]).T @ yy)
            out[:, cy, cx] = np.clip(beta[0], yy.min(axis=0), yy.max(axis=0))
    return torch.from_numpy(out)[None]


@pytest.mark.parametrize("size", [(5, 7), (9, 6)])
def test_cross_regression_matches_a_loop(size):
    g = torch.Generator().manual_seed(0)
    h, w = size
    y, guide = torch.rand(1, 3, h, w, generator=g), torch.rand(1, 3, h, w, generator=g)
    var = half_variance(y, guide)
    feats = torch.rand(1, 6, h, w, generator=g)
    # max_pixels=w: one output row per block, so the halo logic is exercised too
    got = cross_regression(y, guide, var, feats, radius=2, ridge=1e-2, max_pixels=w)
    want = loop_cross_regression(y, guide, var, feats, 2, 1e-2)
    assert got.shape == (1, 3, h, w)
    torch.testing.assert_close(got.double(), want, rtol=1e-4, atol=1e-4)
    whole = cross_regression(y, guide, var, feats, radius=2, ridge=1e-2)
    torch.testing.assert_close(whole, got, rtol=1e-5, atol=1e-5)


def test_half_buffers_split_the_samples():
    s = torch.arange(5.0).view(1, 5, 1, 1, 1).expand(1, 5, 3, 2, 2)
    a, b = half_buffers(s)
    assert a.shape == b.shape == (1, 3, 2, 2)
    assert a.flatten()[0] == 0.5 and b.flatten()[0] == 3.0
    with pytest.raises(ConfigError):
        half_buffers(s[:, :1])


def test_needs_samples():
    method = OnlineCrossRegression()
    with pytest.raises(ConfigError, match="per-sample"):
        method(random_frame(1, 8, 8, seed=0), True)


def test_sequence_with_reset_weights_change_and_hard_cases():
    method = OnlineCrossRegression(seed=0)
    before = [p.detach().clone() for p in method.net.parameters()]
    method.reset()
    for i in range(3):
        out = method(random_frame(1, 32, 32, seed=i, samples=4), reset=i == 0)
        assert out.shape == (1, 3, 32, 32) and torch.isfinite(out).all() and (out >= 0).all()
    after = list(method.net.parameters())
    assert any(not torch.equal(x, y) for x, y in zip(before, after)), "no online step happened"
    with torch.inference_mode():  # a caller's inference mode does not stop the online step
        stepped = [p.detach().clone() for p in method.net.parameters()]
        out = method(random_frame(1, 16, 16, seed=5, samples=2), reset=False)
    assert torch.isfinite(out).all() and any(not torch.equal(x, y) for x, y in zip(stepped, method.net.parameters()))
    method.reset()  # a new sequence re-initialises (keep_weights=False)
    assert all(torch.equal(x, y) for x, y in zip(before, method.net.parameters()))

    hard = OnlineCrossRegression(keep_weights=True)
    for i, (h, w) in enumerate([(32, 32), (13, 21), (1, 1), (7, 5)]):
        f = random_frame(1, h, w, seed=i, kind="hard", samples=3)
        s = f["samples"]
        s.view(-1)[:: 7] = 1e6  # fireflies
        s.view(-1)[1:: 11] = float("nan")
        s.view(-1)[2:: 13] = float("inf")
        s.view(-1)[3:: 17] = -float("inf")
        f["albedo"].view(-1)[::5] = float("nan")
        f["motion"].view(-1)[::3] = float("inf")
        for frame in (f, {**f, "samples": torch.zeros_like(s)}):  # and a black frame
            out = hard(frame, reset=False)
            assert out.shape == (1, 3, h, w) and torch.isfinite(out).all() and (out >= 0).all()


def smooth_sequence(frames=5, size=32, spp=4, seed=0):
    """A static smooth scene with multiplicative per-sample noise: ``(frame dicts, reference [1,3,H,W])``."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(0, 3, size), torch.linspace(0, 3, size), indexing="ij")
    ref = torch.stack([1.2 + torch.sin(xx + c) * torch.cos(yy - c) for c in (0.0, 1.0, 2.0)])[None]
    albedo = torch.full((1, 3, size, size), 0.5)
    normal = torch.zeros(1, 3, size, size)
    normal[:, 2] = 1
    seq = []
    for _ in range(frames):
        samples = (ref[:, None] * (1 + 0.6 * torch.randn(1, spp, 3, size, size, generator=g))).clamp_min(0)
        seq.append({"color": samples.mean(1), "samples": samples, "albedo": albedo, "normal": normal,
                    "depth": torch.ones(1, 1, size, size), "motion": torch.zeros(1, 2, size, size)})
    return seq, ref


def test_reduces_error_on_a_noisy_sequence():
    seq, ref = smooth_sequence()
    method = OnlineCrossRegression(lr=1e-3)
    method.reset()
    errors = []
    for i, f in enumerate(seq):
        out = method(f, reset=i == 0)
        errors.append((((out - ref) ** 2).mean() / ((f["color"] - ref) ** 2).mean()).item())
    # measured (this seed): MSE ratio ONND / noisy input 0.061, 0.051, 0.054, 0.051, 0.043 over the 5 frames
    assert errors[-1] < 0.1, errors
    assert errors[-1] < errors[0], errors  # history and training help after the first frame


def test_denoiser_eval_with_baselines_compare(tmp_path):
    """denoiser-eval's code path with ``baselines=compare``: ONND gets the samples, the others don't;
    on data without samples ONND stops with its one-line ConfigError."""
    from helpers.configs import compose_command

    from denoiser.commands.evaluate import run
    from denoiser.data.synthetic import write_synthetic_sequence
    from denoiser.tables import read_csv

    write_synthetic_sequence(tmp_path / "data/test/seq_000", frames=3, width=32, height=32, samples=4, seed=0)
    base = ["data=tiny", f"data.root={tmp_path / 'data'}", "baselines=compare", "~baselines.oidn_balanced",
            "~baselines.oidn_high", "metrics=[psnr]", "images.frame=null", "warmup=1"]
    overall = run(compose_command("eval", [*base, f"out_dir={tmp_path / 'out'}"], threads=1))
    assert list(overall) == ["noisy input", "OIDN-fast", "ONND"]
    # measured: PSNR noisy 44.2, OIDN-fast 43.2, ONND 51.6 dB
    assert overall["ONND"]["psnr"] > overall["noisy input"]["psnr"] + 3, overall
    assert {r["method"] for r in read_csv(tmp_path / "out" / "metrics.csv")} >= {"ONND"}

    write_synthetic_sequence(tmp_path / "plain/test/seq_000", frames=2, width=32, height=32, seed=1)
    with pytest.raises(ConfigError, match="per-sample"):
        run(compose_command("eval", [*base, f"data.root={tmp_path / 'plain'}", "~baselines.oidn_fast",
                                     f"out_dir={tmp_path / 'out2'}"], threads=1))


def test_denoiser_bench_times_onnd(tmp_path):
    """denoiser-bench with ``baselines=compare``: ONND is timed on frames that carry their samples
    (resampled to each size), its time includes the online step; a network beside it still runs
    on frames without samples (as in denoiser-eval)."""
    from helpers.checkpoints import tiny_checkpoint
    from helpers.configs import compose_command

    from denoiser.commands.bench import run as bench
    from denoiser.data.synthetic import write_synthetic_sequence

    write_synthetic_sequence(tmp_path / "data/test/seq_000", frames=2, width=32, height=32, samples=4, seed=0)
    rows = bench(compose_command("bench", [
        "data=tiny", f"data.root={tmp_path / 'data'}", "baselines=compare", "~baselines.oidn_balanced",
        "~baselines.oidn_high", f"ckpt=[{tiny_checkpoint(tmp_path / 'student.ckpt')}]", "sizes=[[16,16],[24,40]]", "repeats=2", "warmup=1", "use_backends=[eager]",
        f"out_dir={tmp_path / 'bench'}"], threads=1))
    onnd = [r for r in rows if r["method"] == "ONND"]
    assert [(r["height"], r["width"]) for r in onnd] == [(16, 16), (24, 40)]
    assert all(r["ms_median"] > 0 and r["backend"] == "PyTorch eager + online step" for r in onnd), onnd
    assert sorted(r["height"] for r in rows if r["method"] == "student" and r["status"] == "ok") == [16, 24]
    assert any(r["method"] == "OIDN-fast" for r in rows)


def test_online_steps_lower_the_self_supervised_loss():
    """The same frame again and again (no history): each step lowers the cross loss a little.
    Measured: 0.00534 -> 0.00532 after 12 steps at lr 1e-3 (deterministic: seeded network, fixed frame)."""
    seq, _ = smooth_sequence(frames=1)
    method = OnlineCrossRegression(lr=1e-3)
    losses = []
    for _ in range(12):
        method(seq[0], reset=True)
        losses.append(method.last_loss)
    assert losses[-1] < losses[0], losses
    assert all(later <= earlier + 1e-7 for earlier, later in itertools.pairwise(losses)), losses


def test_compare_is_default_plus_onnd():
    """conf/baselines/compare.yaml composes default.yaml and adds ONND, in eval and bench alike."""
    from helpers.configs import compose_command

    ev = compose_command("eval", ["baselines=compare"], threads=3)
    bench = compose_command("bench", ["baselines=compare"], threads=3)
    default = compose_command("eval", [], threads=3)
    assert list(ev.baselines) == [*default.baselines, "onnd"]
    assert all(ev.baselines[k] == default.baselines[k] for k in default.baselines)
    assert bench.baselines.noisy is None and bench.baselines.onnd == ev.baselines.onnd
    assert ev.baselines.onnd._target_ == "denoiser.methods.onnd.OnlineCrossRegression" and ev.baselines.onnd.threads == 3


def test_resize_frame_resamples_each_sample():
    """denoiser-bench resizes ``samples [1, S, 3, h, w]`` sample by sample, like ``color``."""
    import torch.nn.functional as F

    from denoiser.frames import resize_frame

    f = random_frame(1, 8, 12, seed=0, samples=3)
    out = resize_frame(f, 16, 24)
    assert out["samples"].shape == (1, 3, 3, 16, 24) and out["color"].shape == (1, 3, 16, 24)
    want = F.interpolate(f["samples"][:, 1], size=(16, 24), mode="bilinear", align_corners=False)
    torch.testing.assert_close(out["samples"][:, 1], want)


@pytest.mark.parametrize("centre", [0.0, 30.0])
def test_initial_filter_is_set_by_centre_logit(centre):
    """The first frame of a fresh network is the pilot estimate filtered by the initial kernel:
    exactly the pilot with a dominant centre logit (identity filter), its k x k box mean with 0."""
    seq, _ = smooth_sequence(frames=1)
    f = seq[0]
    method = OnlineCrossRegression(centre_logit=centre, kernel_size=3)
    out = method(f, reset=True)
    a, b = half_buffers(f["samples"])
    y_a, y_b = torch.log1p(a), torch.log1p(b)
    feats = torch.cat([f["albedo"], f["normal"]], dim=1)
    var = half_variance(y_a, y_b)
    pilot = 0.5 * (cross_regression(y_a, y_b, var, feats) + cross_regression(y_b, y_a, var, feats))
    if centre:
        expected = torch.expm1(pilot)
    else:  # 3x3 box over the in-image taps
        box = torch.nn.functional.avg_pool2d(pilot, 3, stride=1, padding=1, count_include_pad=False)
        expected = torch.expm1(box)
    torch.testing.assert_close(out, expected, rtol=1e-4, atol=1e-5)
