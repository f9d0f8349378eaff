"""Tests of denoiser-bench: timing rows, FLOPs, memory, quality join, ratio table and plot."""

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.eval_data import write_dataset

from denoiser.configs import build_net, compose_net_config
from denoiser.frames import resize_frame
from denoiser.inference import ovext
from denoiser.measure import PeakRss, time_steps
from denoiser.recurrent import Stepper
from denoiser.report.plot_tradeoff import pareto_front, pareto_front_of_rows
from denoiser.tables import read_csv


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("bench")
    write_dataset(root / "data", sequences=1, frames=3, size=24)
    ckpt = tiny_checkpoint(root / "student.ckpt")
    return root, ckpt


compose = compose_command


def base_label(label: str) -> str:
    """A backend label without the graph OpenVINO ran (``openvino f32 (fused)`` -> ``openvino f32``)."""
    for graph in (" (fused)", " (plain)"):
        if label.endswith(graph):
            return label[: -len(graph)]
    return label


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
    cpuinfo = Path("/proc/cpuinfo").read_text() if Path("/proc/cpuinfo").exists() else ""  # the CPU's flags, read here
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")), [])
    assert all(f"{f} {'yes' if f in flags else 'no'}" in (out / "report.md").read_text()
               for f in ("avx2", "avx512f", "avx512_bf16", "amx_tile"))  # the machine line states this CPU's ISA
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
    assert "## Student vs OIDN-fast" in report and "| 40x24 | fp32 vs fp32 (like with like) |" in report
    # versions and the thread count each engine reports (threads=1 asked of all), in the CSV, JSON and report
    import json

    from denoiser.report.bench_report import engine_versions

    versions = engine_versions()
    doc = json.loads((out / "bench.json").read_text())
    assert doc["machine"]["versions"] == versions and set(doc["machine"]["isa"]) >= {"avx2", "avx512f", "amx_bf16"}
    for engine, version in versions.items():
        assert f"{engine} {version}" in report
    assert timed[("student", "onnxruntime", 16)]["engine"] == f"onnxruntime {versions['onnxruntime']}"
    assert timed[("OIDN-fast", "OIDN (pyoidn)", 16)]["engine"] == f"oidn {versions['oidn']}"
    assert all(r["threads"] == 1 for r in timed.values() if r["device"] == "cpu"), [r["threads"] for r in timed.values()]
    assert all(len(r["times_ms"]) == 2 and r["ms_min"] <= r["ms_median"] <= r["ms_max"]
               for r in doc["rows"] if r["status"] == "ok")
    # the harness check: pyoidn's execute() alone, interleaved with the harness's OIDN path; not a table row
    assert [c["size"] for c in doc["harness_checks"]] == ["16x16", "40x24"]
    assert all(c["status"] == "ok" and c["direct_threads"] == 1 for c in doc["harness_checks"])
    assert "harness overhead on OIDN-fast at 40x24: " in report and not any(r["kind"] == "check" for r in table)
    assert "matmul peak" in report and "accuracy_vs_time.png" in report
    assert (out / "accuracy_vs_time.png").read_bytes()[:4] == b"\x89PNG"
    front = pareto_front_of_rows(table, (24, 40))
    assert front and set(front) <= {"student", "OIDN-fast"}
    # the per-CPU record: the run's ratios into a CSV (once, however often added) and its table
    from denoiser.machine import cpu_signature
    from denoiser.report.cpu_speed import main as cpu_speed

    csv, md = tmp_path / "cpu_speed.csv", tmp_path / "cpu_speed.md"
    assert doc["machine"]["cpu_id"] == cpu_signature() and doc["machine"]["commit"]
    for _ in range(2):
        assert cpu_speed(["add", str(out / "bench.json"), "--csv", str(csv), "--out", str(md)]) == 0
    record = read_csv(csv)
    assert [(r["size"], r["dtype"]) for r in record] == [(s["size"], s["dtype"]) for s in doc["speedups"]]
    assert all(r["cpu_id"] == cpu_signature() and r["baseline"] == "OIDN-fast" for r in record)
    first = doc["speedups"][0]
    assert f"{first['ratio']:.2f} ({first['ratio_lo']:.2f}-{first['ratio_hi']:.2f})" in md.read_text()
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    assert cpu_speed(["add", str(bad), "--csv", str(csv), "--out", str(md)]) == 2
    assert len(read_csv(csv)) == len(record)


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
    """python -m denoiser.commands.tools.bench_networks, tiny: the parent passes each job to a fresh process."""
    from denoiser.commands.tools.bench_networks import run

    rows = run(compose("bench_networks", ["nets=[tiny]", "sizes=[24x16]", "variants=[eager]", "repeats=2",
                                          "kernels=false"]))
    assert [(r["net"], r["variant"], r["size"], r["runs"]) for r in rows] == [("tiny", "eager", "24x16", 2)]
    assert rows[0]["ms"] > 0 and rows[0]["peak_mb"] >= 0 and 0 < rows[0]["gflop"] < 1
    assert "| tiny |" in capsys.readouterr().out


