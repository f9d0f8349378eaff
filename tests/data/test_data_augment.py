"""Augmentation keeps meaning: proved by warping, by normals recomputed from depth, and by values.

The synthetic sequence has exact integer backward motion (frame t = frame t-1 sampled at
p + motion_t(p)), so after any flip/transpose, warping frame t-1 by the *transformed* motion
must still land exactly on frame t. The warp and the normal-from-depth formula below are
written here, independently of the code under test.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from denoiser.buffers import FRAME_INPUTS, native_channels
from denoiser.data import augment as aug
from denoiser.data.augment import Augment
from denoiser.data.dataset import WindowDataset, index_split
from denoiser.data.layouts import NativeLayout
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import ConfigError

NATIVE = {b: list(native_channels(b)) for b in (*FRAME_INPUTS, "reference")}  # the native layout's channels
INPUTS = list(FRAME_INPUTS)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("aug")
    write_synthetic_sequence(root / "train" / "s", frames=4, width=40, height=40, seed=5, samples=2, block=4)
    layout = NativeLayout(NATIVE)
    return WindowDataset(index_split(layout, root, "train"), layout, INPUTS, window=4, crop=24, samples=True)


def warp_mismatch(item: dict, buffer: str) -> tuple[int, int]:
    """(mismatching, checked) pixels of ``buffer`` warped from t-1 to t with nearest lookup."""
    x = item[buffer].numpy()
    m = item["motion"].numpy()
    T, _, H, W = x.shape
    bad = checked = 0
    ys, xs = np.mgrid[0:H, 0:W]
    for t in range(1, T):
        if item["reset"][t]:
            continue
        qx = xs + np.rint(m[t, 0]).astype(int)
        qy = ys + np.rint(m[t, 1]).astype(int)
        ok = (qx >= 0) & (qx < W) & (qy >= 0) & (qy < H)
        prev = x[t - 1][:, qy[ok], qx[ok]]
        cur = x[t][:, ys[ok], xs[ok]]
        bad += int((~np.isclose(prev, cur, rtol=1e-6, atol=0)).any(axis=0).sum())
        checked += int(ok.sum())
    return bad, checked


def normals_from_depth(depth: np.ndarray) -> np.ndarray:
    """Camera-space normal of z = depth[y, x]: pixel (x, y) is at (x, -y, z) (y up, z forward)."""
    dy, dx = np.gradient(depth.astype(np.float64))
    n = np.stack([dx, -dy, -np.ones_like(dx)])
    return n / np.linalg.norm(n, axis=0)


def assert_meaning_kept(item: dict) -> None:
    for b in ("reference", "albedo", "depth"):
        bad, checked = warp_mismatch(item, b)
        assert checked > 0.5 * 3 * 24 * 24 and bad == 0, (b, bad, checked)
    for t in range(item["depth"].shape[0]):
        want = normals_from_depth(item["depth"][t, 0].numpy())[:, 1:-1, 1:-1]
        np.testing.assert_allclose(item["normal"][t].numpy()[:, 1:-1, 1:-1], want, atol=2e-5)


TRANSFORMS = {
    "identity": lambda it: it,
    "hflip": aug.hflip,
    "vflip": aug.vflip,
    "transpose": aug.transpose,
    "transpose+hflip": lambda it: aug.hflip(aug.transpose(it)),
    "hflip+vflip+transpose": lambda it: aug.transpose(aug.vflip(aug.hflip(it))),
}


@pytest.mark.parametrize("name", list(TRANSFORMS))
def test_spatial_transforms_keep_motion_and_normals(dataset, name):
    torch.manual_seed(1)
    item = dataset[0]
    assert_meaning_kept(item)  # the synthetic data itself is consistent
    out = TRANSFORMS[name](item)
    assert_meaning_kept(out)
    if name != "identity":
        assert not torch.equal(out["reference"], item["reference"])


def test_the_warp_check_detects_untransformed_motion(dataset):
    item = dataset[0]
    broken = aug.hflip(item)
    broken["motion"] = item["motion"].flip(-1)  # flipped field, x component not negated
    assert warp_mismatch(broken, "reference")[0] > 0
    broken = aug.transpose(item)
    broken["normal"] = item["normal"].transpose(-1, -2)  # moved but components not swapped
    with pytest.raises(AssertionError):
        assert_meaning_kept(broken)


def test_random_augment_keeps_meaning(dataset):
    a = Augment(flip=True, transpose=True, exposure=None, permute_channels=False)
    g = torch.Generator().manual_seed(0)
    item = dataset[0]
    seen = set()
    for _ in range(12):
        out = a(item, generator=g)
        assert_meaning_kept(out)
        seen.add(out["reference"][0, 0, 0, :3].numpy().tobytes())
    assert len(seen) > 2


def test_exposure_scales_radiance_together(dataset):
    item = dataset[0]
    a = Augment(flip=False, transpose=False, exposure=[0.25, 4.0])
    g = torch.Generator().manual_seed(3)
    factors = []
    for _ in range(6):
        out = a(item, generator=g)
        k = (out["reference"] / item["reference"]).mean().item()
        factors.append(k)
        assert 0.25 <= k <= 4.0
        for b in ("color", "reference", "samples"):
            torch.testing.assert_close(out[b], item[b] * k, rtol=1e-5, atol=0)
        for b in FRAME_INPUTS[1:]:
            assert torch.equal(out[b], item[b])
    assert max(factors) / min(factors) > 1.5


def test_channel_permutation_is_shared(dataset):
    item = dataset[0]
    a = Augment(flip=False, transpose=False, exposure=None, permute_channels=True)
    g = torch.Generator().manual_seed(0)
    perms = set()
    for _ in range(10):
        out = a(item, generator=g)
        perm = [next(j for j in range(3) if torch.equal(out["albedo"][:, i], item["albedo"][:, j])) for i in range(3)]
        perms.add(tuple(perm))
        for b in ("color", "reference"):
            assert torch.equal(out[b], item[b][:, perm])
        assert torch.equal(out["samples"], item["samples"][:, :, perm])
        for b in ("normal", "depth", "motion"):
            assert torch.equal(out[b], item[b])
    assert len(perms) > 1


def test_transpose_skipped_for_non_square_crops():
    item = {"color": torch.rand(2, 3, 4, 6), "motion": torch.rand(2, 2, 4, 6)}
    a = Augment(flip=False, transpose=True)
    for s in range(8):
        assert a(item, generator=torch.Generator().manual_seed(s))["color"].shape == (2, 3, 4, 6)


def test_bad_exposure_range():
    with pytest.raises(ConfigError, match="data.augment.exposure"):
        Augment(exposure=[2.0, 1.0])


def _noise_reference(x: np.ndarray, ref: np.ndarray, f: float) -> np.ndarray:
    """ref + f (x - ref), one pixel at a time (``x`` ``[..., 3, H, W]``, ``ref`` broadcast to it)."""
    ref = np.broadcast_to(ref, x.shape)
    out = np.empty_like(x)
    for idx in np.ndindex(*x.shape):
        out[idx] = ref[idx] + f * (x[idx] - ref[idx])
    return out


def test_noise_scale_shrinks_the_residual_of_labeled_items(dataset):
    item = dataset[0]
    out = Augment(flip=False, transpose=False, noise_scale=[0.4, 0.4])(item, generator=torch.Generator().manual_seed(0))
    ref = item["reference"].numpy()
    np.testing.assert_allclose(out["color"].numpy(), _noise_reference(item["color"].numpy(), ref, 0.4),
                               rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(out["samples"].numpy(), _noise_reference(item["samples"].numpy(), ref[:, None], 0.4),
                               rtol=1e-6, atol=1e-6)
    for b in ("reference", *FRAME_INPUTS[1:]):  # the target and the guides stay
        assert torch.equal(out[b], item[b])
    residual = (out["color"] - out["reference"]).std() / (item["color"] - item["reference"]).std()
    assert abs(float(residual) - 0.4) < 1e-4


def test_noise_scale_draws_within_its_range_and_skips_unlabeled_items(dataset):
    item = dataset[0]
    a = Augment(flip=False, transpose=False, noise_scale=[0.2, 1.0], noise_scale_prob=0.5)
    g = torch.Generator().manual_seed(1)
    factors = []
    for _ in range(24):
        out = a(item, generator=g)
        d = item["color"] - item["reference"]
        factors.append(float(((out["color"] - item["reference"]) * d).sum() / (d * d).sum()))
    kept = [f for f in factors if f == 1.0]
    assert 4 <= len(kept) <= 20 and all(0.2 - 1e-6 <= f <= 1.0 + 1e-6 for f in factors)
    assert max(f for f in factors if f != 1.0) / min(factors) > 1.5
    unlabeled = {**item, "labeled": torch.tensor(False)}
    assert torch.equal(a(unlabeled, generator=g)["color"], item["color"])
    no_reference = {k: v for k, v in item.items() if k != "reference"}
    out = Augment(flip=False, transpose=False, noise_scale=[0.5, 0.5])(no_reference, generator=g)
    assert torch.equal(out["color"], item["color"])


@pytest.mark.parametrize(("kwargs", "key"), [({"noise_scale": [0.5, 1.5]}, "noise_scale"),
                                            ({"noise_scale": [0.0, 1.0]}, "noise_scale"),
                                            ({"noise_scale": [0.5, 1.0], "noise_scale_prob": 2}, "noise_scale_prob")])
def test_bad_noise_scale(kwargs, key):
    with pytest.raises(ConfigError, match=f"data.augment.{key}"):
        Augment(**kwargs)
