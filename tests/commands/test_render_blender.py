"""``denoiser-render-blender``: a user's .blend file (built here with bpy: a moving cube, a light, a
camera, 3 frames at 32x32) rendered with Cycles into the blender layout, read back with the
denoiser's reader (``layout=blender``); its settings report, resume and refusals."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.blender import blender_python_or_skip, build_scene

from denoiser.buffers import FRAME_INPUTS
from denoiser.configs import load_layout

COMMAND = Path(sys.executable).parent / "denoiser-render-blender"


def render(python, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([str(COMMAND), f"blender_python={python}", "threads=2", "spp=2", "ref_spp=8", *args],
                          capture_output=True, text=True, check=False, timeout=300)


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    python = blender_python_or_skip()
    root = tmp_path_factory.mktemp("blend")
    return python, {name: build_scene(python, root / f"{name}.blend", **kw) for name, kw in
                    (("cube", {}), ("blurred", {"motion_blur": True}), ("no_camera", {"camera": False}))}


@pytest.mark.slow
def test_a_users_scene_renders_into_the_blender_layout_and_resumes(scenes, tmp_path):
    """The settings the results depend on are set and reported; noisy and reference frames read
    through layout=blender with every network input (the cube's motion in the Vector pass), the
    reference with another seed; a rerun keeps the frames on disk, a deleted frame is rendered
    again, other settings are refused, and split=unlabeled writes no reference."""
    python, blend = scenes
    out = tmp_path / "mine"
    done = render(python, f"scene={blend['cube']}", "frames=1-3", f"out={out}", "split=train")
    assert done.returncode == 0, done.stderr
    for setting in ("cycles.use_adaptive_sampling: True -> False", "cycles.pixel_filter_type: 'BLACKMAN_HARRIS' -> 'BOX'",
                    "cycles.filter_width: 1.5 -> 1.0", "cycles.use_animated_seed: False -> True",
                    "cycles.use_denoising: True -> False", "view layer 'ViewLayer' use_pass_vector: False -> True"):
        assert f"changed {setting}" in done.stdout, setting
    seq = out / "train" / "cube"
    layout = load_layout("blender")
    [found] = layout.list_sequences(out / "train")
    source = layout.open_sequence(found)
    assert source.frames == 3 and (source.width, source.height) == (32, 32) and source.labeled
    frame, _ = layout.read_frame(source, 1, [*FRAME_INPUTS, "reference"])
    assert {k: v.shape for k, v in frame.items()} == {"color": (32, 32, 3), "albedo": (32, 32, 3), "normal": (32, 32, 3),
                                                     "depth": (32, 32, 1), "motion": (32, 32, 2), "reference": (32, 32, 3)}
    assert np.abs(frame["motion"][..., 0]).max() > 0.5      # the cube moves 0.5 m per frame
    assert frame["depth"].min() < 10 and not np.array_equal(frame["color"], frame["reference"])
    info = json.loads((seq / "render.json").read_text())
    assert info["noisy"] == {"spp": 2, "seed": 1} and info["reference"] == {"spp": 8, "seed": 1001}
    assert info["frames"] == [1, 2, 3] and any("filter_width" in c for c in info["changed"])

    stamps = {p: p.stat().st_mtime_ns for p in seq.rglob("*.exr")}
    (seq / "noisy" / "0002.exr").unlink()
    again = render(python, f"scene={blend['cube']}", "frames=1-3", f"out={out}", "split=train")
    assert again.returncode == 0, again.stderr
    assert "noisy frame 2 " in again.stdout and "noisy frame 1 " not in again.stdout
    assert "reference frame" not in again.stdout
    assert all(p.stat().st_mtime_ns == t for p, t in stamps.items() if p.name != "0002.exr")
    other = render(python, f"scene={blend['cube']}", "frames=1-3", f"out={out}", "split=train", "spp=3")
    assert other.returncode == 2 and "rendered with other settings (noisy:" in other.stderr.strip().splitlines()[-1]

    unlabeled = render(python, f"scene={blend['cube']}", "frames=2-3", f"out={out}", "split=unlabeled")
    assert unlabeled.returncode == 0, unlabeled.stderr
    assert sorted(p.name for p in (out / "unlabeled" / "cube" / "noisy").iterdir()) == ["0002.exr", "0003.exr"]
    assert not (out / "unlabeled" / "cube" / "reference").exists()
    assert not layout.open_sequence(out / "unlabeled" / "cube").labeled


@pytest.mark.slow
@pytest.mark.parametrize("name, problem", [("blurred", "motion blur is on"), ("no_camera", "the scene has no camera")])
def test_a_scene_with_motion_blur_or_no_camera_is_refused(scenes, tmp_path, name, problem):
    python, blend = scenes
    done = render(python, f"scene={blend[name]}", f"out={tmp_path / 'out'}")
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and problem in lines[0] and str(blend[name]) in lines[0]
    assert not (tmp_path / "out").exists()


def test_without_the_bpy_venv_one_line_says_how_to_build_it(tmp_path):
    blend = tmp_path / "shot.blend"
    blend.write_bytes(b"BLENDER")
    done = render(tmp_path / "no_venv" / "python", f"scene={blend}", f"out={tmp_path / 'out'}")
    lines = done.stderr.strip().splitlines()
    assert done.returncode == 2 and len(lines) == 1 and "make blender-venv" in lines[0], done.stderr
    bad = render(tmp_path / "no_venv" / "python", f"scene={blend}", f"out={tmp_path / 'out'}", "split=training")
    assert bad.returncode == 2 and "split=training: not one of train, val, test, unlabeled" in bad.stderr