def test_default_student_for_the_ratio():
    from denoiser.report.speedup import default_student

    assert default_student(["teacher", "student_distilled", "student_no_kd"]) == "student_distilled"
    assert default_student(["teacher", "tiny"]) == "teacher"
    assert default_student([]) is None


def test_cpu_isa_flags():
    from denoiser.machine import cpu_isa, has_bf16

    info = "processor : 0\nflags\t\t: fpu sse avx2 avx512f avx512_bf16 amx_tile\nbugs : x\n"
    flags = cpu_isa(info)
    assert flags["avx512_bf16"] and flags["amx_tile"] and flags["avx2"] and not flags["amx_bf16"]
    assert not any(cpu_isa("").values())
    assert has_bf16(flags) and not has_bf16(cpu_isa("flags : avx2 avx512f\n"))


def test_cpu_signature_and_class():
    """A virtual machine's CPUs read alike by name; the signature and the vector class tell them apart."""
    from denoiser.machine import cpu_isa, cpu_signature
    from denoiser.report.cpu_speed import cpu_class

    info = ("processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\nmodel\t\t: 167\n"
            "model name\t: Intel(R) Xeon(R) Processor\nprocessor\t: 1\nmodel\t\t: 1\n")
    assert cpu_signature(info) == "GenuineIntel family 6 model 167" and cpu_signature("") == "unknown"
    assert cpu_class(cpu_isa("flags : avx2 avx512f avx512_bf16 amx_tile amx_bf16\n")) == "AMX"
    assert cpu_class(cpu_isa("flags : avx2 avx512f avx512_bf16\n")) == "AVX-512 + BF16"
    assert cpu_class(cpu_isa("flags : avx2 avx512f\n")) == "AVX-512"
    assert cpu_class(cpu_isa("flags : avx2 fma\n")) == "AVX2" and cpu_class(cpu_isa("")) == "other"


