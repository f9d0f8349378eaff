"""``data.extra_roots`` entries in a layout of their own: Blender Cycles renders joined to native
(Mitsuba) ones in one training set (the model release's data mix, issue 62)."""

from __future__ import annotations

import numpy as np
import pytest

from denoiser.buffers import FRAME_INPUTS
from denoiser.configs import load_layout
from denoiser.data import exr
from denoiser.data.datamodule import SequenceDataModule
from denoiser.data.dataset import WindowDataset, extra_root_entries, index_split
from denoiser.data.sequence import write_sequence_json
from denoiser.errors import ConfigError

H, W, FRAMES = 16, 20, 3


def cycles_frame(t: int, reference: bool) -> dict:
    """Channels of one Cycles frame as Blender names them (static content, no motion)."""
    rng = np.random.default_rng(7 + t)
    ref = np.random.default_rng(0).uniform(0.1, 4.0, (H, W, 3)).astype(np.float32)
    ch = {}

    def put(name, suffixes, arr):
        for i, s in enumerate(suffixes):
            ch[f"ViewLayer.{name}.{s}"] = np.ascontiguousarray(arr[..., i], dtype=np.float32)

    if reference:
        put("Combined", "RGBA", np.dstack([ref, np.ones((H, W))]))
        return ch
    put("Combined", "RGBA", np.dstack([ref * rng.uniform(0.5, 1.5, ref.shape), np.ones((H, W))]))
    put("Depth", "Z", np.full((H, W, 1), 3.0))
    put("Denoising Normal", "XYZ", np.dstack([np.zeros((H, W)), np.zeros((H, W)), np.ones((H, W))]))
    put("Denoising Albedo", "RGB", np.full((H, W, 3), 0.5))
    put("Vector", "XYZW", np.zeros((H, W, 4)))
    return ch


@pytest.fixture()
def roots(tmp_path):
    """A native root (train/mitsuba_000) and a Blender root (train/cycles_000) of the same frames."""
    blender = load_layout("blender")
    seq = tmp_path / "cycles" / "train" / "cycles_000"
    for t in range(FRAMES):
        exr.write_channels(seq / "noisy" / f"{t + 1:04d}.exr", cycles_frame(t, reference=False))
        exr.write_channels(seq / "reference" / f"{t + 1:04d}.exr", cycles_frame(t, reference=True))
    native_seq = tmp_path / "mitsuba" / "train" / "mitsuba_000"
    src = blender.open_sequence(seq)
    for t in range(FRAMES):
        frame, _ = blender.read_frame(src, t, [*FRAME_INPUTS, "reference"])
        exr.write_frame(native_seq / f"frame_{t:04d}.exr", frame)
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    write_sequence_json(native_seq, {
        "width": W, "height": H, "frames": FRAMES, "spp": 1, "buffers": [*FRAME_INPUTS, "reference"],
        "cameras": [{"to_world": eye, "fov": 30}] * FRAMES, "cuts": [], "scene": {"name": "t"},
        "renderer": {"name": "blender", "version": "5.0", "variant": "cycles"}, "seeds": {}, "render_seconds": {}})
    return tmp_path / "mitsuba", tmp_path / "cycles"


def test_an_extra_root_in_another_layout_reads_the_same_buffers(roots):
    mitsuba, cycles = roots
    native = load_layout("native")
    sources = index_split(native, mitsuba, "train", [{"root": str(cycles), "layout": "blender"}])
    assert [s.name for s in sources] == ["train/mitsuba_000", "train/cycles_000"]
    assert sources[0].layout is None and type(sources[1].layout).__name__ == "BlenderLayout"
    items = WindowDataset(sources, native, list(FRAME_INPUTS), window=FRAMES)
    a, b = items[0], items[1]
    for k in (*FRAME_INPUTS, "reference"):
        assert a[k].shape == b[k].shape == (FRAMES, a[k].shape[1], H, W)
        assert a[k].equal(b[k]), k


def test_the_data_module_joins_and_shares_a_root_of_another_layout(roots, tmp_path):
    mitsuba, cycles = roots
    dm = SequenceDataModule(root=str(mitsuba), layout=load_layout("native"), window=2, crop=8, batch_size=2,
                            extra_roots=[{"root": str(cycles), "layout": "blender"}], extra_share=0.5,
                            val_split=None, test_split=None, augment=None, cache_dir=str(tmp_path / "cache"))
    extra = dm.extra_windows()
    assert sorted(set(extra)) == [False, True] and len(extra) == 2 * (FRAMES - 1)
    batch = next(iter(dm.train_dataloader()))
    assert batch["color"].shape == (2, 2, 3, 8, 8) and batch["reference"].isfinite().all()


def test_a_malformed_extra_root_names_its_entry():
    with pytest.raises(ConfigError, match=r"extra_roots\[1\]"):
        extra_root_entries(["data/a", {"path": "data/b"}])
    with pytest.raises(ConfigError, match="unknown 'nope'"):
        extra_root_entries([{"root": "data/b", "layout": "nope"}])
