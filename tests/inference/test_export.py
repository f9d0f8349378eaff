"""Tests of denoiser-export: ONNX opset 17 with dynamic size and explicit recurrent state."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from helpers.ovext import extension_or_skip

from denoiser.checkpoint import save_checkpoint
from denoiser.configs import build_net, compose_net_config
from denoiser.errors import UserError
from denoiser.frames import random_frame
from denoiser.inference.step_graph import OnnxStep, StepGraph, check_export, uses_extension

VENV_BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A tiny checkpoint exported once through the console script (export + ORT check)."""
    root = tmp_path_factory.mktemp("export")
    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(0)
    net = build_net(cfg).eval()
    ckpt = save_checkpoint(root / "tiny.ckpt", net, cfg)
    onnx_path = root / "tiny.onnx"
    proc = subprocess.run([str(VENV_BIN / "denoiser-export"), f"ckpt={ckpt}", f"out={onnx_path}", "check_size=[20,28]",
                           "threads=1", f"hydra.run.dir={root / 'h'}"], capture_output=True, text=True, timeout=300,
                          check=False)
    return root, net, ckpt, onnx_path, proc


def test_graph_interface(tiny):
    _, net, _, path, _ = tiny
    model = onnx.load(str(path))
    assert model.opset_import[0].version == 17
    inputs = {i.name: [d.dim_param or d.dim_value for d in i.type.tensor_type.shape.dim] for i in model.graph.input}
    assert list(inputs) == StepGraph(net).input_names()
    assert inputs["color"] == [1, 3, "height", "width"] and inputs["reset"] == [1]
    assert inputs["state_features"] == [1, net.temporal.state_features, "height", "width"]
    outputs = [o.name for o in model.graph.output]
    assert outputs == ["output", "next_state_output", "next_state_color", "next_state_features", "next_state_guide"]
    assert {p.key: p.value for p in model.metadata_props}["state_keys"] == "output,color,features,guide"


@pytest.mark.parametrize("size", [(24, 40), (33, 17)])
def test_onnx_matches_pytorch_at_other_sizes(tiny, size):
    _, net, _, path, _ = tiny
    errors = check_export(net, path, size=size, steps=3)
    assert set(errors) >= {"output", "next_state_color"}
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


def test_state_carries_history(tiny):
    """The second step depends on the state: feeding a reset or another state changes the output."""
    _, _, _, path, _ = tiny
    runner = OnnxStep(path)
    f0, f1 = random_frame(1, 16, 16, seed=1, kind="hard"), random_frame(1, 16, 16, seed=2, kind="hard")
    for f in (f0, f1):
        f["motion"].zero_()
    _, state = runner.step(f0, None, reset=True)
    with_history, _ = runner.step(f1, state, reset=False)
    after_reset, _ = runner.step(f1, state, reset=True)
    fresh, _ = runner.step(f1, None, reset=True)
    assert not np.allclose(with_history, after_reset)
    assert np.allclose(after_reset, fresh, atol=1e-6)
    # a reset never reads the old state: NaN and Inf there do not reach the output
    broken = {k: np.full_like(v, np.nan) for k, v in state.items()}
    broken["output"][..., ::2] = np.inf
    after_broken, _ = runner.step(f1, broken, reset=True)
    assert np.isfinite(after_broken).all() and np.allclose(after_broken, fresh, atol=1e-6)


def test_graph_is_lean(tiny):
    """The kernel application adds no convolution (its views are slices, not a one-hot im2col
    convolution) and no shape arithmetic per tap: the graph's only convolutions are the
    network's own (the first one split per input part), and its non-constant nodes stay few (the tiny graph had 4446 nodes with
    the training path's in-place taps, 807 with the im2col convolutions, 940 now)."""
    _, net, _, path, _ = tiny
    nodes = onnx.load(str(path)).graph.node
    convs = sum(isinstance(m, torch.nn.Conv2d) for m in net.modules())
    # the U-Net's first convolution runs once per input part: the embedding, then each history
    # input; the EmbedNet's first layer once per part too (color feature, guide)
    parts = 1 + (len(net.temporal.input_layout) if net.temporal is not None else 0)
    assert sum(n.op_type == "Conv" for n in nodes) == convs + (parts - 1) + (2 - 1)
    assert sum(n.op_type != "Constant" for n in nodes) < 1200


