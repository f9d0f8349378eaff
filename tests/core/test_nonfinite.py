"""One rule for non-finite inputs, in the EXR reader, the network and its ONNX export: NaN -> 0, -Inf -> 0,
+Inf -> 65504 (docs/design.md §3.2).

A frame with whole rows of -Inf, +Inf and NaN must denoise exactly like the same frame with those
values replaced by hand: finite, and non-negative (no -Inf becomes negative energy that the
kernels spread over their footprint).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from denoiser.buffers import FRAME_INPUTS, native_channels
from denoiser.configs import build_net, compose_net_config
from denoiser.frames import random_frame

H, W = 16, 20
#: (non-finite value, the row of the frame that gets it, the value the rule replaces it by)
ROWS = [(float("-inf"), 2, 0.0), (float("inf"), 7, 65504.0), (float("nan"), 11, 0.0)]
GUIDES = [b for b in FRAME_INPUTS if b != "color"]


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    return build_net(compose_net_config("tiny", "student")).eval()


def frames(buffers: list[str], seed: int, samples: int = 2) -> tuple[dict, dict]:
    """``(bad frame, the same frame with the rule applied by hand)`` with the rows of ``ROWS`` in ``buffers``."""
    base = random_frame(1, H, W, seed=seed, samples=samples)
    bad = {k: v.clone() for k, v in base.items()}
    fixed = {k: v.clone() for k, v in base.items()}
    for k in buffers:
        for value, row, replacement in ROWS:
            bad[k][..., row, :] = value
            fixed[k][..., row, :] = replacement
    return bad, fixed


@pytest.mark.parametrize("buffers", [["color"], ["samples"], GUIDES, ["color", "samples", *GUIDES]],
                         ids=["color", "samples", "guides", "all"])
def test_step_applies_the_rule(net, buffers):
    state_bad = state_fixed = None
    with torch.no_grad():
        for t in range(2):  # the second step also runs the history through warp and blend
            bad, fixed = frames(buffers, seed=t)
            out_bad, state_bad, _ = net.step(bad, state_bad)
            out_fixed, state_fixed, _ = net.step(fixed, state_fixed)
            assert torch.isfinite(out_bad).all()
            assert torch.equal(out_bad, out_fixed), (out_bad - out_fixed).abs().max()
            assert out_bad.min() >= 0, f"negative output {out_bad.min():.4g} from non-negative radiance"
            for k in state_bad:
                assert torch.equal(state_bad[k], state_fixed[k]), k


def test_reader_and_network_share_the_rule():
    """The numpy version (EXR reader) and the torch version (network) replace every value alike."""
    from denoiser.data import exr
    from denoiser.nn.inputs import sanitize
    from denoiser.nonfinite import POSINF, replace_array, replace_tensor

    for dtype in (np.float32, np.float16):
        big = float(np.finfo(dtype).max)  # finite HDR, however large, is kept
        arr = np.array([np.nan, -np.inf, np.inf, -big, big, -2.5, 0.0, 3.0], dtype)
        want = np.array([0, 0, POSINF, -big, big, -2.5, 0, 3], dtype)
        got = arr.copy()
        assert replace_array(got) == 3 and got.dtype == dtype
        np.testing.assert_array_equal(got, want)
        reader = arr.copy()
        assert exr.sanitize(reader) == 3
        np.testing.assert_array_equal(reader, want)
        for fn in (replace_tensor, sanitize):
            out = fn(torch.from_numpy(arr.copy()))
            assert out.dtype == torch.float32
            np.testing.assert_array_equal(out.numpy(), want.astype(np.float32))
    assert exr.POS_INF_REPLACEMENT == POSINF


def test_frame_read_from_exr_equals_raw_frame(net, tmp_path):
    """Reading the bad frame from an EXR (the reader replaces) or giving it raw to the network: same output."""
    from denoiser.data import exr

    bad, _ = frames(["color", *GUIDES], seed=5, samples=0)
    path = tmp_path / "bad.exr"
    exr.write_frame(path, {k: v[0].permute(1, 2, 0).numpy() for k, v in bad.items()})
    spec = {k: native_channels(k, v.shape[1]) for k, v in bad.items()}
    arrays, replaced = exr.read_frame(path, spec)
    assert replaced == 3 * W * sum(v.shape[1] for v in bad.values())
    read = {k: torch.from_numpy(v).permute(2, 0, 1)[None] for k, v in arrays.items()}
    with torch.no_grad():
        assert torch.equal(net.step(read)[0], net.step(bad)[0])


@pytest.mark.parametrize("engine", ["onnxruntime", "openvino", "openvino_fused_f32"])
def test_onnx_export_applies_the_rule(net, tmp_path, engine):
    """The exported step applies the rule in every engine: ONNX Runtime, OpenVINO on the plain
    graph and on the f32 graph with the extension's operations (OpenVINO once read NaN as +Inf in
    the traced selects: NaN -> 65504, a firefly where PyTorch has 0)."""
    from denoiser.inference.step_graph import OnnxStep, OpenVinoStep, export_onnx

    if engine == "onnxruntime":
        pytest.importorskip("onnxruntime")
        runner = OnnxStep(export_onnx(net, tmp_path / "tiny.onnx"), threads=1)
    else:
        pytest.importorskip("openvino")
        fused = engine == "openvino_fused_f32"
        if fused:
            from helpers.ovext import extension_or_skip

            extension_or_skip()
        runner = OpenVinoStep(export_onnx(net, tmp_path / "tiny.onnx", matmul_heads=fused, fused_kernels=fused),
                              1, precision="f32")
    state_torch = state_bad = state_fixed = None
    with torch.no_grad():
        for t in range(2):
            bad, fixed = frames(["color", *GUIDES], seed=t, samples=0)
            expected, state_torch, _ = net.step(bad, state_torch, torch.tensor([t == 0]))
            got, state_bad = runner.step(bad, state_bad, reset=t == 0)
            got_fixed, state_fixed = runner.step(fixed, state_fixed, reset=t == 0)
            assert np.isfinite(got).all() and got.min() >= 0
            np.testing.assert_array_equal(got, got_fixed)
            scale = max(1.0, float(expected.abs().max()))
            assert np.abs(got - expected.numpy()).max() <= 1e-4 * scale


@pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning")
@pytest.mark.parametrize("values", [(0.0, 65504.0, 0.0), (0.0, 1e4, -1e4), (1.0, 2.0, 3.0)])
def test_traced_selects_equal_nan_to_num(values):
    """The traced form of nan_to_num (comparisons and selects) gives torch's values bit for bit,
    finite values beyond the replacements included."""
    from denoiser.nonfinite import nan_to_num

    nan, posinf, neginf = values
    x = torch.tensor([float("nan"), float("inf"), -float("inf"), 0.0, -0.0, 1.5, -2.0, 3e38, -3e38, 1e-40])
    with torch.no_grad():
        traced = torch.jit.trace(lambda t: nan_to_num(t, nan, posinf, neginf), (x,))
    assert "aten::nan_to_num" not in [n.kind() for n in traced.graph.nodes()]
    expected = x.nan_to_num(nan=nan, posinf=posinf, neginf=neginf)
    assert torch.equal(traced(x), expected)
    assert torch.equal(nan_to_num(x, nan, posinf, neginf), expected)
