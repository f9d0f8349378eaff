"""The machine's matmul peak (:func:`denoiser.machine.matmul_peak`): the faster of torch.mm and
OpenVINO's MatMul, so that a graph OpenVINO runs cannot read above 100% of it where torch's MKL
takes a narrower path than the CPU has (AVX2 code on AMD CPUs with AVX-512)."""
import pytest
import torch

from denoiser import machine


def test_openvino_matmul_computes_and_is_timed():
    """The OpenVINO product runs (a small one here) and gives a finite positive rate."""
    pytest.importorskip("openvino")
    peak = machine.openvino_matmul_peak(size=128, repeats=2, warmup=1)
    assert peak is not None and 0.0 < peak < float("inf")


@pytest.mark.parametrize("torch_rate, ov_rate, want", [(100.0, 250.0, 250.0), (300.0, 250.0, 300.0),
                                                        (100.0, None, 100.0)])
def test_the_peak_is_the_faster_engine(monkeypatch, torch_rate, ov_rate, want):
    """f32: the larger of the two engines' rates (OpenVINO missing: torch's alone)."""
    monkeypatch.setattr(machine, "torch_matmul_peak", lambda *a, **k: torch_rate)
    monkeypatch.setattr(machine, "openvino_matmul_peak", lambda *a, **k: ov_rate)
    assert machine.matmul_peak() == want


def test_other_dtypes_take_torch_alone(monkeypatch):
    """bf16 (and any other dtype) is torch's product only: the OpenVINO one is f32."""
    monkeypatch.setattr(machine, "torch_matmul_peak", lambda *a, **k: 50.0)
    monkeypatch.setattr(machine, "openvino_matmul_peak", lambda *a, **k: pytest.fail("f32 only"))
    assert machine.matmul_peak(dtype=torch.bfloat16) == 50.0