def export_command(tmp_path, ckpt, out, *overrides) -> subprocess.CompletedProcess:
    """``denoiser-export`` of ``ckpt`` to ``out`` with ``overrides``, checked at 28x20 on one thread."""
    return subprocess.run([str(VENV_BIN / "denoiser-export"), f"ckpt={ckpt}", f"out={out}", *overrides,
                           "check_size=[20,28]", "threads=1", f"hydra.run.dir={tmp_path / 'h'}"],
                          capture_output=True, text=True, timeout=300, check=False)


def test_matmul_heads_export(tiny, tmp_path):
    """``heads=matmul`` (the f32 graph's form): every U-Net head becomes matrix products (the
    level-0 head one per part, no 1x1 convolution left for a head) and each decoder block's first
    convolution runs per part, the skip and the upsampled features (no concatenation feeds a
    convolution), with the same numbers as PyTorch."""
    _, net, ckpt, conv_path, _ = tiny
    out = tmp_path / "mm.onnx"
    proc = export_command(tmp_path, ckpt, out, "heads=matmul")
    assert proc.returncode == 0, proc.stderr[-2000:]
    conv_nodes, mm_nodes = onnx.load(str(conv_path)).graph.node, onnx.load(str(out)).graph.node
    heads = sum(n > 0 for n in net.unet.head_channels)

    def count(nodes, op):
        return sum(n.op_type == op for n in nodes)

    decoders = len(net.unet.decoder)
    assert count(mm_nodes, "Conv") == count(conv_nodes, "Conv") - heads + decoders

    def concat_into_conv(nodes) -> bool:
        made_by = {o: n for n in nodes for o in n.output}
        return any(made_by[i].op_type == "Concat" for n in nodes if n.op_type == "Conv" for i in n.input if i in made_by)

    assert not concat_into_conv(mm_nodes) and concat_into_conv(conv_nodes)  # the other form concatenates
    assert count(mm_nodes, "MatMul") == count(conv_nodes, "MatMul") + heads + 1  # level 0: two parts
    errors = check_export(net, out, size=(33, 17), steps=3)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


def count_of(model, op: str) -> int:
    return sum(n.op_type == op for n in model.graph.node)


def test_fused_kernels_export(tiny, tmp_path):
    """``kernels=fused``: one ``denoiser::PyramidFilter`` node instead of the partition, the
    kernel softmaxes, the k*k multiply-adds per level and the upsampling, ``denoiser::Log1p``
    for the input transforms' ``log1p`` and ``denoiser::WarpHistory`` for the history's sampling (no
    ``GridSample``); checked by the command
    with OpenVINO (ONNX Runtime cannot run it), and equal to PyTorch at another size over three
    recurrent steps."""
    pytest.importorskip("openvino", reason="openvino is not installed (pip install .[openvino])")
    extension_or_skip()
    _, net, ckpt, conv_path, _ = tiny
    out = tmp_path / "fused.onnx"
    proc = export_command(tmp_path, ckpt, out, "kernels=fused")
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "OpenVINO vs PyTorch at 28x20" in proc.stdout and "trtexec" not in proc.stdout
    plain, fused = onnx.load(str(conv_path)), onnx.load(str(out))
    levels = len(net.filter.kernel_sizes)
    ours = [n.op_type for n in fused.graph.node if n.domain == "denoiser"]
    assert ours.count("PyramidFilter") == 1 and set(ours) == {"PyramidFilter", "Log1p", "WarpHistory"}  # the whole filter, one node
    assert ours.count("WarpHistory") == 1 and count_of(fused, "GridSample") == 0  # the history's sampling, one node

    count = count_of
    assert count(plain, "Log") - count(fused, "Log") == ours.count("Log1p") >= 2  # the color and albedo features
    assert count(fused, "Softmax") == count(plain, "Softmax") - levels - 1  # the kernels' and the partition's
    assert uses_extension(out) and not uses_extension(conv_path)
    errors = check_export(net, out, size=(33, 17), steps=3)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


