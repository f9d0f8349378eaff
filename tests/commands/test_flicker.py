"""``denoiser-flicker``: folders of denoised frames measured side by side with the noisy render's
motion vectors (Blender and native layouts), its table, plot and flicker.json, and its errors."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.configs import compose_command
from helpers.eval_data import write_sequence
from helpers.flicker_data import write_blender_sequence, write_denoised

from denoiser.data import exr
from denoiser.errors import UserError

VENV_BIN = Path(sys.executable).parent


def flicker(overrides):
    from denoiser.commands.flicker import run

    return run(compose_command("flicker", overrides))


@pytest.mark.slow
def test_console_script_on_blender_frames_writes_table_plot_and_json(tmp_path):
    render = write_blender_sequence(tmp_path / "render" / "shot")
    steady = write_denoised(tmp_path / "steady")
    jumpy = write_denoised(tmp_path / "jumpy", jitter=0.1)
    out = tmp_path / "report"
    proc = subprocess.run([str(VENV_BIN / "denoiser-flicker"), str(jumpy), str(steady), "layout=blender",
                           f"motion={render}", f"out={out}"], capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert str(jumpy) in proc.stdout and str(steady) in proc.stdout and "noisy input" in proc.stdout
    record = json.loads((out / "flicker.json").read_text())
    assert [f["name"] for f in record["folders"]] == ["noisy input", str(jumpy), str(steady)]
    by = {f["name"]: f for f in record["folders"]}
    assert record["mask"] == "forward-backward"
    # the reference behind a sliding square with exact vectors: no flicker once disocclusions are masked
    assert by[str(steady)]["mean"] == pytest.approx(0.0, abs=1e-6)
    assert by[str(jumpy)]["mean"] > 1.0 and by["noisy input"]["mean"] > by[str(jumpy)]["mean"]
    assert by[str(steady)]["per_frame"][0] is None and len(by[str(steady)]["per_frame"]) == 5
    assert 0.8 < by[str(steady)]["kept"] < 1.0  # the uncovered wall is not counted
    assert (out / "flicker.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_native_layout_and_denoised_channels(tmp_path):
    """A native render (a pan, motion (+1, 0)) and frames in denoiser-eval's ``denoised`` buffer."""
    render = write_sequence(tmp_path / "render", frames=4, size=(16, 21), shift=1.0)
    folder = tmp_path / "ours"
    for t in range(4):
        ref = exr.read_channels(render / f"frame_{t:04d}.exr", ["reference.R", "reference.G", "reference.B"])
        exr.write_channels(folder / f"frame_{t:04d}.exr", {f"denoised.{c}": ref[f"reference.{c}"] for c in "RGB"})
    result = flicker([f"dirs=[{folder}]", f"motion={render}", "input=false", f"out={tmp_path}/o"])
    assert list(result) == [str(folder)]
    values = result[str(folder)]["per_frame"]
    assert math.isnan(values[0]) and len(values) == 4
    # the pattern is smooth and moves by exactly one pixel: nearly no flicker, the border column masked
    assert result[str(folder)]["mean"] < 0.5 and result[str(folder)]["kept"] == pytest.approx(20 / 21, abs=1e-6)
    assert json.loads((tmp_path / "o" / "flicker.json").read_text())["mask"] == "guide"


@pytest.mark.slow
def test_bad_input_is_one_clear_error(tmp_path):
    render = write_blender_sequence(tmp_path / "render", frames=3)
    good = write_denoised(tmp_path / "good", frames=3)
    short = write_denoised(tmp_path / "short", frames=2)
    (tmp_path / "empty").mkdir()
    novec = write_blender_sequence(tmp_path / "novec", frames=3, vector=False)
    base = ["layout=blender", f"motion={render}"]
    cases = [([f"dirs=[{tmp_path / 'missing'}]", *base], "folder does not exist"),
             ([f"dirs=[{tmp_path / 'empty'}]", *base], "no .exr frames"),
             ([f"dirs=[{good},{short}]", *base], "2 frame"),
             ([f"dirs=[{good}]", "layout=blender", f"motion={novec}"], "no motion pass")]
    for overrides, message in cases:
        with pytest.raises(UserError, match=message):
            flicker(overrides)
    out = tmp_path / "o"
    proc = subprocess.run([str(VENV_BIN / "denoiser-flicker"), str(good), str(short), "layout=blender",
                           f"motion={render}", f"out={out}"], capture_output=True, text=True, timeout=300, check=False)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: ") and str(short) in lines[0]
    assert not out.exists()  # nothing half-written


def test_plain_arguments_become_the_dirs_override():
    from denoiser.commands.flicker import dirs_argv

    assert dirs_argv(["a/b", "layout=blender", "it's"]) == ["layout=blender", "dirs=['a/b','it\\'s']"]
    assert np.array_equal(dirs_argv(["x=1"]), ["x=1"])
