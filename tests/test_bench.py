"""Tests of denoiser-bench: timing rows, FLOPs, memory, quality join, ratio table and plot."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import compose_command, tiny_checkpoint

sys.path.insert(0, str(Path(__file__).parent))
from test_eval_data import write_dataset

from denoiser.backends import Stepper
from denoiser.configs import build_net, compose_net_config
from denoiser.frames import resize_frame
from denoiser.measure import PeakRss, read_csv, time_steps
from denoiser.plot_tradeoff import pareto_front, pareto_front_of_rows


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    write_dataset(root / "data", sequences=1, frames=3, size=24)
    ckpt = tiny_checkpoint(root / "student.ckpt")
    return root, ckpt


compose = compose_command


def test_bench_end_to_end(setup, tmp_path):
    from denoiser.commands.bench import run as bench
    from denoiser.commands.evaluate import run as evaluate

    root, ckpt = setup
    data = ["data=tiny", f"data.root={root / 'data'}", "threads=1"]
    evaluate(compose("eval", [*data, f"ckpt=[{ckpt}]", "~baselines.oidn_balanced", "~baselines.oidn_high",
                              "metrics=[psnr]", "images.frame=null", f"out_dir={tmp_path / 'eval'}"]))
    out = tmp_path / "bench"
    wide = '{wide: {net: tiny, overrides: ["net.unet.encoder=[12,16,20]","net.unet.bottleneck=20"]}}'
    rows = bench(compose("bench", [*data, f"ckpt=[{ckpt}]", f"variants={wide}", "curves={width: [student, wide]}",
                                   f"eval_csv={tmp_path / 'eval' / 'metrics.csv'}", "sizes=[[16,16],[24,40]]",
                                   "repeats=2", "warmup=1", "use_backends=[eager,channels_last,onnxruntime,cuda_fp16]",
                                   "~baselines.oidn_balanced", "~baselines.oidn_high", "skip={wide: [[24,40]]}",
                                   "method_backends={wide: [eager]}",
                                   f"out_dir={out}"]))
    table = read_csv(out / "bench.csv")
    assert len(table) == len(rows)
    timed = {(r["method"], r["backend"], r["height"]): r for r in table if r["status"] == "ok"}
    assert timed[("student", "eager fp32", 16)]["dtype"] == "fp32"
    assert "avx512_bf16" in (out / "report.md").read_text()
    for size in (16, 24):
        for key in (("student", "eager fp32", size), ("student", "onnxruntime", size), ("OIDN-fast", "OIDN (pyoidn)", size)):
            assert timed[key]["ms_median"] > 0 and timed[key]["repeats"] == 2, key
    assert ("wide", "eager fp32", 16) in timed and not any(r["method"] == "wide" and r["height"] == 24 for r in table)
    assert [r["backend"] for r in table if r["method"] == "wide"] == ["eager fp32"]
    s16, s24 = timed[("student", "eager fp32", 16)], timed[("student", "eager fp32", 24)]
    # conv FLOPs scale with the padded pixel count: 16x16 -> 24x40 (pads to 24x40) is 3.75x
    assert 3.0 < s24["gflop"] / s16["gflop"] < 4.5
    assert s16["params"] == build_net(compose_net_config("tiny", "student")).num_parameters()
    assert timed[("wide", "eager fp32", 16)]["params"] > s16["params"]
    if not torch.cuda.is_available():
        assert any(r["device"] == "cuda" and r["status"] == "skipped: no CUDA device" for r in table)
    eval_rows = {r["method"]: r for r in read_csv(tmp_path / "eval" / "metrics.csv") if r["sequence"] == "mean"}
    # the eager row's PSNR is measured through the eager backend and agrees with denoiser-eval's
    for size in (16, 24):
        row = timed[("student", "eager fp32", size)]
        assert row["psnr_from"] == "backend"
        assert abs(row["psnr"] - eval_rows["student"]["psnr"]) < 1e-4
        assert math.isclose(row["psnr_eval"], eval_rows["student"]["psnr"], rel_tol=1e-9)
        ort = timed[("student", "onnxruntime", size)]
        assert ort["psnr_from"] == "backend" and abs(ort["psnr"] - row["psnr"]) < 1e-3
    oidn = timed[("OIDN-fast", "OIDN (pyoidn)", 16)]
    assert oidn["psnr_from"] == "eval" and math.isclose(oidn["psnr"], eval_rows["OIDN-fast"]["psnr"], rel_tol=1e-9)
    assert math.isnan(timed[("wide", "eager fp32", 16)]["psnr"])  # untrained variant: no quality
    report = (out / "report.md").read_text()
    assert "## Student vs OIDN-fast" in report and "| 40x24 | fastest backend |" in report
    assert "matmul peak" in report and "accuracy_vs_time.png" in report
    assert (out / "accuracy_vs_time.png").read_bytes()[:4] == b"\x89PNG"
    front = pareto_front_of_rows(table, (24, 40))
    assert front and set(front) <= {"student", "OIDN-fast"}


def test_pareto_front():
    pts = {"a": (1.0, 20.0), "b": (2.0, 25.0), "c": (3.0, 24.0), "d": (0.5, 10.0), "e": (2.0, 25.0)}
    assert pareto_front(pts) == ["d", "a", "b", "e"]
    assert pareto_front({"x": (1.0, 1.0)}) == ["x"]


def test_resize_frame_scales_motion_and_keeps_unit_normals():
    g = torch.Generator().manual_seed(0)
    frame = {"color": torch.rand(1, 3, 8, 10, generator=g), "motion": torch.ones(1, 2, 8, 10),
             "normal": torch.nn.functional.normalize(torch.randn(1, 3, 8, 10, generator=g), dim=1)}
    out = resize_frame(frame, 16, 30)
    assert out["color"].shape == (1, 3, 16, 30)
    assert torch.allclose(out["motion"][:, 0], torch.full((1, 16, 30), 3.0))
    assert torch.allclose(out["motion"][:, 1], torch.full((1, 16, 30), 2.0))
    assert torch.allclose(out["normal"].norm(dim=1), torch.ones(1, 16, 30), atol=1e-5)


def test_time_steps_carries_state_and_resets_once():
    calls = []

    def step(frame, state):
        reset = state is None
        calls.append((reset, state))
        return frame, (0 if reset else state + 1)

    times = time_steps(Stepper(step), [{"i": 0}, {"i": 1}], warmup=2, repeats=3)
    assert len(times) == 3 and all(t >= 0 for t in times)
    assert [c[0] for c in calls] == [True, False, False, False, False]
    assert [c[1] for c in calls[1:]] == [0, 1, 2, 3]


@pytest.mark.parametrize("method", ["sample", "hwm"])
def test_peak_rss_sees_an_allocation(method):
    with PeakRss(method=method) as mem:
        block = np.ones(64 * 2**20 // 8)  # 64 MiB, touched
        block += 1
    del block
    assert mem.megabytes > 40


@pytest.mark.slow
def test_bench_networks_measures_in_a_subprocess(capsys):
    """python -m denoiser.commands.bench_networks, tiny: the parent passes each job to a fresh process."""
    from denoiser.commands.bench_networks import run

    rows = run(compose("bench_networks", ["nets=[tiny]", "sizes=[24x16]", "variants=[eager]", "repeats=2",
                                          "kernels=false"]))
    assert [(r["net"], r["variant"], r["size"], r["runs"]) for r in rows] == [("tiny", "eager", "24x16", 2)]
    assert rows[0]["ms"] > 0 and rows[0]["peak_mb"] >= 0 and 0 < rows[0]["gflop"] < 1
    assert "| tiny |" in capsys.readouterr().out


def test_default_student_for_the_ratio():
    from denoiser.commands.bench import default_student

    assert default_student(["teacher", "student_distilled", "student_no_kd"]) == "student_distilled"
    assert default_student(["teacher", "tiny"]) == "teacher"
    assert default_student([]) is None


def test_cpu_isa_flags():
    from denoiser.commands.bench import cpu_isa

    info = "processor : 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16 amx_tile\nbugs : x\n"
    flags = cpu_isa(info)
    assert flags["avx512_bf16"] and flags["amx_tile"] and flags["avx2"] and not flags["amx_bf16"]
    assert not any(cpu_isa("").values())


@pytest.mark.slow
def test_bench_openvino_rows(setup, tmp_path):
    """The OpenVINO backends of conf/bench.yaml time the network (or say why they are skipped)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    from denoiser.commands.bench import run as bench

    root, ckpt = setup
    rows = bench(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                   "sizes=[[16,24]]", "repeats=2", "warmup=1", "use_backends=[openvino_f32,openvino_bf16]",
                                   "baselines={}", f"out_dir={tmp_path}"]))
    by = {r["backend"]: r for r in rows}
    assert by["openvino f32"]["status"] == "ok" and by["openvino f32"]["ms_median"] > 0
    assert by["openvino f32"]["dtype"] == "fp32" and by["openvino bf16"]["dtype"] == "bf16"
    assert by["openvino bf16"]["status"] == "ok" or by["openvino bf16"]["status"].startswith("skipped: ")


