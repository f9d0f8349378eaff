"""The graphs' matmul peak (:func:`denoiser.inference.peak.engines_matmul_peak`): the faster of
torch.mm and OpenVINO's MatMul, so that a graph OpenVINO runs cannot read above 100% of it where
torch's MKL takes a narrower path than the CPU has (AVX2 code on AMD CPUs with AVX-512)."""
import pytest

from denoiser.inference import peak


def test_openvino_matmul_computes_and_is_timed():
    """The OpenVINO product runs (a small one here) and gives a finite positive rate."""
    pytest.importorskip("openvino")
    rate = peak.openvino_matmul_peak(size=128, repeats=2, warmup=1)
    assert rate is not None and 0.0 < rate < float("inf")


@pytest.mark.parametrize("torch_rate, ov_rate, want", [(100.0, 250.0, 250.0), (300.0, 250.0, 300.0),
                                                        (100.0, None, 100.0)])
def test_the_peak_is_the_faster_engine(monkeypatch, torch_rate, ov_rate, want):
    """The larger of the two engines' rates (OpenVINO missing: torch's alone)."""
    monkeypatch.setattr(peak, "matmul_peak", lambda *a, **k: torch_rate)
    monkeypatch.setattr(peak, "openvino_matmul_peak", lambda *a, **k: ov_rate)
    assert peak.engines_matmul_peak() == want