@pytest.mark.parametrize("graph", ["onnxruntime", "openvino_f32"])
def test_the_direct_ablation_exports(tmp_path, graph):
    """``ablation=direct`` (the U-Net predicts the colour, :class:`~denoiser.nn.filters.DirectColor`)
    exports, in ONNX Runtime's graph and in the OpenVINO f32 graph that make ablations times, and
    equals PyTorch over three recurrent steps: its ``expm1`` is written ``exp - 1`` in a graph
    (ONNX has no Expm1; make ablations could not time the variant)."""
    from denoiser.inference.step_graph import export_onnx

    fused = graph == "openvino_f32"
    if fused:
        extension_or_skip()
    torch.manual_seed(0)
    net = build_net(compose_net_config("tiny", "student", ablation="direct")).eval()
    path = export_onnx(net, tmp_path / "direct.onnx", matmul_heads=fused, fused_kernels=fused)
    assert uses_extension(path) == fused
    errors = check_export(net, path, size=(33, 17), steps=3)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


def test_export_command(tiny):
    *_, out, proc = tiny
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "ONNX Runtime vs PyTorch at 28x20" in proc.stdout and "max abs error" in proc.stdout
    assert "trtexec --onnx=" in proc.stdout and out.exists()


def test_export_config_errors(tiny, tmp_path):
    from omegaconf import OmegaConf

    from denoiser.commands.export import run

    _, _, ckpt, _, _ = tiny
    base = {"ckpt": str(ckpt), "out": str(tmp_path / "x.onnx"), "opset": 17, "batch": 1, "trace_size": [37, 61],
            "check_size": [37, 61], "tolerance": 1e-4, "threads": None}
    with pytest.raises(UserError, match="check_size must differ"):
        run(OmegaConf.create(base))
    with pytest.raises(UserError, match="should end in .onnx"):
        run(OmegaConf.create({**base, "out": str(tmp_path / "x.txt")}))
    with pytest.raises(UserError, match="none.ckpt: checkpoint file does not exist"):
        run(OmegaConf.create({**base, "ckpt": str(tmp_path / "none.ckpt")}))
    with pytest.raises(UserError, match="heads: 'dense' is not conv or matmul"):
        run(OmegaConf.create({**base, "check_size": [20, 28], "heads": "dense"}))
    with pytest.raises(UserError, match="kernels: 'unfold' is not graph or fused"):
        run(OmegaConf.create({**base, "check_size": [20, 28], "kernels": "unfold"}))
    assert not (tmp_path / "x.onnx").exists()


def test_export_refuses_non_finite_weights(tmp_path):
    """The graph leaves out the logits' non-finite replacement (denoiser.nn.kernels.scale_logits),
    so it relies on finite weights: a diverged network is refused with one line, nothing written."""
    from denoiser.inference.step_graph import export_onnx

    net = build_net(compose_net_config("tiny", "student")).eval()
    with torch.no_grad():
        net.unet.heads[0].weight[0, 0, 0, 0] = float("nan")
    out = tmp_path / "bad.onnx"
    with pytest.raises(UserError, match=r"^run/last.ckpt: cannot export non-finite .* weights in unet.heads.0.weight"):
        export_onnx(net, out, metadata={"checkpoint": "run/last.ckpt"})
    assert list(tmp_path.iterdir()) == []