def test_bench_profile_says_where_the_time_goes(setup, tmp_path):
    """profile=true: the OpenVINO row carries its op types' times; profile.csv and the report
    section hold them (shares of one step sum to 1, the network's convolutions are among them);
    a backend that cannot profile (eager) adds no rows."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    from denoiser.commands.bench import run as bench

    root, ckpt = setup
    rows = bench(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                   "sizes=[[16,24]]", "repeats=1", "warmup=1", "use_backends=[eager,openvino_f32]",
                                   "profile=true", "quality=false", "baselines={}", f"out_dir={tmp_path}"]))
    by = {r["backend"]: r for r in rows}
    assert "profile" not in by["eager fp32"]
    ops = by["openvino f32"]["profile"]
    assert "Convolution" in ops and all(ms >= 0 for ms in ops.values()) and list(ops.values()) == sorted(ops.values(), reverse=True)
    table = read_csv(tmp_path / "profile.csv")
    assert {r["backend"] for r in table} == {"openvino f32"} and {r["op_type"] for r in table} == set(ops)
    assert abs(sum(float(r["share"]) for r in table) - 1.0) < 1e-6
    assert "## Where the time goes" in (tmp_path / "report.md").read_text()


def test_bench_quality_false_borrows_eval_psnr(setup, tmp_path):
    """quality=false: no backend run for quality; the networks' psnr is denoiser-eval's, marked so."""
    from denoiser.commands.bench import run as bench

    root, ckpt = setup
    csv = tmp_path / "metrics.csv"
    csv.write_text("method,scene,sequence,frames,psnr,ms_per_frame\nstudent,mean,mean,1,12.5,1.0\n")
    rows = bench(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                   "sizes=[[16,16]]", "repeats=1", "warmup=0", "use_backends=[eager]", "baselines={}",
                                   "quality=false", f"eval_csv={csv}", f"out_dir={tmp_path / 'bench'}"]))
    assert [(r["psnr"], r["psnr_eval"], r["psnr_from"]) for r in rows if r["method"] == "student"] == [(12.5, 12.5, "eval")]


def test_ratio_uses_the_fastest_row_with_its_own_psnr():
    from denoiser.commands.bench import ratio_rows

    def row(method, backend, ms, psnr):
        return {"method": method, "backend": backend, "device": "cpu", "height": 8, "width": 8, "ms_median": ms,
                "psnr": psnr}

    rows = [row("OIDN-fast", "OIDN (pyoidn)", 10.0, 30.0), row("s", "eager fp32", 8.0, 31.0),
            row("s", "openvino bf16", 2.0, 30.5), row("s", "onnxruntime", 1.0, float("nan"))]
    fastest = next(r for r in ratio_rows(rows, "s", "OIDN-fast", [[8, 8]]) if r["compare"] == "fastest backend")
    assert fastest["student"] == "s (openvino bf16)" and fastest["ratio"] == 5.0
    assert fastest["student_psnr"] == 30.5 and math.isclose(fastest["psnr_gain"], 0.5)


@pytest.mark.slow
def test_bench_openvino_bf16_psnr_through_the_backend(tmp_path):
    """The bf16 row's PSNR is measured through OpenVINO bf16: finite and within 0.1 dB of eager fp32
    (bf16 keeps 8 mantissa bits; tests/test_openvino.py bounds the output error at 3e-2)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")
    from denoiser.backends import OpenVinoBackend
    from denoiser.commands.bench import run as bench

    reason = OpenVinoBackend(precision="bf16").available()
    if reason:
        pytest.skip(reason)
    write_dataset(tmp_path / "data", sequences=1, frames=4, size=32)
    ckpt = tiny_checkpoint(tmp_path / "student.ckpt")
    rows = bench(compose("bench", ["data=tiny", f"data.root={tmp_path / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                   "sizes=[[32,32]]", "repeats=1", "warmup=0", "use_backends=[eager,openvino_bf16]",
                                   "baselines={}", f"out_dir={tmp_path / 'bench'}"]))
    by = {r["backend"]: r for r in rows}
    assert by["openvino bf16"]["status"] == "ok" and by["openvino bf16"]["psnr_from"] == "backend"
    eager, bf16 = by["eager fp32"]["psnr"], by["openvino bf16"]["psnr"]
    assert math.isfinite(eager) and math.isfinite(bf16)
    assert abs(bf16 - eager) < 0.1, (bf16, eager)  # measured here: 17.050 vs 17.051 dB
    assert "through each row's own backend" in (tmp_path / "bench" / "report.md").read_text()


