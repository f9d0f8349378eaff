"""The OpenVINO backend: the exported step graph compiled by OpenVINO against eager PyTorch.

Tolerances (tiny net, 4 frames of ``random_frame(kind="hard")``: fireflies, HDR values in the
hundreds, large motion; a reset at frame 2; errors relative to ``max(1, |value|)``):

* f32: ``F32_RTOL`` = 1e-4 (measured with OpenVINO 2026.4 on an AVX512 CPU: 1.8e-6 on the
  output, 1.1e-5 on the color state; float32 rounding in another operator order);
* bf16: ``BF16_RTOL`` = 0.03 on the output (measured: 6.5e-3 on the output, 1.2e-3 on the
  feature state; bfloat16 keeps 8 mantissa bits, 0.4 % per rounding; 5x margin). The
  kernel application keeps the output a convex combination of input pixels, so bf16 errors
  in the logits move weights, never the range.
"""

import numpy as np
import pytest
import torch
from helpers.ovext import extension_or_skip

pytest.importorskip("openvino", reason="openvino is not installed (pip install .[openvino])")
pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")

from denoiser.configs import build_net, compose_net_config
from denoiser.frames import random_frame
from denoiser.inference import ovext
from denoiser.inference.backends import OpenVinoBackend, TorchBackend
from denoiser.inference.step_graph import OpenVinoStep, compiled_kernels, export_onnx
from denoiser.recurrent import RecurrentRunner

