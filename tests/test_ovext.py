"""The OpenVINO extension (denoiser.ovext): ``denoiser::KernelApply`` against the kernel filter.

The operation is compared with a plain loop over pixels (the definition in
``denoiser/nn/kernels.py``) and with eager :func:`~denoiser.nn.kernels.apply_kernels`, at odd
sizes, kernels larger than the image, extreme logits and fireflies; then as part of a whole
exported network (tests/test_openvino.py runs the fused graph's parity over a sequence).
"""

import math
import stat

import numpy as np
import pytest
import torch

pytest.importorskip("openvino", reason="openvino is not installed (pip install .[openvino])")
pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")

from denoiser import ovext
from denoiser.errors import UserError
from denoiser.nn.kernels import apply_kernels, kernels_as_op

if ovext.kernel_extension() is None:
    pytest.skip(f"the OpenVINO extension is unavailable: {ovext.unavailable_reason()}", allow_module_level=True)


class Filter(torch.nn.Module):
    def __init__(self, scale):
        super().__init__()
        self.scale = scale

    def forward(self, x, logits):
        return apply_kernels(x, logits, self.scale)


def export_filter(path, scale, x, logits):
    """A graph of one ``denoiser::KernelApply`` (x ``[B, C, H, W]``, logits ``[B, k*k, H, W]``)."""
    dynamic = {"x": {2: "h", 3: "w"}, "logits": {2: "h", 3: "w"}}
    with kernels_as_op(True), torch.no_grad():
        torch.onnx.export(Filter(scale), (x, logits), str(path), input_names=["x", "logits"], output_names=["y"],
                          dynamic_axes=dynamic, opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    return path


def run_openvino(path, x, logits, threads=1, precision="f32"):
    import openvino as ov

    core = ov.Core()
    ovext.load_into(core, path)
    hint = {"f32": "f32", "bf16": "bf16"}[precision]
    compiled = core.compile_model(core.read_model(str(path)), "CPU",
                                  {"INFERENCE_NUM_THREADS": threads, "INFERENCE_PRECISION_HINT": hint})
    return compiled({"x": x.numpy(), "logits": logits.numpy()})[compiled.output(0)]


def loop_reference(x, logits, scale):
    """The definition, one pixel at a time (float64)."""
    x, logits = x.double().numpy(), logits.double().numpy()
    n, _, h, w = x.shape
    k = math.isqrt(logits.shape[1])
    r = k // 2
    out = np.zeros_like(x)
    for b in range(n):
        for y in range(h):
            for px in range(w):
                z = logits[b, :, y, px]
                if scale is not None:
                    z = z * scale / np.sqrt(z.var() + 1.0)
                taps = [(t, y + t // k - r, px + t % k - r) for t in range(k * k)]
                taps = [(t, yy, xx) for t, yy, xx in taps if 0 <= yy < h and 0 <= xx < w]
                zs = np.array([z[t] for t, _, _ in taps])
                e = np.exp(zs - zs.max())
                wts = e / e.sum()
                for wt, (_, yy, xx) in zip(wts, taps):
                    out[b, :, y, px] += wt * x[b, :, yy, xx]
    return out


@pytest.mark.parametrize("k", [1, 3, 5, 7])
@pytest.mark.parametrize("scale", [None, 2.5])
def test_kernel_apply_matches_the_loop_over_pixels(tmp_path, k, scale):
    """Odd sizes (5 x 9: a 7 x 7 kernel is taller than the image), two images, four channels."""
    g = torch.Generator().manual_seed(k)
    x = torch.rand(2, 4, 5, 9, generator=g) * 10
    logits = torch.randn(2, k * k, 5, 9, generator=g) * 3
    path = export_filter(tmp_path / "f.onnx", scale, x, logits)
    got = run_openvino(path, x, logits)
    want = loop_reference(x, logits, scale)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)
    np.testing.assert_allclose(got, apply_kernels(x, logits, scale).numpy(), rtol=2e-5, atol=2e-5)


def test_kernel_apply_hard_values_and_threads(tmp_path):
    """Fireflies, black pixels, logits at +-1e4 (saturated softmaxes: one-hot kernels), and a
    row split across threads: equal to eager within float32 rounding, finite, and the same bits
    with 1 and 2 threads (each row is computed by one thread in a fixed order)."""
    g = torch.Generator().manual_seed(3)
    h, w = 37, 61
    x = torch.rand(1, 4, h, w, generator=g)
    x[:, :3, ::7, ::5] = 5e4  # fireflies
    x[:, :3, 10:20] = 0.0  # black
    logits = torch.randn(1, 25, h, w, generator=g) * 4
    logits[:, :, ::3] = 1e4 * torch.sign(torch.randn(1, 25, 1, w, generator=g))
    for scale in (None, 5.0):
        path = export_filter(tmp_path / f"h{scale}.onnx", scale, x, logits)
        one = run_openvino(path, x, logits, threads=1)
        two = run_openvino(path, x, logits, threads=2)
        want = apply_kernels(x, logits, scale).numpy()
        assert np.isfinite(one).all()
        np.testing.assert_array_equal(one, two)
        np.testing.assert_allclose(one, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


def test_kernel_apply_in_bf16_inference(tmp_path):
    """Under ``INFERENCE_PRECISION_HINT=bf16`` the operation still runs in float32 (its inputs
    arrive converted): the same numbers as f32."""
    import openvino as ov

    if "BF16" not in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"):
        pytest.skip("the CPU has no bf16")
    g = torch.Generator().manual_seed(4)
    x, logits = torch.rand(1, 4, 12, 20, generator=g), torch.randn(1, 25, 12, 20, generator=g)
    path = export_filter(tmp_path / "b.onnx", 2.5, x, logits)
    np.testing.assert_allclose(run_openvino(path, x, logits, precision="bf16"), run_openvino(path, x, logits),
                               rtol=1e-6, atol=1e-6)


def test_missing_extension_is_one_clear_line(tmp_path, monkeypatch):
    from denoiser.step_graph import OpenVinoStep

    x, logits = torch.rand(1, 4, 8, 8), torch.randn(1, 9, 8, 8)
    path = export_filter(tmp_path / "m.onnx", None, x, logits)
    monkeypatch.setattr(ovext, "_status", lambda: (None, "no C++ compiler ($CXX, g++ or c++) to build it"))
    with pytest.raises(UserError, match=r"m\.onnx: uses denoiser::KernelApply.*no C\+\+ compiler"):
        OpenVinoStep(path)


def test_failed_build_leaves_nothing_and_says_why(tmp_path, monkeypatch):
    """A compiler error becomes the reason (one line) and no library is left in the cache."""
    fake = tmp_path / "fake-cxx"
    fake.write_text("#!/bin/sh\necho 'kernel_apply.cpp:1:1: error: simulated failure' >&2\nexit 1\n")
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("CXX", str(fake))
    monkeypatch.setenv("DENOISER_CACHE", str(tmp_path / "cache"))
    ovext._status.cache_clear()
    try:
        assert ovext.kernel_extension() is None
        assert "simulated failure" in ovext.unavailable_reason()
        left = [p for p in (tmp_path / "cache").rglob("*") if p.is_file()]
        assert left == [], left
    finally:
        ovext._status.cache_clear()  # the next use builds again under the restored environment