def test_bench_quality_limits_match_eval(tmp_path):
    """quality_frames and max_sequences score what denoiser-eval scores with max_frames on that sequence."""
    from denoiser.commands.bench import run as bench
    from denoiser.commands.evaluate import run as evaluate

    write_dataset(tmp_path / "data", sequences=2, frames=4, size=32)
    ckpt = tiny_checkpoint(tmp_path / "student.ckpt", seed=1)
    data = ["data=tiny", f"data.root={tmp_path / 'data'}", "threads=1"]
    evaluate(compose("eval", [*data, f"ckpt=[{ckpt}]", "~baselines.oidn_fast", "~baselines.noisy",
                              "~baselines.oidn_balanced", "~baselines.oidn_high", "metrics=[psnr]", "max_frames=3",
                              "images.frame=null", f"out_dir={tmp_path / 'eval'}"]))
    first = next(r for r in read_csv(tmp_path / "eval" / "metrics.csv") if r["sequence"] != "mean")
    rows = bench(compose("bench", [*data, f"ckpt=[{ckpt}]", "sizes=[[32,32]]", "repeats=1", "warmup=0",
                                   "use_backends=[eager]", "~baselines.oidn_fast", "~baselines.oidn_balanced",
                                   "~baselines.oidn_high", "quality_frames=3", "max_sequences=1",
                                   f"out_dir={tmp_path / 'bench'}"]))
    (row,) = rows
    assert abs(row["psnr"] - first["psnr"]) < 1e-4


def test_share_of_the_peak_uses_the_larger_of_the_peaks_before_and_after(setup, tmp_path, monkeypatch):
    """The matmul peak is taken before and after the methods; the larger one is the peak of the
    report and of every row's share (a share must not look better because the machine was slow
    when one of them was taken)."""
    import denoiser.commands.bench as bench_module

    peaks = iter([100.0, 250.0])
    monkeypatch.setattr(bench_module, "matmul_peak", lambda *a, **k: next(peaks))
    root, ckpt = setup
    out = tmp_path / "bench"
    rows = bench_module.run(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                              "sizes=[[16,16]]", "repeats=1", "warmup=1", "use_backends=[eager]",
                                              "quality=false", "baselines={}", f"out_dir={out}"]))
    row = next(r for r in rows if r["method"] == "student")
    assert row["peak_fraction"] == pytest.approx(row["gflops_per_s"] / 250.0)
    assert "fp32 matmul peak 250.0 GFLOP/s" in (out / "report.md").read_text()