@pytest.mark.slow
def test_bench_openvino_rows(setup, tmp_path):
    """The OpenVINO backends of conf/bench.yaml time the network (or say why they are skipped)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    from denoiser.commands.bench import run as bench

    root, ckpt = setup
    rows = bench(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                   "sizes=[[16,24]]", "repeats=2", "warmup=1", "use_backends=[openvino_f32,openvino_bf16]",
                                   "baselines={}", f"out_dir={tmp_path}"]))
    openvino = [r["backend"] for r in rows if r["backend"].startswith("openvino")]
    assert len(openvino) == 2 and all(b.endswith((" (fused)", " (plain)")) for b in openvino), openvino  # which graph ran
    by = {base_label(r["backend"]): r for r in rows}
    assert by["openvino f32"]["status"] == "ok" and by["openvino f32"]["ms_median"] > 0
    assert by["openvino f32"]["dtype"] == "fp32" and by["openvino bf16"]["dtype"] == "bf16"
    assert by["openvino bf16"]["status"] == "ok" or by["openvino bf16"]["status"].startswith("skipped: ")
    # the report says whether bf16 pays here, by the same run's medians (what precision=auto measures)
    report = (tmp_path / "report.md").read_text()
    if by["openvino bf16"]["status"] == "ok":
        f32, bf16 = by["openvino f32"]["ms_median"], by["openvino bf16"]["ms_median"]
        assert f"OpenVINO bf16 {bf16:.1f} ms, f32 {f32:.1f} ms" in report
        assert ("bf16 pays on this CPU" if bf16 < f32 else "bf16 does not pay on this CPU") in report
    else:
        assert "## bf16 or f32" not in report
    # which implementations ran, named by OpenVINO's compiled model (issue 66: the profile per ISA)
    kernels = by["openvino f32"]["kernels"]
    assert list(kernels["openvino"]["Convolution"]) and "Input" not in kernels["openvino"], kernels
    assert "## Which kernels ran" in report and "Convolution " in report.split("## Which kernels ran")[1]
    if "(fused)" in by["openvino f32"]["backend"]:
        assert kernels["extension"] == ovext.built_for() and kernels["extension"] in report
    else:
        assert kernels["extension"] is None


def test_the_kernels_section_and_the_isa_caps(monkeypatch):
    """The sizes of one method and backend that ran the same kernels share a line, a size that ran
    others gets its own; node types without a kernel of their own are left out.
    An instruction-set cap in the environment is named on the machine line and the ratio's."""
    from denoiser.machine import ISA_CAPS, isa_caps
    from denoiser.report.bench_report import caps_sentence, kernels_section

    def row(h, w, conv, ext="avx2 avx fma sse2 (-march=x86-64-v3 from $DENOISER_OVEXT_MARCH)"):
        return {"method": "student", "backend": "openvino f32 (fused)", "height": h, "width": w,
                "kernels": {"openvino": {"Convolution": {conv: 19}, "Reshape": {"unknown_f32": 3},
                                         "Reference": {"ref_f32": 10}}, "extension": ext}}

    lines = kernels_section([row(16, 24, "brgconv_avx2_f32"), row(32, 48, "brgconv_avx2_f32"),
                             row(64, 96, "jit_avx2_f32"), {"method": "OIDN-fast", "backend": "OIDN", "height": 16,
                                                           "width": 24}])
    items = [line for line in lines if line.startswith("- ")]
    ext = "the extension's operations (`Reference`) built for avx2 avx fma sse2 (-march=x86-64-v3 from $DENOISER_OVEXT_MARCH)"
    assert items == [f"- **student**, openvino f32 (fused) (24x16, 48x32): Convolution brgconv_avx2_f32 x19; Reference ref_f32 x10; {ext}",
                     f"- **student**, openvino f32 (fused) (96x64): Convolution jit_avx2_f32 x19; Reference ref_f32 x10; {ext}"], items
    assert kernels_section([{"method": "m", "backend": "eager"}]) == []
    for name in ISA_CAPS:
        monkeypatch.delenv(name, raising=False)
    assert isa_caps() == {} and caps_sentence({}) == ""
    monkeypatch.setenv("ONEDNN_MAX_CPU_ISA", "AVX2")
    monkeypatch.setenv("MKL_ENABLE_INSTRUCTIONS", " ")  # blank: not a cap
    assert isa_caps() == {"ONEDNN_MAX_CPU_ISA": "AVX2"}
    sentence = caps_sentence(isa_caps())
    assert "$ONEDNN_MAX_CPU_ISA=AVX2 (oneDNN: OpenVINO's CPU plugin" in sentence and "OIDN reads no such cap" in sentence


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
    by = {base_label(r["backend"]): r for r in rows}
    assert "profile" not in by["eager fp32"]
    ops = by["openvino f32"]["profile"]
    assert "Convolution" in ops and all(ms >= 0 for ms in ops.values()) and list(ops.values()) == sorted(ops.values(), reverse=True)
    table = read_csv(tmp_path / "profile.csv")
    assert {base_label(r["backend"]) for r in table} == {"openvino f32"} and {r["op_type"] for r in table} == set(ops)
    assert abs(sum(float(r["share"]) for r in table) - 1.0) < 1e-6
    report = (tmp_path / "report.md").read_text()
    assert "## Where the time goes" in report
    # the fused graph's Reference nodes are the extension's operations, each named (issue 66)
    extension = by["openvino f32"]["extension_profile"]
    if "(fused)" in by["openvino f32"]["backend"]:
        assert {"PyramidFilterHead", "EmbedNet", "WarpHistory"} <= set(extension), extension
        assert sum(extension.values()) == pytest.approx(ops["Reference"], rel=1e-6)
        assert "The extension's operations" in report and "| PyramidFilterHead |" in report
    else:
        assert extension == {}


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


