"""denoiser/commands/tools/albedo_bound.py (``python -m denoiser.commands.tools.albedo_bound``): the ceiling that
remodulating with a noisy albedo sets (issue 12)."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from denoiser.commands.tools import albedo_bound
from denoiser.data import exr
from denoiser.metrics import psnr

H = W = 16


def load():
    return albedo_bound


def write(path: Path, color: np.ndarray, albedo: np.ndarray, layer: str = "ViewLayer") -> None:
    """One Blender-5-style multi-part frame of view layer ``layer``: ``color, albedo: [H, W, 3]``."""
    parts = [{f"{layer}.Combined.{c}": color[..., i] for i, c in enumerate("RGB")},
             {f"{layer}.Denoising Albedo.{c}": albedo[..., i] for i, c in enumerate("RGB")}]
    exr.write_multipart(path, parts, names=[f"{layer}.Combined", f"{layer}.Denoising Albedo"])


def chw(x: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(x).permute(2, 0, 1)[None]


@pytest.mark.parametrize("layer", ["ViewLayer", "Studio"])   # any single view layer, as the Blender layout reads it
def test_bound_is_reference_irradiance_times_noisy_albedo(tmp_path, layer):
    rng = np.random.default_rng(0)
    seq = tmp_path / "split" / "wall"
    expected_noisy, expected_bound = [], []
    for t in range(4):
        albedo = rng.uniform(0.2, 0.9, (H, W, 3)).astype(np.float32)       # reference (area-average) albedo
        irradiance = np.full((H, W, 3), 0.5 + 0.1 * t, np.float32)          # smooth lighting
        noisy_albedo = (albedo * rng.uniform(0.5, 1.5, (H, W, 3))).astype(np.float32)
        noisy = (irradiance * noisy_albedo * rng.uniform(0.7, 1.3, (H, W, 3))).astype(np.float32)
        write(seq / "noisy" / f"{t + 1:04d}.exr", noisy, noisy_albedo, layer)
        write(seq / "reference" / f"{t + 1:04d}.exr", irradiance * albedo, albedo, layer)
        if t >= 2:  # the two warm-up frames are skipped
            ref = chw(irradiance * albedo)
            expected_noisy.append(psnr(chw(noisy), ref).item())
            expected_bound.append(psnr(chw(irradiance * noisy_albedo), ref).item())
    mod = load()
    n, b, frames = mod.sequence_bound(mod.load_layout("blender", mod.REFERENCE_ALBEDO), seq, warmup=2)
    assert frames == 2
    assert n == pytest.approx(np.mean(expected_noisy), abs=1e-4)
    assert b == pytest.approx(np.mean(expected_bound), abs=1e-4)
    assert n < b < 60.0  # the noisy albedo costs the bound; the input is below it


def test_clean_albedo_gives_no_ceiling_and_the_table_is_written(tmp_path):
    """An albedo equal to the reference's: the remodulated reference irradiance is the reference."""
    seq = tmp_path / "split" / "flat"
    albedo = np.full((H, W, 3), 0.5, np.float32)
    for t in range(3):
        write(seq / "noisy" / f"{t + 1:04d}.exr", albedo * 1.1, albedo)
        write(seq / "reference" / f"{t + 1:04d}.exr", albedo, albedo)
    out = tmp_path / "report" / "bound.md"
    assert load().main([str(tmp_path / "split"), "--out", str(out), "--warmup", "0"]) == 0
    row = next(line for line in out.read_text().splitlines() if line.startswith("| flat |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[1] == "3" and float(cells[3]) > 80.0 > float(cells[2])


def test_missing_reference_is_one_line_and_exit_2(tmp_path, capsys):
    seq = tmp_path / "split" / "s"
    albedo = np.full((H, W, 3), 0.5, np.float32)
    for t in range(3):
        write(seq / "noisy" / f"{t + 1:04d}.exr", albedo, albedo)
    (seq / "reference").mkdir()
    with pytest.raises(SystemExit) as exit_:
        load().main([str(tmp_path / "split")])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "0003.exr" in err[0] and "no reference frame" in err[0] and str(seq) in err[0]


def test_the_command_takes_key_value_arguments_and_refuses_mistakes_in_one_line(tmp_path):
    """``python -m denoiser.commands.tools.albedo_bound``: ``out=``/``warmup=`` as well as ``--out``; no
    sequences, a bad value and a missing argument are one line ``error: ...`` and exit 2."""
    seq = tmp_path / "split" / "flat"
    albedo = np.full((H, W, 3), 0.5, np.float32)
    for t in range(3):
        write(seq / "noisy" / f"{t + 1:04d}.exr", albedo * 1.1, albedo)
        write(seq / "reference" / f"{t + 1:04d}.exr", albedo, albedo)
    command = [sys.executable, "-m", "denoiser.commands.tools.albedo_bound"]
    out = tmp_path / "bound.md"
    ok = subprocess.run([*command, str(tmp_path / "split"), f"out={out}", "warmup=1"], capture_output=True,
                        text=True, check=False)
    assert ok.returncode == 0, ok.stderr
    assert "| flat | 2 |" in out.read_text() and "| flat | 2 |" in ok.stdout
    for args, words in (([str(tmp_path / "nowhere")], "no sequences"), ([str(tmp_path / "split"), "warmup=x"], "warmup"),
                        ([str(tmp_path / "split"), "warmup=-1"], "negative"), ([], "split_dir")):
        bad = subprocess.run([*command, *args], capture_output=True, text=True, check=False)
        assert bad.returncode == 2 and bad.stderr.startswith("error: ") and bad.stderr.count("\n") == 1, bad.stderr
        assert words in bad.stderr and "Traceback" not in bad.stderr
