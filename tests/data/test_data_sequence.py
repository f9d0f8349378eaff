"""sequence.json schema: write/load round trip, validation errors, agreement with the disk."""

from __future__ import annotations

import json

import numpy as np
import pytest

from denoiser.buffers import FRAME_INPUTS
from denoiser.data import exr
from denoiser.data.layouts import NativeLayout
from denoiser.data.sequence import (
    FORMAT_VERSION,
    SequenceMeta,
    load_sequence_json,
    parse_sequence_meta,
    write_sequence_json,
)
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import UserError

NATIVE = {"color": ["color.R", "color.G", "color.B"], "albedo": ["albedo.R", "albedo.G", "albedo.B"],
          "normal": ["normal.X", "normal.Y", "normal.Z"], "depth": ["depth.Z"], "motion": ["motion.X", "motion.Y"],
          "reference": ["reference.R", "reference.G", "reference.B"]}


def meta_dict(frames=3, **over):
    eye = [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    d = {
        "format_version": FORMAT_VERSION, "width": 32, "height": 16, "frames": frames, "spp": 4,
        "buffers": [*FRAME_INPUTS, "reference"],
        "cameras": [{"to_world": eye, "fov": 40.0} for _ in range(frames)], "cuts": [2],
        "scene": {"name": "box", "effects": ["dof"]},
        "renderer": {"name": "mitsuba", "version": "3.9.0", "variant": "scalar_rgb"},
        "seeds": {"scene": 1, "frames": [1, 2, 3]}, "render_seconds": {"color": 0.5, "reference": 12.0},
    }
    d.update(over)
    return d


def test_write_and_load_roundtrip(tmp_path):
    written = write_sequence_json(tmp_path, meta_dict(custom_note="kept"))
    assert (tmp_path / "sequence.json").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["sequence.json"]  # no temporary file left
    meta = load_sequence_json(tmp_path)
    assert meta == written
    assert isinstance(meta, SequenceMeta)
    assert (meta.width, meta.height, meta.frames, meta.spp, meta.cuts) == (32, 16, 3, 4, (2,))
    assert meta.labeled and meta.scene_name == "box" and meta.scene["effects"] == ["dof"]
    assert meta.cameras[1].fov == 40.0 and meta.cameras[0].to_world[3][3] == 1.0
    assert meta.renderer["variant"] == "scalar_rgb" and meta.render_seconds["reference"] == 12.0
    assert meta.extra == {"custom_note": "kept"}
    again = write_sequence_json(tmp_path / "b" / "sequence.json", meta)
    assert again == meta
    assert json.loads((tmp_path / "b" / "sequence.json").read_text())["custom_note"] == "kept"


@pytest.mark.parametrize("change, message", [
    (lambda d: d.pop("width"), "missing required key 'width'"),
    (lambda d: d.pop("cameras"), "missing required key 'cameras'"),
    (lambda d: d.update(frames=0), "key 'frames': must be >= 1"),
    (lambda d: d.update(spp="4"), "key 'spp': must be an integer"),
    (lambda d: d.update(buffers=["color", "shadow"]), "key 'buffers': unknown buffer"),
    (lambda d: d.update(buffers=["albedo"]), "key 'buffers': must include color"),
    (lambda d: d["cameras"].pop(), "key 'cameras': has 2 entries but frames is 3"),
    (lambda d: d["cameras"][1].update(fov=0), r"key 'cameras\[1\].fov'"),
    (lambda d: d["cameras"][0].update(to_world=[[1, 0], [0, 1]]), r"key 'cameras\[0\].to_world': must be a 4x4"),
    (lambda d: d.update(cuts=[5]), "key 'cuts': frame index 5 out of range"),
    (lambda d: d.update(cuts=[2, 1]), "key 'cuts': must be sorted"),
    (lambda d: d.update(scene={"effects": []}), "key 'scene.name'"),
    (lambda d: d["renderer"].pop("version"), "key 'renderer.version'"),
    (lambda d: d.update(seeds={"a": 1.5}), "key 'seeds.a'"),
    (lambda d: d.update(render_seconds={"color": -1}), "key 'render_seconds.color'"),
    (lambda d: d.update(format_version=99), "key 'format_version': 99 is newer"),
    (lambda d: d["buffers"].append("samples"), "key 'sample_count': must be >= 1"),
])
def test_validation_names_file_and_key(tmp_path, change, message):
    d = meta_dict()
    change(d)
    path = tmp_path / "sequence.json"
    path.write_text(json.dumps(d))
    with pytest.raises(UserError, match=message) as info:
        load_sequence_json(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_write_refuses_invalid_meta(tmp_path):
    with pytest.raises(UserError, match="missing required key 'spp'"):
        write_sequence_json(tmp_path, {k: v for k, v in meta_dict().items() if k != "spp"})
    assert not (tmp_path / "sequence.json").exists()


def test_not_json_and_missing(tmp_path):
    (tmp_path / "sequence.json").write_text("{width: 3")
    with pytest.raises(UserError, match="sequence.json: not valid JSON"):
        load_sequence_json(tmp_path)
    with pytest.raises(UserError, match="does not exist"):
        load_sequence_json(tmp_path / "other")
    with pytest.raises(UserError, match="top level must be a JSON object"):
        parse_sequence_meta([1, 2])


def test_frame_count_disagrees_with_disk(tmp_path):
    seq = tmp_path / "s"
    write_synthetic_sequence(seq, frames=3, width=16, height=16)
    (seq / "frame_0002.exr").unlink()
    with pytest.raises(UserError, match=r"sequence.json: key 'frames' says 3 but 2 frame file\(s\)"):
        NativeLayout(NATIVE).open_sequence(seq)


def test_frame_size_disagrees(tmp_path):
    seq = tmp_path / "s"
    write_synthetic_sequence(seq, frames=2, width=16, height=16)
    exr.write_frame(seq / "frame_0001.exr", {"color": np.ones((8, 16, 3), np.float32)})
    with pytest.raises(UserError, match=r"frame_0001.exr: is 16x8 but .*sequence.json \(width x height\) is 16x16"):
        NativeLayout(NATIVE).open_sequence(seq)


def test_declared_buffer_missing_in_frames(tmp_path):
    seq = tmp_path / "s"
    write_synthetic_sequence(seq, frames=1, width=16, height=16, labeled=False)
    d = json.loads((seq / "sequence.json").read_text())
    d["buffers"].append("reference")
    (seq / "sequence.json").write_text(json.dumps(d))
    with pytest.raises(UserError, match=r"frame_0000.exr: sequence.json lists buffer reference but channel\(s\) "
                                        r"reference.R, reference.G, reference.B are missing; present: albedo.B"):
        NativeLayout(NATIVE).open_sequence(seq)


def test_gap_in_frame_numbers(tmp_path):
    seq = tmp_path / "s"
    write_synthetic_sequence(seq, frames=3, width=16, height=16)
    (seq / "frame_0001.exr").rename(seq / "frame_0007.exr")
    with pytest.raises(UserError, match="expected frame 1 but found frame_0002.exr"):
        NativeLayout(NATIVE).open_sequence(seq)


def test_missing_sequence_json(tmp_path):
    seq = tmp_path / "s"
    write_synthetic_sequence(seq, frames=2, width=16, height=16, samples=2)
    (seq / "sequence.json").unlink()
    with pytest.raises(UserError, match="sequence.json: file does not exist"):
        NativeLayout(NATIVE).open_sequence(seq)
    src = NativeLayout(NATIVE, require_meta=False).open_sequence(seq)  # e.g. denoising a folder
    assert (src.frames, src.width, src.height, src.sample_count) == (2, 16, 16, 2)
    assert set(src.buffers) == {"color", "albedo", "normal", "depth", "motion", "reference", "samples"}