F32_RTOL = 1e-4
BF16_RTOL = 0.03
RESETS = (True, False, True, False)  # first frame and a cut in the middle
TEMPORAL = ["+net.temporal.history_clamp=1.0", "+net.temporal.reject_threshold=0.1"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    torch.manual_seed(0)
    # with the shipped student's temporal options: the history clamp and the disocclusion gate
    # (denoiser::ClampBlend and denoiser::GuideGate in the fused graphs)
    net = build_net(compose_net_config("tiny", "student", overrides=TEMPORAL)).eval()
    root = tmp_path_factory.mktemp("ov")
    path = export_onnx(net, root / "tiny.onnx")
    export_onnx(net, root / "tiny-mm.onnx", matmul_heads=True)
    if ovext.kernel_extension() is not None:
        export_onnx(net, root / "tiny-mm-fused.onnx", matmul_heads=True, fused_kernels=True)
        export_onnx(net, root / "tiny-fused.onnx", fused_kernels=True)
    frames = [random_frame(1, 20, 28, seed=10 + t, kind="hard") for t in range(len(RESETS))]
    eager = RecurrentRunner(net.step)
    expected = []
    with torch.no_grad():
        for frame, reset in zip(frames, RESETS):
            expected.append((eager(frame, reset).numpy(), {k: v.numpy() for k, v in eager.state.items()}))
    return net, path, frames, expected


def relative_errors(path, frames, expected, precision):
    runner = RecurrentRunner(OpenVinoStep(path, threads=1, precision=precision).step)
    worst = {}
    for frame, reset, (out, state) in zip(frames, RESETS, expected):
        got = runner(frame, reset)
        pairs = [("output", out, got)] + [(k, state[k], runner.state[k]) for k in state]
        for name, a, b in pairs:
            assert a.shape == b.shape, name
            err = float((np.abs(a - b) / np.maximum(1.0, np.abs(a))).max())
            worst[name] = max(worst.get(name, 0.0), err)
    return worst


def graph(path, name):
    """One of the fixture's exported graphs: ``conv``, ``matmul`` (heads), ``matmul-fused`` (the
    graph the f32 backend runs: matmul heads and denoiser::KernelApply) or ``fused`` (bf16's)."""
    if "fused" in name:
        extension_or_skip()
    return path.with_name({"conv": "tiny.onnx", "matmul": "tiny-mm.onnx", "matmul-fused": "tiny-mm-fused.onnx",
                           "fused": "tiny-fused.onnx"}[name])


@pytest.mark.parametrize("heads", ["conv", "matmul", "matmul-fused", "fused"])
def test_f32_matches_eager(tiny, heads):
    _, path, frames, expected = tiny
    path = graph(path, heads)
    errors = relative_errors(path, frames, expected, "f32")
    print("openvino f32 max relative error", errors)
    assert set(errors) >= {"output", "features", "color"}
    assert all(e <= F32_RTOL for e in errors.values()), errors


@pytest.mark.parametrize("kernels", ["graph", "fused"])
def test_bf16_within_its_tolerance(tiny, kernels):
    if OpenVinoBackend(precision="bf16").available():
        pytest.skip(OpenVinoBackend(precision="bf16").available())
    _, path, frames, expected = tiny
    path = graph(path, "conv" if kernels == "graph" else "fused")
    step = OpenVinoStep(path, threads=1, precision="bf16")
    assert step.precision(1, 20, 28) == "bf16"
    errors = relative_errors(path, frames, expected, "bf16")
    print("openvino bf16 max relative error", errors)
    assert errors["output"] <= BF16_RTOL, errors


def test_compiles_once_per_size_and_resets(tiny):
    _, path, frames, _ = tiny
    step = OpenVinoStep(path, threads=1)
    runner = RecurrentRunner(step.step)
    runner(frames[0], True)
    runner(frames[1], False)
    assert list(step._compiled) == [(1, 20, 28)]
    small = {k: v[..., :16, :16] for k, v in frames[0].items()}
    runner(small, True)
    assert list(step._compiled) == [(1, 20, 28), (1, 16, 16)]
    # state None is a reset: the first frame again gives the first output
    again = RecurrentRunner(step.step)
    assert np.array_equal(again(frames[0], True), RecurrentRunner(step.step)(frames[0], False))
    # a reset never reads the old state (its sample positions lie off the image): NaN and Inf
    # there do not reach the output
    _, state = step.step(frames[0], None, reset=True)
    broken = {k: np.where(np.arange(v.shape[-1]) % 2 == 0, np.nan, np.inf).astype(v.dtype) * np.ones_like(v)
              for k, v in state.items()}
    fresh, _ = step.step(frames[1], None, reset=True)
    after, _ = step.step(frames[1], broken, reset=True)
    assert np.isfinite(after).all() and np.array_equal(after, fresh)


@pytest.mark.parametrize("heads", ["conv", "matmul-fused"])
def test_the_state_is_not_copied_and_a_held_state_is_never_written(tiny, heads):
    """OpenVinoStep returns its slots' arrays as the state (no copy): a sequence stepped alone
    runs on two slots, and a state that is still held (stepped from again, two sequences in
    turn) keeps its values while other steps run; every output equals a fresh runner's."""
    _, path, frames, _ = tiny
    path = graph(path, heads)
    step = OpenVinoStep(path, threads=1)

    def alone(frames_resets):  # a fresh runner per sequence: the reference
        runner = RecurrentRunner(OpenVinoStep(path, threads=1).step)
        return [(runner(f, r), {k: v.copy() for k, v in runner.state.items()}) for f, r in frames_resets]

    sequence = list(zip(frames, RESETS)) * 2
    runner = RecurrentRunner(step.step)
    got = [runner(f, r) for f, r in sequence]
    assert all(np.array_equal(a, b) for a, (b, _) in zip(got, alone(sequence)))
    assert len(step._compiled[(1, 20, 28)][1]) == 2                         # one sequence: two slots, in turn
    held = OpenVinoStep(path, threads=1)
    _, state = held.step(frames[0], None, reset=True)                       # slot 0
    slots = held._compiled[(1, 20, 28)][1]
    assert all(state[k] is slots[0].arrays[f"next_state_{k}"] for k in state)   # not a copy
    kept = {k: v.copy() for k, v in state.items()}
    held.step(frames[1], state)                                             # slot 1, reading slot 0
    held.step(frames[2], None, reset=True)                                  # slot 0 is held by `state`: slot 1
    held.step(frames[3], held.step(frames[1], state)[1])
    assert all(np.array_equal(state[k], kept[k]) for k in state)            # held: never written
    del state
    held.step(frames[2], None, reset=True)
    assert len(slots) == 3 and not any(s.held(slots) for s in slots)        # a slot no one holds is reused
    a_state = b_state = None                                                # two sequences in turn
    reference_a, reference_b = alone(list(zip(frames, RESETS))), alone(list(zip(frames[::-1], RESETS)))
    for t, (fa, fb, reset) in enumerate(zip(frames, frames[::-1], RESETS)):
        out_a, a_state = step.step(fa, None if reset else a_state, reset)
        out_b, b_state = step.step(fb, None if reset else b_state, reset)
        assert np.array_equal(out_a, reference_a[t][0]) and np.array_equal(out_b, reference_b[t][0]), t
        assert all(np.array_equal(a_state[k], reference_a[t][1][k]) for k in a_state), t
    step.close()
    assert all(np.isfinite(v).all() for v in a_state.values())              # the arrays outlive the runner


def test_backend_steps_like_the_eager_backend(tiny):
    net, _, frames, _ = tiny
    backend = OpenVinoBackend("openvino f32", precision="f32")
    assert backend.available() is None and backend.dtype == "fp32"
    ov_runner = RecurrentRunner(backend.prepare(net, frames[0], threads=1).step)
    eager = RecurrentRunner(TorchBackend().prepare(net, frames[0], threads=1).step)
    for frame, reset in zip(frames, RESETS):
        a, b = eager(frame, reset).numpy(), ov_runner(frame, reset)
        assert np.all(np.abs(a - b) <= F32_RTOL * np.maximum(1.0, np.abs(a)))
    with pytest.raises(ValueError, match="precision"):
        OpenVinoBackend(precision="fp8")


def test_backend_exports_heads_per_precision(tiny):
    """f32 runs the heads as matrix products and each decoder block's first convolution per
    part, bf16 the heads as 1x1 convolutions and the decoder on concatenations (the heads' forms
    are each the faster one in OpenVINO at that precision; the per-part decoder was measured in
    f32 only: docs/export.md)."""
    import onnx

    net = tiny[0]
    heads = sum(n > 0 for n in net.unet.head_channels)
    convs = {}
    for precision in ("f32", "bf16"):
        backend = OpenVinoBackend(precision=precision)
        assert backend.matmul_heads == (precision == "f32")
        nodes = onnx.load(backend._export(net)).graph.node
        convs[precision] = sum(n.op_type == "Conv" for n in nodes)
    assert convs["bf16"] - convs["f32"] == heads - len(net.unet.decoder)


def test_fused_option_forces_the_graph(monkeypatch):
    """fused=false: the plain graph, said in the label, without building the extension; fused=true
    without the extension: available() says why."""
    monkeypatch.setattr(ovext, "_status", lambda: (None, "no C++ compiler ($CXX, g++ or c++)"))
    plain = OpenVinoBackend("openvino f32", precision="f32", fused=False)
    assert plain.label == "openvino f32 (plain)" and plain.fused_kernels is False
    forced = OpenVinoBackend("openvino bf16", precision="bf16", fused=True)
    assert forced.label == "openvino bf16 (fused)"
    if OpenVinoBackend(precision="f32").available() is None:
        assert "fused=true: the OpenVINO extension is unavailable" in OpenVinoBackend(precision="f32", fused=True).available()


@pytest.mark.parametrize("extension", [True, False])
def test_backend_fuses_kernels_when_the_extension_builds(tiny, monkeypatch, capsys, extension):
    """With the extension the f32 backend exports one denoiser::PyramidFilterHead (its matmul heads'
    level-0 head computed inside the filter; bf16 exports denoiser::PyramidFilter); without it
    (no compiler) the backend says why on stderr and runs the plain graph, with the same numbers."""
    import onnx

    if extension:
        extension_or_skip()
    else:
        monkeypatch.setattr(ovext, "_status", lambda: (None, "no C++ compiler ($CXX, g++ or c++)"))
    net, _, frames, expected = tiny
    backend = OpenVinoBackend("openvino f32", precision="f32")
    runner = RecurrentRunner(backend.prepare(net, frames[0], threads=1).step)
    assert backend.fused_kernels is extension
    assert backend.label == f"openvino f32 ({'fused' if extension else 'plain'})"  # the graph that ran, in every row
    nodes = onnx.load(backend._export(net)).graph.node
    assert sum(n.op_type == "PyramidFilterHead" for n in nodes) == int(extension)
    assert not any(n.op_type == "PyramidFilter" for n in nodes)
    assert ("plain kernel filter graph (no C++ compiler" in capsys.readouterr().err) is not extension
    for frame, reset, (out, _) in zip(frames, RESETS, expected):
        got = runner(frame, reset)
        assert np.all(np.abs(out - got) <= F32_RTOL * np.maximum(1.0, np.abs(out)))


def test_the_bench_warm_up_reaches_every_slot(tiny):
    """denoiser-bench's default warm-up runs every infer request a recurrent OpenVINO step
    alternates between (its two slots), so no timed step is the first on a request (whose
    intermediate memory OpenVINO maps then: at 1080p about 1,400-3,400 page faults and 200 ms on the
    first timed step after a one-step warm-up, 10-20 faults on the later ones)."""
    from denoiser.configs import compose_config
    from denoiser.measure import recurrent_steps, round_robin

    _, path, frames, _ = tiny
    cfg = compose_config([], "bench")
    step = OpenVinoStep(path, threads=1)
    stepper = type("S", (), {"step": staticmethod(step.step), "sync": staticmethod(lambda: None)})
    _, errors = round_robin({"f32": recurrent_steps(stepper, frames)}, int(cfg.warmup), 0)
    assert not errors
    slots = step._compiled[(1, 20, 28)][1]
    assert len(slots) == 2 and all(s.fed for s in slots)  # each request has inferred


def test_the_profile_is_the_last_step_alone(tiny):
    """OpenVINO's CPU plugin reports each node's mean over every infer of a compiled model, the
    cold first one included; last_profile gives the last step's own times (n * mean_n - (n-1) *
    mean_(n-1), the two slots' requests sharing one graph). Read as OpenVINO gives them, the
    bench's profiles carried the first step's allocations and page faults."""
    _, path, frames, _ = tiny
    step = OpenVinoStep(path, threads=1, profile=True)
    runner = RecurrentRunner(step.step)
    totals = []
    for t in range(6):
        runner(frames[t % len(frames)], t == 0)
        profile = step.last_profile()
        assert all(ms >= -0.01 for ms in step.last_nodes.values()), step.last_nodes
        assert sum(profile.values()) == pytest.approx(sum(step.last_nodes.values()))
        totals.append(sum(profile.values()))
    means = sum(node.real_time.total_seconds() * 1000 for node in step._last.profiling_info)
    # the first step is the cold one: OpenVINO's means sit above the fastest later step's own time
    assert min(totals[1:]) < means < totals[0], (totals, means)


def test_the_kernels_that_ran(tiny):
    """OpenVinoStep.last_kernels: the implementations of the compiled model the last step ran
    (node type -> implementation -> count), the graph's inputs, outputs and constants left out."""
    _, path, frames, _ = tiny
    step = OpenVinoStep(path, threads=1)
    assert step.last_kernels == {}
    RecurrentRunner(step.step)(frames[0], True)
    b, _, h, w = frames[0]["color"].shape
    compiled, _ = step.compiled(b, h, w)
    assert step.last_kernels == compiled_kernels(compiled)
    assert sum(step.last_kernels["Convolution"].values()) >= 3, step.last_kernels
    assert not {"Input", "Output", "Const"} & set(step.last_kernels)


CAPPED = """
import numpy as np, openvino as ov
from openvino import opset13 as ops
from denoiser.inference.step_graph import compiled_kernels
x = ops.parameter([1, 8, 16, 16], np.float32)
y = ops.convolution(x, ops.constant(np.ones((8, 8, 3, 3), np.float32)), [1, 1], [1, 1], [1, 1], [1, 1])
compiled = ov.Core().compile_model(ov.Model([y], [x]), "CPU", {"INFERENCE_PRECISION_HINT": "f32"})
print(" ".join(compiled_kernels(compiled)["Convolution"]))
from denoiser.inference.backends import OpenVinoBackend
print(OpenVinoBackend(precision="bf16", fused=False).available())
"""


def test_an_isa_cap_shows_in_the_kernels_that_ran():
    """$ONEDNN_MAX_CPU_ISA=AVX2 makes OpenVINO's CPU plugin run its AVX2 convolutions on an AVX-512
    CPU (how the bench shows an AVX2 CPU's profile on one: docs/export.md), and the kernels' names
    say so: the cap is checked by what ran, not inferred from a time. Under it the bf16 backend
    says in one line why it is skipped (OpenVINO still reports BF16 there, then fails to compile)."""
    import os
    import subprocess
    import sys

    from denoiser.machine import cpu_isa

    if not cpu_isa()["avx512f"]:
        pytest.skip("this CPU has no AVX-512: there is nothing to cap")
    env = {k: v for k, v in os.environ.items() if k not in ("ONEDNN_MAX_CPU_ISA", "DNNL_MAX_CPU_ISA")}
    ran = {}
    for cap in ("", "AVX2"):
        proc = subprocess.run([sys.executable, "-c", CAPPED], env={**env, **({"ONEDNN_MAX_CPU_ISA": cap} if cap else {})},
                              capture_output=True, text=True, timeout=300, check=False)
        assert proc.returncode == 0, proc.stderr[-2000:]
        ran[cap] = proc.stdout.splitlines()
    (plain, bf16), (capped, bf16_capped) = ran[""], ran["AVX2"]
    assert plain.split() == [plain] and "avx512" in plain, ran
    assert capped.split() == [capped] and "avx2" in capped and "avx512" not in capped, ran
    assert bf16_capped == "$ONEDNN_MAX_CPU_ISA=AVX2 caps oneDNN below bfloat16 (OpenVINO would fail to compile bf16)"
    assert bf16 == "None" or "no bf16 support" in bf16, ran


def test_bf16_capped_reads_the_onednn_caps():
    from denoiser.inference.backends import bf16_capped

    assert bf16_capped({}) is None and bf16_capped({"ONEDNN_MAX_CPU_ISA": "AVX512_CORE_AMX"}) is None
    assert bf16_capped({"MKL_ENABLE_INSTRUCTIONS": "AVX2"}) is None  # MKL's cap is not OpenVINO's
    assert "$DNNL_MAX_CPU_ISA=avx2 caps" in bf16_capped({"DNNL_MAX_CPU_ISA": "avx2"})