def test_speedups_are_paired_per_round_and_precision_matched():
    """Each row's speed-up is the median of the per-round ratios OIDN time / its time (computed
    here by hand), with the min-max as interval at 7 rounds; the student's fp32 rows come first
    and are labelled like with like, its bf16 rows are labelled as bf16 against OIDN's fp32."""
    from denoiser.report.speedup import add_speedups, precision_order, ratio_rows

    def row(backend, dtype, times, kind="checkpoint", method="s"):
        return {"method": method, "backend": backend, "dtype": dtype, "device": "cpu", "height": 8, "width": 8,
                "kind": kind, "ms_median": sorted(times)[3], "times_ms": times, "psnr": 30.0, "repeats": len(times)}

    oidn = row("OIDN (pyoidn)", "fp32", [10, 12, 11, 30, 10, 10, 10], kind="baseline", method="OIDN-fast")
    ov_bf16 = row("openvino bf16", "bf16", [2, 3, 2, 6, 4, 5, 2])
    ov_f32 = row("openvino f32", "fp32", [5, 6, 5.5, 10, 4, 5, 5])
    rows = precision_order([oidn, ov_bf16, ov_f32])
    assert [r["backend"] for r in rows] == ["OIDN (pyoidn)", "openvino f32", "openvino bf16"]
    add_speedups(rows, "OIDN-fast")
    # by hand: 10/5, 12/6, 11/5.5, 30/10, 10/4, 10/5, 10/5 = 2, 2, 2, 3, 2.5, 2, 2 -> median 2, min 2, max 3
    assert (ov_f32["speedup"], ov_f32["speedup_lo"], ov_f32["speedup_hi"]) == (2.0, 2.0, 3.0)
    # 5, 4, 5.5, 5, 2.5, 2, 5 -> sorted 2, 2.5, 4, 5, 5, 5, 5.5
    assert (ov_bf16["speedup"], ov_bf16["speedup_lo"], ov_bf16["speedup_hi"]) == (5.0, 2.0, 5.5)
    assert ov_f32["speedup_coverage"] == pytest.approx(1 - 2 / 2**7)
    ratios = ratio_rows(rows, "s", "OIDN-fast", [[8, 8]])
    assert [(r["student"], r["compare"], r["ratio"]) for r in ratios] == [
        ("s (openvino f32)", "fp32 vs fp32 (like with like)", 2.0), ("s (openvino bf16)", "bf16 vs fp32", 5.0)]
    assert ratios[1]["speedup_text"] == "5.00 (2.00-5.50)"


def test_median_interval_by_hand():
    """Order statistics: 7 values give the min-max (coverage 1 - 2/2^7), 9 the second smallest
    and second largest (1 - 2 (1 + 9)/2^9), 5 only the min-max at 1 - 2/2^5 < 95%."""
    from denoiser.measure import median_interval

    seven = median_interval([7, 1, 5, 3, 2, 6, 4])
    assert (seven["median"], seven["lo"], seven["hi"]) == (4, 1, 7) and seven["coverage"] == 1 - 2 / 128
    nine = median_interval([9, 1, 8, 2, 7, 3, 6, 4, 5])
    assert (nine["median"], nine["lo"], nine["hi"]) == (5, 2, 8) and nine["coverage"] == 1 - 2 * 10 / 512
    five = median_interval([5, 4, 3, 2, 1])
    assert (five["lo"], five["hi"], five["coverage"]) == (1, 5, 1 - 2 / 32)


