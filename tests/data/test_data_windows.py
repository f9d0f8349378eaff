"""Window and crop indexing, camera cuts, in-order evaluation items (native layout, real EXRs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from denoiser.buffers import FRAME_INPUTS, native_channels
from denoiser.data.dataset import SequenceDataset, WindowDataset, index_split, reset_flags, window_starts
from denoiser.data.layouts import NativeLayout
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import UserError

NATIVE = {b: list(native_channels(b)) for b in (*FRAME_INPUTS, "reference")}  # the native layout's channels
INPUTS = list(FRAME_INPUTS)


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("windows")
    written = {
        "a": write_synthetic_sequence(root / "train" / "a", frames=6, width=32, height=24, cuts=[3], seed=1),
        "b": write_synthetic_sequence(root / "train" / "b", frames=4, width=32, height=24, seed=2, samples=2),
    }
    return root, written


def test_window_starts_and_reset_flags():
    assert list(window_starts(6, 4, 1)) == [0, 1, 2]
    assert list(window_starts(10, 4, 4)) == [0, 4]
    assert list(window_starts(3, 4, 1)) == []
    assert reset_flags(0, 4, [3]).tolist() == [True, False, False, True]
    assert reset_flags(2, 4, [3]).tolist() == [True, True, False, False]
    assert reset_flags(3, 3, [3]).tolist() == [True, False, False]
    assert reset_flags(1, 2, [5]).tolist() == [True, False]


def test_windows_index_every_run_of_T_frames(root):
    root, _ = root
    layout = NativeLayout(NATIVE)
    sources = index_split(layout, root, "train")
    assert [s.name for s in sources] == ["train/a", "train/b"]
    ds = WindowDataset(sources, layout, INPUTS, window=3, stride=1, crop=None)
    assert len(ds) == (6 - 3 + 1) + (4 - 3 + 1)
    got = [(ds[i]["sequence"], ds[i]["frame_index"].tolist()) for i in range(len(ds))]
    assert got[0] == ("train/a", [0, 1, 2]) and got[3] == ("train/a", [3, 4, 5]) and got[5] == ("train/b", [1, 2, 3])
    ds2 = WindowDataset(sources, layout, INPUTS, window=2, stride=2, crop=None)
    assert [ds2[i]["frame_index"][0].item() for i in range(len(ds2))] == [0, 2, 4, 0, 2]


def test_cut_sets_reset_inside_a_window(root):
    root, _ = root
    layout = NativeLayout(NATIVE)
    ds = WindowDataset(index_split(layout, root, "train")[:1], layout, INPUTS, window=4, crop=None)
    flags = {ds[i]["frame_index"][0].item(): ds[i]["reset"].tolist() for i in range(len(ds))}
    assert flags == {0: [True, False, False, True], 1: [True, False, True, False], 2: [True, True, False, False]}
    # a window spanning the cut: the frame after the cut is new content (motion zero there)
    item = ds[0]
    assert item["motion"][3].abs().sum() == 0 and item["motion"][1].abs().sum() > 0


def find_offset(full: np.ndarray, patch: np.ndarray) -> tuple[int, int]:
    """(top, left) where ``patch`` [C, h, w] sits in ``full`` [H, W, C] (exact match)."""
    h, w = patch.shape[-2:]
    hits = [(y, x) for y in range(full.shape[0] - h + 1) for x in range(full.shape[1] - w + 1)
            if np.array_equal(full[y:y + h, x:x + w].transpose(2, 0, 1), patch)]
    assert len(hits) == 1
    return hits[0]


def test_same_random_crop_for_all_frames_and_buffers(root):
    root, written = root
    layout = NativeLayout(NATIVE)
    sources = index_split(layout, root, "train")
    ds = WindowDataset(sources[1:], layout, INPUTS, window=3, crop=[8, 12], samples=True)
    torch.manual_seed(0)
    offsets = set()
    for _ in range(4):
        item = ds[len(ds) - 1]  # train/b frames 1..3
        assert item["color"].shape == (3, 3, 8, 12) and item["samples"].shape == (3, 2, 3, 8, 12)
        assert item["depth"].shape == (3, 1, 8, 12) and item["motion"].shape == (3, 2, 8, 12)
        top, left = find_offset(written["b"]["reference"][1], item["reference"][0].numpy())
        offsets.add((top, left))
        for t in range(3):
            f = 1 + t
            for name in (*FRAME_INPUTS, "reference"):
                expect = written["b"][name][f][top:top + 8, left:left + 12].transpose(2, 0, 1)
                np.testing.assert_array_equal(item[name][t].numpy(), expect, err_msg=f"{name} frame {f}")
            s = written["b"]["samples"][f][:, top:top + 8, left:left + 12].transpose(0, 3, 1, 2)
            np.testing.assert_array_equal(item["samples"][t].numpy(), s)
            np.testing.assert_allclose(item["samples"][t].mean(0), item["color"][t], rtol=1e-5, atol=1e-6)
    assert len(offsets) > 1  # the crop is random from item to item


def test_crop_larger_than_frame_and_too_short_sequences(root):
    root, _ = root
    layout = NativeLayout(NATIVE)
    sources = index_split(layout, root, "train")
    with pytest.raises(UserError, match=r"frames are 32x24, smaller than data.crop 40x40"):
        WindowDataset(sources, layout, INPUTS, window=2, crop=40)
    with pytest.raises(UserError, match=r"no sequence has data.window=7 frames \(longest has 6\)"):
        WindowDataset(sources, layout, INPUTS, window=7)


def test_labeled_split_needs_reference(tmp_path):
    write_synthetic_sequence(tmp_path / "train" / "u", frames=2, width=16, height=16, labeled=False)
    layout = NativeLayout(NATIVE)
    sources = index_split(layout, tmp_path, "train")
    with pytest.raises(UserError, match=r"train/u: sequence lacks buffer\(s\) reference"):
        WindowDataset(sources, layout, INPUTS, window=2)
    ds = WindowDataset(sources, layout, INPUTS, window=2, labeled=False)
    assert "reference" not in ds[0] and ds[0]["labeled"].item() is False
    ds = WindowDataset(sources, layout, INPUTS, window=2, labeled=False, fill_reference=True)
    assert ds[0]["reference"].abs().sum() == 0


def test_missing_split_directory(tmp_path):
    with pytest.raises(UserError, match=r"val: split directory does not exist"):
        index_split(NativeLayout(NATIVE), tmp_path, "val")
    (tmp_path / "val").mkdir()
    with pytest.raises(UserError, match=r"val: split has no sequences"):
        index_split(NativeLayout(NATIVE), tmp_path, "val")


def test_evaluation_whole_sequences_in_order(root):
    root, written = root
    layout = NativeLayout(NATIVE)
    sources = index_split(layout, root, "train")
    ds = SequenceDataset(sources, layout, INPUTS)
    assert len(ds) == 2
    item = ds[0]
    assert item["color"].shape == (6, 3, 24, 32) and item["frame_index"].tolist() == list(range(6))
    assert item["reset"].tolist() == [True, False, False, True, False, False]
    np.testing.assert_array_equal(item["reference"][4].numpy(), written["a"]["reference"][4].transpose(2, 0, 1))
    pieces = SequenceDataset(sources, layout, INPUTS, window=4)
    got = [(p["sequence"], p["frame_index"].tolist(), p["reset"].tolist()) for p in pieces]
    assert got == [("train/a", [0, 1, 2, 3], [True, False, False, True]),
                   ("train/a", [4, 5], [False, False]),  # continues the history of the previous piece
                   ("train/b", [0, 1, 2, 3], [True, False, False, False])]
    starts_at_cut = SequenceDataset(sources[:1], layout, INPUTS, window=3)
    assert [p["reset"].tolist() for p in starts_at_cut] == [[True, False, False], [True, False, False]]
