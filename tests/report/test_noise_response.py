"""The noise response (denoiser/report/noise_response.py, denoiser/commands/tools/noise_response.py): the scaled
input is the augmentation's rule, and the table's figures are the network's, checked with a
network that returns its input (output = input for every factor) and one that returns the
reference (output independent of the factor), against a plain PSNR loop."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from denoiser.buffers import FRAME_INPUTS
from denoiser.checkpoint import save_checkpoint
from denoiser.configs import build_net, compose_net_config, load_layout
from denoiser.data.evalset import read_frame
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import UserError
from denoiser.metrics import tonemap
from denoiser.report.history_diagnosis import open_sequence
from denoiser.report.noise_response import grey, grey_frame, response, run, scaled_inputs

ROOT = Path(__file__).resolve().parents[2]
SIZE = 32


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    seq = tmp_path_factory.mktemp("noise") / "seq"
    write_synthetic_sequence(seq, frames=4, width=SIZE, height=SIZE, seed=2)
    return seq


class Passthrough:
    """A step function returning the input colour (``reference`` set: the reference instead)."""

    def __init__(self, references=None):
        self.references, self.calls = references, 0

    def step(self, frame, state=None, reset=None):
        out = frame["color"] if self.references is None else self.references[self.calls % len(self.references)]
        self.calls += 1
        return out, {}, {}


def plain_psnr(x: torch.Tensor, ref: torch.Tensor) -> float:
    a, b = tonemap(x).double().numpy(), tonemap(ref).double().numpy()
    total = 0.0
    for v in np.nditer(a - b):
        total += float(v) ** 2
    return 10 * np.log10(1 / (total / a.size))


def test_scaled_inputs_scale_the_residual_of_color_and_samples(sequence):
    source, dataset = open_sequence(sequence, load_layout("native"))
    inputs, ref, _ = read_frame(dataset, source, 1)
    inputs["samples"] = torch.rand(1, 2, 3, SIZE, SIZE, generator=torch.Generator().manual_seed(0))
    half = scaled_inputs(inputs, ref, 0.5)
    torch.testing.assert_close(half["color"], ref + 0.5 * (inputs["color"] - ref), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(half["samples"], ref[:, None] + 0.5 * (inputs["samples"] - ref[:, None]),
                               rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(scaled_inputs(inputs, ref, 1.0)["color"], inputs["color"], rtol=1e-6, atol=1e-6)
    assert float(scaled_inputs(inputs, ref, 40.0)["color"].min()) >= 0.0       # clamped where f > 1 overshoots
    for key in FRAME_INPUTS[1:]:  # the guides pass unchanged
        assert scaled_inputs(inputs, ref, 0.5)[key] is inputs[key]
    assert "reference" not in half


def test_response_reports_the_networks_figures(sequence):
    source, dataset = open_sequence(sequence, load_layout("native"))
    frames = [read_frame(dataset, source, i) for i in range(source.frames)]
    refs = [ref for _, ref, _ in frames]
    identity = response(Passthrough(), dataset, source, [0.5, 1.0])
    perfect = response(Passthrough(refs), dataset, source, [0.5, 1.0])
    for f, row in zip((0.5, 1.0), identity):
        inputs = [scaled_inputs(x, ref, f)["color"] for x, ref, _ in frames]
        expected = [plain_psnr(x, ref) for x, ref in zip(inputs, refs)]
        assert row["factor"] == f
        assert row["input_f0"] == pytest.approx(expected[0], abs=1e-3) == row["output_f0"]
        assert row["input_f2"] == pytest.approx(np.mean(expected[2:]), abs=1e-3) == row["output_f2"]
    assert identity[0]["input_f0"] > identity[1]["input_f0"] + 5     # half the residual: ~6 dB cleaner
    assert perfect[0]["output_f2"] == perfect[1]["output_f2"] > 90   # the reference itself, at every f
    with pytest.raises(UserError, match="factors > 0"):
        response(Passthrough(), dataset, source, [0.0])


def test_grey_is_the_luminance_in_every_channel(sequence):
    x = torch.rand(2, 3, 4, 5, generator=torch.Generator().manual_seed(1))
    g = grey(x)
    for b in range(2):
        for y in range(4):
            for i in range(5):
                lum = 0.2126729 * x[b, 0, y, i] + 0.7151522 * x[b, 1, y, i] + 0.0721750 * x[b, 2, y, i]
                assert torch.allclose(g[b, :, y, i], lum.expand(3), atol=1e-6)
    source, dataset = open_sequence(sequence, load_layout("native"))
    inputs, ref, _ = read_frame(dataset, source, 0)
    gi, gref = grey_frame(inputs, ref)
    assert torch.equal(gref, grey(ref)) and torch.equal(gi["albedo"], grey(inputs["albedo"]))
    assert all(gi[k] is inputs[k] for k in FRAME_INPUTS[2:])           # geometry unchanged
    coloured, greyed = (response(Passthrough(), dataset, source, [1.0], grey_inputs=g)[0] for g in (False, True))
    assert (coloured["inputs"], greyed["inputs"]) == ("colour", "grey")
    frames = [read_frame(dataset, source, i) for i in range(source.frames)]
    assert greyed["input_f0"] == pytest.approx(plain_psnr(grey(frames[0][0]["color"]), grey(frames[0][1])), abs=1e-3)


def test_the_script_writes_the_table_and_refuses_bad_input_in_one_line(sequence, tmp_path):
    torch.manual_seed(0)
    cfg = compose_net_config("tiny")
    ckpt = save_checkpoint(tmp_path / "tiny.ckpt", build_net(cfg).eval(), cfg)
    out = tmp_path / "response.md"
    results, text = run(ckpt, [sequence], "native", [0.5, 1.0], out, grey_too=True, plot=tmp_path / "r.png")
    assert out.read_text() == text and len(results["seq"]) == 4
    with Image.open(tmp_path / "r.png") as im:
        assert im.format == "PNG" and im.width >= 400
    for row in ("| seq | colour | 0.5 |", "| seq | colour | 1 |", "| seq | grey | 0.5 |", "| seq | grey | 1 |"):
        assert row in text
    script = [sys.executable, "-m", "denoiser.commands.tools.noise_response", f"ckpt={ckpt}"]
    proc = subprocess.run([*script, f"sequences=[{tmp_path / 'nope'}]"], capture_output=True, text=True, cwd=ROOT, check=False)
    assert proc.returncode == 2 and proc.stderr.startswith("error: ") and proc.stderr.count("\n") == 1
    proc = subprocess.run([*script, f"sequences=[{sequence}]", "factors=[a]"], capture_output=True, text=True,
                          cwd=ROOT, check=False)
    assert proc.returncode == 2 and "factors: not numbers" in proc.stderr and proc.stderr.count("\n") == 1
    proc = subprocess.run([*script, f"sequences=[{sequence}]", "grey=maybe"], capture_output=True, text=True, cwd=ROOT, check=False)
    assert proc.returncode == 2 and "grey: true or false" in proc.stderr and proc.stderr.count("\n") == 1