def test_round_robin_rotates_the_order_each_round():
    """Warm-up: each entry's steps in turn inside its context; then each round times every entry
    once, the order rotated by the round; the times are the (fake) clock's differences around
    the timed call only, not around the untimed staging."""
    from denoiser.measure import round_robin

    log = []
    now = {"t": 0.0}

    def clock():
        return now["t"]

    def entry(name, cost):
        def stage(k):
            log.append(("stage", name, k))
            now["t"] += 100  # staging is untimed: never in the result

            def call():
                log.append(("call", name, k))
                now["t"] += cost
            return call
        return stage

    class Context:
        def __init__(self, name):
            self.name = name

        def __enter__(self):
            log.append(("enter", self.name))

        def __exit__(self, *exc):
            log.append(("exit", self.name))

    def failing(k):
        if k == 2:
            raise RuntimeError("boom")
        return lambda: None

    entries = {"a": entry("a", 1.0), "b": entry("b", 2.0), "c": entry("c", 3.0), "d": failing}
    seconds, errors = round_robin(entries, warmup=1, repeats=4, warmup_context=Context, clock=clock)
    assert log[:6] == [("enter", "a"), ("stage", "a", 0), ("call", "a", 0), ("exit", "a"), ("enter", "b"),
                       ("stage", "b", 0)]
    calls = [(name, k) for what, name, *k in log if what == "call"]
    timed_order = [name for name, (k,) in calls if k >= 1]
    assert timed_order == ["a", "b", "c", "b", "c", "a", "c", "a", "b", "a", "b", "c"]
    assert seconds == {"a": [1.0] * 4, "b": [2.0] * 4, "c": [3.0] * 4, "d": [0.0]}
    assert list(errors) == ["d"] and str(errors["d"]) == "boom"


@pytest.mark.slow
def test_bench_openvino_bf16_psnr_through_the_backend(tmp_path):
    """The bf16 row's PSNR is measured through OpenVINO bf16: finite and within 0.1 dB of eager fp32
    (bf16 keeps 8 mantissa bits; tests/inference/test_openvino.py bounds the output error at 3e-2)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")
    from denoiser.commands.bench import run as bench
    from denoiser.inference.backends import OpenVinoBackend

    reason = OpenVinoBackend(precision="bf16").available()
    if reason:
        pytest.skip(reason)
    write_dataset(tmp_path / "data", sequences=1, frames=4, size=32)
    ckpt = tiny_checkpoint(tmp_path / "student.ckpt")
    rows = bench(compose("bench", ["data=tiny", f"data.root={tmp_path / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                   "sizes=[[32,32]]", "repeats=1", "warmup=0", "use_backends=[eager,openvino_bf16]",
                                   "baselines={}", f"out_dir={tmp_path / 'bench'}"]))
    by = {base_label(r["backend"]): r for r in rows}
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
    monkeypatch.setattr(bench_module, "engines_matmul_peak", lambda *a, **k: next(peaks))
    root, ckpt = setup
    out = tmp_path / "bench"
    rows = bench_module.run(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                              "sizes=[[16,16]]", "repeats=1", "warmup=1", "use_backends=[eager]",
                                              "quality=false", "baselines={}", f"out_dir={out}"]))
    row = next(r for r in rows if r["method"] == "student")
    assert row["peak_fraction"] == pytest.approx(row["gflops_per_s"] / 250.0)
    assert "fp32 matmul peak 250.0 GFLOP/s" in (out / "report.md").read_text()


def test_no_module_changes_the_allocator_for_the_process():
    """Every method of denoiser-bench runs under the same process-wide settings: no module of the
    package tunes glibc's allocator (``keep_freed_memory``'s ``mallopt`` was removed after
    measuring it, docs/export.md)."""
    import denoiser

    root = Path(denoiser.__file__).parent
    assert [str(p) for p in root.rglob("*.py") if "mallopt" in p.read_text()] == []


def test_skip_names_a_method_or_a_backend(setup, tmp_path):
    """``skip`` leaves out a method at some sizes, or a backend (its ``use_backends`` key) for
    every network at some sizes; the rest still runs."""
    import denoiser.commands.bench as bench_module

    root, ckpt = setup
    rows = bench_module.run(compose("bench", ["data=tiny", f"data.root={root / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                              "sizes=[[16,16],[16,24]]", "repeats=1", "warmup=1",
                                              "use_backends=[eager,channels_last]", "skip={eager: [[16,24]]}",
                                              "quality=false", "baselines={}", f"out_dir={tmp_path / 'bench'}"]))
    ran = {(r["backend"], r["width"]) for r in rows if r["method"] == "student" and r["status"] == "ok"}
    assert ran == {("eager fp32", 16), ("channels_last fp32", 16), ("channels_last fp32", 24)}
