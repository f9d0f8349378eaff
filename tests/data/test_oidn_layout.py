"""layout=oidn (denoiser/data/layouts/oidn.py, conf/layout/oidn.yaml): OIDN-named files, one feature per
file, written with OpenEXR from the pixels of a native-layout sequence, read into the same buffers
(motion zero: OIDN's files carry none); single images, OIDN's reference rule, the spp choice, and
one-line errors for a gap in a sequence and a missing feature file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from denoiser.buffers import FRAME_INPUTS
from denoiser.configs import load_layout
from denoiser.data import exr
from denoiser.data.dataset import SequenceDataset, index_split
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import UserError

BUFFERS = list(FRAME_INPUTS)
RGB = ("R", "G", "B")


def write_feature(path: Path, array: np.ndarray, names=RGB) -> None:
    """One feature ``[H, W, C]`` as its own EXR file (OIDN's naming: channels R, G, B; a 1-channel Y)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    exr.write_channels(path, {n: array[..., i] for i, n in enumerate(names)})


def write_oidn_frame(base: Path, frame: dict, spp: int = 4, reference: str | None = "ref", depth: bool = True) -> None:
    write_feature(base.with_name(f"{base.name}_{spp:04d}spp.hdr.exr"), frame["color"])
    write_feature(base.with_name(f"{base.name}_{spp:04d}spp.alb.exr"), frame["albedo"])
    write_feature(base.with_name(f"{base.name}_{spp:04d}spp.nrm.exr"), frame["normal"])
    if depth:
        write_feature(base.with_name(f"{base.name}_{spp:04d}spp.z.exr"), frame["depth"], names=("Y",))
    if reference:
        write_feature(base.with_name(f"{base.name}_{reference}.hdr.exr"), frame["reference"])


@pytest.fixture
def same_pixels(tmp_path):
    """A native val split (a 3-frame sequence) and the same pixels in OIDN's naming (frames 5, 6, 7 of
    ``shot`` in a sub-folder); returns both roots and the written buffers."""
    native, oidn = tmp_path / "native", tmp_path / "oidn"
    written = write_synthetic_sequence(native / "val" / "shot", frames=3, width=32, height=32, labeled=True, seed=3)
    for t in range(3):
        write_oidn_frame(oidn / "val" / "scene1" / f"shot_f{5 + t:04d}", {k: v[t] for k, v in written.items()})
    return native, oidn, written


def items(root: Path, layout_name: str, **fields) -> list[dict]:
    layout = load_layout(layout_name)
    for k, v in fields.items():
        setattr(layout, k, v)
    sources = index_split(layout, root, "val")
    data = SequenceDataset(sources, layout, BUFFERS)
    return [data[i] for i in range(len(data))]


def test_oidn_named_files_read_into_the_native_layouts_buffers(same_pixels):
    native, oidn, _ = same_pixels
    (a,), (b,) = items(native, "native"), items(oidn, "oidn")
    assert b["sequence"] == "val/shot" and b["color"].shape == (3, 3, 32, 32)
    for buffer in (*(b for b in FRAME_INPUTS if b != "motion"), "reference"):
        assert torch.equal(a[buffer], b[buffer]), buffer
    assert torch.equal(b["reset"], a["reset"]) and torch.equal(b["frame_index"], torch.arange(3))
    assert not torch.equal(a["motion"], torch.zeros_like(a["motion"]))   # the native sequence moves
    assert torch.equal(b["motion"], torch.zeros_like(a["motion"]))       # OIDN's files carry no motion


def test_single_images_oidns_reference_rule_and_the_spp_choice(tmp_path):
    written = write_synthetic_sequence(tmp_path / "native" / "val" / "x", frames=2, width=32, height=32, seed=1)
    one, two = ({k: v[t] for k, v in written.items()} for t in range(2))
    root = tmp_path / "oidn"
    write_oidn_frame(root / "val" / "still", one, spp=1, reference=None, depth=False)   # no _ref: the most
    write_oidn_frame(root / "val" / "still", {**two, "color": two["reference"]}, spp=1024, reference=None, depth=False)
    write_oidn_frame(root / "val" / "still", {**one, "color": one["color"] * 2}, spp=16, reference=None, depth=False)
    (item,) = items(root, "oidn")
    assert item["sequence"] == "val/still" and item["color"].shape[0] == 1      # a 1-frame sequence
    assert torch.equal(item["color"][0], torch.from_numpy(one["color"]).permute(2, 0, 1))    # the fewest samples
    assert torch.equal(item["reference"][0], torch.from_numpy(two["reference"]).permute(2, 0, 1))  # 1024 spp
    assert torch.equal(item["depth"], torch.ones_like(item["depth"]))           # no z file: the constant
    (item16,) = items(root, "oidn", spp=16)
    assert torch.equal(item16["color"][0], torch.from_numpy(one["color"] * 2).permute(2, 0, 1))


def test_a_gap_or_a_missing_feature_file_is_one_line_naming_it(same_pixels):
    _, oidn, _ = same_pixels
    folder = oidn / "val" / "scene1"
    (folder / "shot_f0006_0004spp.alb.exr").unlink()
    with pytest.raises(UserError, match=r"shot frame 6: no alb file"):
        items(oidn, "oidn")
    for path in folder.glob("shot_f0006_*"):
        path.unlink()
    with pytest.raises(UserError, match=r"frames 5\.\.7 miss 6 "):
        items(oidn, "oidn")
