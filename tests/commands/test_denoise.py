"""Tests of denoiser-denoise: native and Blender input, recurrent state, resume, errors."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.eval_data import write_sequence

from denoiser.checkpoint import load_denoiser
from denoiser.data.exr import list_channels, read_channels, write_channels
from denoiser.errors import UserError

VENV_BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("denoise")
    seq = write_sequence(root / "shot", frames=5, size=(24, 32), cuts=(3,), seed=4)
    ckpt = tiny_checkpoint(root / "tiny.ckpt")
    return root, seq, ckpt


def compose_denoise(overrides):
    return compose_command("denoise", overrides, threads=1)


def denoise(overrides):
    """denoiser-denoise in-process; f32 unless the test names a backend or precision (the default,
    precision=auto, may run bf16 where it is faster: these tests compare with eager's frames)."""
    from denoiser.commands.denoise import run

    if not any(o.startswith(("backend=", "precision=")) for o in overrides):
        overrides = [*overrides, "precision=f32"]
    return run(compose_denoise(overrides))


def expected_outputs(ckpt, seq, frames=5, cuts=(3,)):
    """Denoiser.forward over the whole sequence (state carried, reset at 0 and at the cuts)."""
    from denoiser.data.exr import read_frame

    names = {"color": ("color.R", "color.G", "color.B"), "albedo": ("albedo.R", "albedo.G", "albedo.B"),
             "normal": ("normal.X", "normal.Y", "normal.Z"), "depth": ("depth.Z",), "motion": ("motion.X", "motion.Y")}
    items = [read_frame(seq / f"frame_{t:04d}.exr", names)[0] for t in range(frames)]
    batch = {k: torch.stack([torch.from_numpy(it[k]).permute(2, 0, 1) for it in items])[None] for k in names}
    reset = torch.tensor([[t == 0 or t in cuts for t in range(frames)]])
    with torch.no_grad():
        out, _, _ = load_denoiser(ckpt)(batch, reset=reset)
    return out[0]


def denoised(path):
    ch = read_channels(path)
    return np.stack([ch["denoised.R"], ch["denoised.G"], ch["denoised.B"]])


def test_console_script_denoises_with_state_carried(setup, tmp_path):
    _root, seq, ckpt = setup
    out = tmp_path / "out"
    proc = subprocess.run([str(VENV_BIN / "denoiser-denoise"), f"ckpt={ckpt}", f"input={seq}", f"output={out}",
                           "threads=1", "precision=f32", f"hydra.run.dir={tmp_path / 'run'}"], capture_output=True,
                          text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "denoised 5 frame(s)" in proc.stdout
    expected = expected_outputs(ckpt, seq)
    for t in range(5):
        f = out / f"frame_{t:04d}.exr"
        assert set(list_channels(seq / f.name)) < set(list_channels(f))  # input channels preserved
        assert np.allclose(denoised(f), expected[t].numpy(), atol=1e-5), t
        orig, new = read_channels(seq / f.name), read_channels(f)
        assert all(np.array_equal(orig[k], new[k]) for k in orig)
    assert not list(out.glob(".*"))  # no temporary files left


@pytest.mark.parametrize("delete, replay, replayed", [((1, 2, 3, 4), None, 1), ((3, 4), None, 0), ((2, 4), None, 2),
                                                       ((2, 3, 4), 1, 1)])
def test_resume_is_exact(setup, tmp_path, delete, replay, replayed):
    _root, seq, ckpt = setup
    out = tmp_path / "out"
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={out}"])
    full = {t: denoised(out / f"frame_{t:04d}.exr") for t in range(5)}
    for t in delete:
        (out / f"frame_{t:04d}.exr").unlink()
    counts = denoise([f"ckpt={ckpt}", f"input={seq}", f"output={out}", f"replay_frames={'null' if replay is None else replay}"])
    assert counts["written"] == len(delete) and counts["replayed"] == replayed
    for t in range(5):
        got = denoised(out / f"frame_{t:04d}.exr")
        if replay is None or t >= 3:  # exact replay, or after the cut at 3 where history resets anyway
            assert np.array_equal(got, full[t]), t
    assert denoise([f"ckpt={ckpt}", f"input={seq}", f"output={out}"])["written"] == 0


def test_rgb_output(setup, tmp_path):
    _, seq, ckpt = setup
    out = tmp_path / "rgb"
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={out}", "write=rgb", "half=true"])
    assert sorted(list_channels(out / "frame_0004.exr")) == ["B", "G", "R"]


def test_missing_buffer_lists_channels_and_writes_nothing(setup, tmp_path):
    _, seq, ckpt = setup
    src = tmp_path / "nonormal"
    src.mkdir()
    for t in range(2):
        ch = read_channels(seq / f"frame_{t:04d}.exr")
        write_channels(src / f"frame_{t:04d}.exr", {k: v for k, v in ch.items() if not k.startswith("normal.")})
    with pytest.raises(UserError, match=r"frame_0000.exr: missing buffer\(s\) normal.*present channels: albedo.B"):
        denoise([f"ckpt={ckpt}", f"input={src}", f"output={tmp_path / 'o'}"])
    assert not (tmp_path / "o").exists()


def test_damaged_frame_leaves_no_output(setup, tmp_path):
    _, seq, ckpt = setup
    src = tmp_path / "damaged"
    src.mkdir()
    for t in range(3):
        data = (seq / f"frame_{t:04d}.exr").read_bytes()
        (src / f"frame_{t:04d}.exr").write_bytes(data if t != 2 else data[: len(data) // 2])
    with pytest.raises(UserError, match="frame_0002.exr"):
        denoise([f"ckpt={ckpt}", f"input={src}", f"output={tmp_path / 'o'}"])
    assert not (tmp_path / "o").exists()
    with pytest.raises(UserError, match="input directory"):
        denoise([f"ckpt={ckpt}", f"input={src}", f"output={src}"])


def test_blender_layout(setup, tmp_path):
    """Cycles multilayer names; Vector (X, Y) with +Y up becomes motion (X, -Y)."""
    _, seq, ckpt = setup
    src = tmp_path / "blender"
    for t in range(3):
        ch = read_channels(seq / f"frame_{t:04d}.exr")
        layer = {"ViewLayer.Combined." + c: ch[f"color.{c}"] for c in "RGB"}
        layer["ViewLayer.Combined.A"] = np.ones_like(ch["color.R"])
        layer.update({"ViewLayer.Denoising Albedo." + c: ch[f"albedo.{c}"] for c in "RGB"})
        layer.update({"ViewLayer.Denoising Normal." + c: ch[f"normal.{c}"] for c in "XYZ"})
        layer["ViewLayer.Depth.Z"] = ch["depth.Z"]
        layer["ViewLayer.Vector.X"] = ch["motion.X"]
        layer["ViewLayer.Vector.Y"] = -ch["motion.Y"]
        layer["ViewLayer.Vector.Z"] = layer["ViewLayer.Vector.W"] = np.zeros_like(ch["motion.X"])
        write_channels(src / "noisy" / f"{t + 1:04d}.exr", layer)
    out = tmp_path / "out"
    denoise([f"ckpt={ckpt}", f"input={src}", f"output={out}", "layout=blender"])
    expected = expected_outputs(ckpt, seq, frames=3, cuts=())
    assert sorted(p.name for p in out.glob("*.exr")) == ["0001.exr", "0002.exr", "0003.exr"]  # beside report.*
    for t in range(3):
        f = out / f"{t + 1:04d}.exr"
        assert "ViewLayer.Vector.W" in list_channels(f)
        assert np.allclose(denoised(f), expected[t].numpy(), atol=1e-5), t


def test_backend_choice_and_errors():
    from denoiser.commands.denoise import make_backend, openvino_installed

    cpu = torch.device("cpu")
    name, backend = make_backend(None, "f32", cpu)
    assert name == ("openvino" if openvino_installed() else "eager") and backend.dtype == "fp32"
    if torch.cuda.is_available():
        assert make_backend(None, "f32", torch.device("cuda"))[0] == "eager"
    else:
        with pytest.raises(UserError, match="backend=eager precision=f32: no CUDA device"):
            make_backend(None, "f32", torch.device("cuda"))
    assert make_backend("eager", "bf16", cpu)[1].dtype == "bf16"
    with pytest.raises(UserError, match="backend: 'tensorrt' is not one of"):
        make_backend("tensorrt", "f32", cpu)
    with pytest.raises(UserError, match="precision: 'fp8'"):
        make_backend("eager", "fp8", cpu)
    with pytest.raises(UserError, match="onnxruntime runs precision=f32 only"):
        make_backend("onnxruntime", "bf16", cpu)


@pytest.mark.parametrize("backend, precision, rtol", [("onnxruntime", "f32", 1e-4), ("openvino", "f32", 1e-4),
                                                      ("openvino", "bf16", 0.03)])
def test_graph_backends_match_eager(setup, tmp_path, backend, precision, rtol):
    """The exported graph in ONNX Runtime / OpenVINO gives eager's frames (tolerances: tests/inference/test_openvino.py)."""
    from denoiser.commands.denoise import make_backend

    try:
        make_backend(backend, precision, torch.device("cpu"))
    except UserError as exc:
        pytest.skip(str(exc))
    _, seq, ckpt = setup
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={tmp_path / 'eager'}", "backend=eager", "write=rgb"])
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={tmp_path / 'graph'}", f"backend={backend}",
             f"precision={precision}", "write=rgb"])
    for t in range(5):
        a = np.stack([read_channels(tmp_path / "eager" / f"frame_{t:04d}.exr")[c] for c in "RGB"])
        b = np.stack([read_channels(tmp_path / "graph" / f"frame_{t:04d}.exr")[c] for c in "RGB"])
        assert np.all(np.abs(a - b) <= rtol * np.maximum(1.0, np.abs(a))), (t, float(np.abs(a - b).max()))


def test_default_precision_is_the_faster_one_measured(setup, tmp_path, capsys):
    """OpenVINO's default precision (auto) times f32 and bf16 on the first frame and runs the faster,
    saying which with both figures; without bf16 on the CPU it runs f32 and says why."""
    pytest.importorskip("openvino")
    from denoiser.checkpoint import load_denoiser
    from denoiser.frames import random_frame
    from denoiser.inference.backends import faster_precision
    from denoiser.machine import has_bf16

    _, seq, ckpt = setup
    denoise([f"ckpt={ckpt}", f"input={seq}", f"output={tmp_path / 'out'}", "backend=openvino", "threads=1"])
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("precision auto: "))
    chosen = line.split()[2].rstrip(":")
    assert f"precision {'bf16' if chosen == 'bf16' else 'fp32'})" in out  # what ran is what was chosen
    if not has_bf16():
        assert chosen == "f32" and "bf16 not timed" in line
    net = load_denoiser(ckpt, torch.device("cpu"))
    frame = random_frame(1, 24, 32, seed=0)
    choice = faster_precision(net, frame, threads=1, warmup=1, repeats=2)
    assert choice.precision == min(choice.ms, key=lambda p: (choice.ms[p], p != "f32"))
    assert f"{choice.ms['f32']:.0f}" in choice.reason and "at 32x24 on 1 thread(s)" in choice.reason or \
        "bf16 not timed" in choice.reason


def test_auto_precision_is_openvino_only():
    from denoiser.commands.denoise import make_backend

    with pytest.raises(UserError, match="precision=auto: measures backend=openvino's f32 and bf16 only, not backend=eager"):
        make_backend("eager", "auto", torch.device("cpu"))


def test_a_resumed_auto_run_keeps_the_precision_it_chose(setup, tmp_path, capsys):
    """precision=auto writes its choice beside the frames; a resumed run reads it instead of timing
    again (a new measurement could choose the other precision, and the resumed frames would then
    not be those of an uninterrupted run)."""
    pytest.importorskip("openvino")
    import json

    _, seq, ckpt = setup
    out = tmp_path / "out"
    argv = [f"ckpt={ckpt}", f"input={seq}", f"output={out}", "backend=openvino", "threads=1"]
    denoise(argv)
    record = json.loads((out / "denoise_precision.json").read_text())
    assert record["precision"] in ("f32", "bf16") and set(record["ms"]) <= {"f32", "bf16"}
    record["precision"] = other = "bf16" if record["precision"] == "f32" else "f32"  # what a new timing might pick
    (out / "denoise_precision.json").write_text(json.dumps(record))
    for name in ("frame_0003.exr", "frame_0004.exr"):
        (out / name).unlink()
    capsys.readouterr()
    try:
        denoise(argv)
    except UserError as exc:  # bf16 recorded on a CPU without it: the backend says so
        assert other == "bf16" and "bf16" in str(exc)
        return
    printed = capsys.readouterr().out
    assert f"precision auto: {other}, as the run that wrote the frames" in printed
    assert f"precision {'bf16' if other == 'bf16' else 'fp32'})" in printed
