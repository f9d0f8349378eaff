"""The CUDA backends (denoiser/inference/cuda_backend.py): on the CPU their logic (weights cast once,
channels-last, the state carried, static buffers with copy-in, the reset flag, one set of
buffers per frame size) against the eager float32 runner over a sequence with motion and a
camera cut; on a GPU (``-m gpu``) the same parity for fp16 and the CUDA graph replay."""

from __future__ import annotations

import pytest
import torch

from denoiser.configs import build_net, compose_net_config
from denoiser.frames import random_frame
from denoiser.inference.cuda_backend import (
    CudaBackend,
    CudaGraphBackend,
    StaticStep,
    cuda_event_times,
    device_report,
)
from denoiser.recurrent import RecurrentRunner

#: max |difference| / max |reference| per precision over the sequence (measured on the CPU:
#: fp32 3.7e-7, bf16 3.6e-3; fp16 has 3 more mantissa bits than bf16: its figure awaits a GPU run)
TOLERANCE = {"fp32": 1e-5, "bf16": 2e-2, "fp16": 1e-2}
RESETS = (True, False, False, True, False, False)  # a camera cut at frame 3


@pytest.fixture(scope="module")
def net():
    torch.manual_seed(0)
    net = build_net(compose_net_config("tiny", "student")).eval()
    with torch.no_grad():  # sharper, more varied kernels than an untrained head's
        for head in net.unet.heads:
            head.weight.mul_(8.0)
    return net


def sequence(height=24, width=40, device="cpu"):
    """Frames with motion up to a quarter of the frame, fireflies and sky (``kind=hard``)."""
    return [({k: v.to(device) for k, v in random_frame(1, height, width, seed=s, kind="hard").items()}, reset)
            for s, reset in enumerate(RESETS)]


def eager_outputs(net, frames):
    with torch.inference_mode():
        return [out.clone() for out in RecurrentRunner(net.step).run(frames)]


def run(stepper, frames):
    return [out.float().cpu() for out in RecurrentRunner(stepper.step).run(frames)]


def assert_parity(outputs, reference, precision):
    for out, ref in zip(outputs, reference):
        err = (out - ref).abs().max().item() / ref.abs().max().item()
        assert err <= TOLERANCE[precision], (precision, err)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_eager_cast_matches_fp32_runner_on_cpu(net, precision):
    frames = sequence()
    backend = CudaBackend(precision=precision, device="cpu")
    assert backend.available() is None and not backend.uses_triton()
    stepper = backend.prepare(net, frames[0][0], 1)
    assert_parity(run(stepper, frames), eager_outputs(net, frames), precision)
    assert next(net.parameters()).dtype == torch.float32  # the caller's network is untouched
    prepared = backend.prepare_net(net)
    weights = [p for p in prepared.parameters() if p.dim() == 4]
    assert all(p.dtype == backend_dtype(precision) for p in prepared.parameters())
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in weights)


def backend_dtype(precision):
    return {"fp32": torch.float32, "bf16": torch.bfloat16}[precision]


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_static_buffers_match_fp32_runner_on_cpu(net, precision):
    """Static state buffers and the reset flag give the eager runner's outputs, cut included."""
    frames = sequence()
    backend = CudaGraphBackend(precision=precision, device="cpu", compile=False, graph=False)
    assert backend.available() is None
    stepper = backend.prepare(net, frames[0][0], 1)
    assert_parity(run(stepper, frames), eager_outputs(net, frames), precision)


def test_static_step_copies_inputs_in_and_keeps_its_state_buffers(net):
    frames = sequence()
    backend = CudaGraphBackend(precision="fp32", device="cpu", compile=False, graph=False)
    prepared = backend.prepare_net(net)
    static = StaticStep(prepared, prepared.step, "cpu", graph=False)
    reference = eager_outputs(net, frames[:3])
    # one caller buffer reused for every frame, overwritten in place between steps
    buffer = {k: v.clone() for k, v in frames[0][0].items()}
    state, outputs = None, []
    for frame, _ in frames[:3]:
        for k, v in frame.items():
            buffer[k].copy_(v)
        out, new_state = static.step(buffer, state)
        assert state is None or new_state is state  # the same state buffers every step
        state = new_state
        outputs.append(out)
    slot = next(iter(static.slots.values()))
    assert all(slot.inputs[k].data_ptr() != buffer[k].data_ptr() for k in buffer)
    assert slot.state is state and set(state) == {"output", "color", "features", "guide"}
    assert_parity(outputs, reference, "fp32")
    # the first output was returned as a copy: later steps did not change it
    assert torch.equal(outputs[0], static.step(frames[0][0], None)[0])


def test_static_step_has_one_set_of_buffers_per_frame_size(net):
    small, large = sequence(16, 16), sequence(24, 40)
    frames = small[:3] + large[:3] + small[3:]  # every size change comes with a reset
    backend = CudaGraphBackend(precision="fp32", device="cpu", compile=False, graph=False)
    stepper = backend.prepare(net, frames[0][0], 1)
    assert_parity(run(stepper, frames), eager_outputs(net, frames), "fp32")


def test_options_are_checked():
    with pytest.raises(Exception, match="precision"):
        CudaBackend(precision="int8")
    with pytest.raises(Exception, match="reduce-overhead"):
        CudaGraphBackend(mode="reduce-overhead")
    assert "CUDA graphs" in CudaGraphBackend(device="cpu").available()
    if not torch.cuda.is_available():
        assert CudaBackend().available() == "no CUDA device"
    assert device_report()["torch"] == torch.__version__


# ----------------------------------------------------------------------------- on a GPU



@pytest.mark.parametrize("triton_filter", [False, "auto"])
@pytest.mark.parametrize("precision", ["fp16", "bf16"])
@pytest.mark.parametrize("kind", ["eager", "graph"])
@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cuda_matches_fp32_runner(net, kind, precision, triton_filter):
    frames = sequence(device="cuda")
    reference = [o.cpu() for o in eager_outputs(net.cuda(), frames)]
    net.cpu()
    cls = CudaBackend if kind == "eager" else CudaGraphBackend
    extra = {} if kind == "eager" else {"compile": False}
    backend = cls(precision=precision, triton_filter=triton_filter, **extra)
    assert backend.available() is None
    stepper = backend.prepare(net, frames[0][0], 1)
    outputs = [out.cpu() for out in RecurrentRunner(stepper.step).run(frames)]
    assert_parity(outputs, reference, "bf16" if precision == "bf16" else "fp16")
    if kind == "graph":
        slots = stepper.step.__self__.slots
        assert len(slots) == 1 and next(iter(slots.values())).graph is not None


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_compiled_graph_matches_and_times_with_events(net):
    frames = sequence(device="cuda")
    reference = [o.cpu() for o in eager_outputs(net.cuda(), frames)]
    net.cpu()
    stepper = CudaGraphBackend(precision="fp16").prepare(net, frames[0][0], 1)
    outputs = [out.cpu() for out in RecurrentRunner(stepper.step).run(frames)]
    assert_parity(outputs, reference, "fp16")
    times = cuda_event_times(stepper, [f for f, _ in frames], warmup=1, repeats=5)
    assert len(times) == 5 and all(t > 0 for t in times)
    assert device_report()["gpu"] != "none"


def test_denoise_command_offers_the_cuda_backends():
    from denoiser.commands.denoise import make_backend
    from denoiser.errors import UserError

    with pytest.raises(UserError, match="backend=cuda needs device=cuda"):
        make_backend("cuda", "fp16", torch.device("cpu"))
    with pytest.raises(UserError, match="precision=fp16 needs backend=cuda"):
        make_backend("eager", "fp16", torch.device("cpu"))
    if torch.cuda.is_available():
        _, backend = make_backend("cuda_compiled", "fp16", torch.device("cuda"))
        assert isinstance(backend, CudaGraphBackend) and backend.dtype == "fp16"
    else:
        with pytest.raises(UserError, match="backend=cuda_compiled precision=fp16: no CUDA device"):
            make_backend("cuda_compiled", "fp16", torch.device("cuda"))


def test_step_traffic_counts_what_a_step_must_move(net):
    from denoiser.buffers import CHANNELS, FRAME_INPUTS
    from denoiser.inference.cuda_backend import step_traffic

    h, w = 16, 24
    fp32 = step_traffic(net, h, w, "fp32", channels_last=False)
    weights = sum(p.numel() * 4 for p in net.parameters())
    state = sum(net.temporal.state_channels().values())
    inputs = sum(CHANNELS[k] for k in FRAME_INPUTS)
    assert fp32["weights"] == weights
    assert fp32["floor"] == weights + (inputs + 2 * state + 3) * h * w * 4
    assert fp32["ops"] > 10 * fp32["floor"]  # unfused: every operator reads and writes its tensors
    assert step_traffic(net, h, w, "fp16")["weights"] == weights // 2


def test_gpu_check_reports_the_device_and_stops_without_one(tmp_path):
    from helpers.configs import compose_command

    from denoiser.commands.tools.gpu_check import run

    if torch.cuda.is_available():
        pytest.skip("on a GPU the check runs for minutes: scripts/gpu_check.sh")
    result = run(compose_command("gpu_check", [f"out={tmp_path}"]))
    text = (tmp_path / "gpu.md").read_text()
    assert result["device"]["torch"] == torch.__version__ and f"torch: {torch.__version__}" in text
    assert "no CUDA device: nothing measured" in text


def test_gpu_check_training_step_reduces_the_per_item_loss_to_a_scalar_and_steps():
    """The device check's training step (run on the CPU here): DenoiseLoss's per-item terms [B] are
    averaged into one scalar, whose backward and AdamW step change the weights (a lent H200 once
    failed on `loss.backward()` of the [B] sum)."""
    from denoiser.commands.tools.gpu_check import train_step
    from denoiser.configs import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.lit.losses import DenoiseLoss

    torch.manual_seed(0)
    net = build_net(compose_net_config("tiny", "student")).train()
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
    seq = [random_frame(2, 16, 16, seed=i) for i in range(3)]
    window = {k: torch.stack([f[k] for f in seq], dim=1) for k in seq[0]}
    reset = torch.zeros(2, 3, dtype=torch.bool)
    reset[:, 0] = True
    before = [p.detach().clone() for p in net.parameters()]
    loss_fn = DenoiseLoss()
    loss = train_step(net, opt, loss_fn, window, window["color"] * 0.5, reset)()
    assert loss.dim() == 0 and torch.isfinite(loss)
    with torch.no_grad():
        outputs, _, _ = net(window, reset=reset)
    assert any(not torch.equal(a, p) for a, p in zip(before, net.parameters()))
    assert torch.isfinite(outputs).all()


def test_gpu_check_resumed_report_keeps_the_sections_it_does_not_set(tmp_path):
    from denoiser.commands.tools.gpu_check import Report

    first = Report(tmp_path / "gpu.md")
    first.set("Device", "- gpu: A")
    first.set("Inference", "| a |\n|---|\n| 1 |")
    first.set("Training step", "failed")
    second = Report(tmp_path / "gpu.md", keep=True)
    second.set("Training step", "| ms |\n|---|\n| 30 |")
    second.set("Training run", "exit 0")
    text, block = (tmp_path / "gpu.md").read_text().split("\n<!-- gpu:begin -->\n")
    assert text == ("# GPU check\n\n## Device\n\n- gpu: A\n\n## Inference\n\n| a |\n|---|\n| 1 |\n\n"
                    "## Training step\n\n| ms |\n|---|\n| 30 |\n\n## Training run\n\nexit 0\n")
    # the README block (make readme): the card, then the sections it repeats, kept across a resume
    assert block == ("gpu: A\n\n**Inference.**\n\n| a |\n|---|\n| 1 |\n\n**Training step.**\n\n| ms |\n|---|\n"
                     "| 30 |\n\n**Training run.** exit 0\n<!-- gpu:end -->\n")
    assert Report(tmp_path / "gpu.md", keep=True).sections == second.sections
    assert Report(tmp_path / "other.md", keep=True).sections == {}


def test_gpu_check_loader_rate_runs_past_one_epoch(tmp_path):
    """The data module's rate is timed over more batches than one epoch of a small carried subset
    holds (a lent H200's check stopped on StopIteration): the loader goes round again."""
    from helpers.eval_data import write_dataset

    from denoiser.commands.tools.gpu_check import loader_rate

    root = write_dataset(tmp_path, split="train", sequences=1, frames=4, size=32)
    overrides = ["experiment=demo", *["net=tiny", "kernel=student"], f"data.root={root}", "data.val_split=null",
                 "data.extra_share=null", "data.extra_roots=[]",
                 "data.window=2", "data.crop=16", "data.batch_size=1", "data.num_workers=0", "data.pin_memory=false"]
    assert loader_rate(overrides, batches=12) > 0


def test_gpu_check_evaluates_a_gpu_trained_checkpoint_on_this_cpu(tmp_path):
    """sections=[cpu_eval]: a checkpoint (trained on a lent GPU) evaluated where this runs, into the
    kept report, which keeps the sections of the lease; without eval_ckpt: one clear error."""
    from helpers.checkpoints import tiny_checkpoint
    from helpers.configs import compose_command
    from helpers.eval_data import write_dataset

    from denoiser.commands.tools.gpu_check import Report, run
    from denoiser.errors import ConfigError

    Report(tmp_path / "gpu.md").set("Device", "- gpu: NVIDIA H200")
    root = write_dataset(tmp_path / "demo", split="test", sequences=1, frames=3, size=32)
    ckpt = tiny_checkpoint(tmp_path / "gpu.ckpt")
    overrides = [f"out={tmp_path}", "sections=[cpu_eval]", "keep_report=true", f"data_root={root}",
                 f"eval.ledger={tmp_path / 'ledger.csv'}"]
    with pytest.raises(ConfigError, match="eval_ckpt"):
        run(compose_command("gpu_check", overrides))
    run(compose_command("gpu_check", [*overrides, f"eval_ckpt={ckpt}"]))
    report = Report(tmp_path / "gpu.md", keep=True).sections
    assert report["Device"] == "- gpu: NVIDIA H200\n"
    body = report["CPU evaluation of the GPU-trained checkpoint"]
    assert "`gpu.ckpt` on" in body and "split test" in body and "exit 0" in body
    assert "| gpu_student |" in body and "| noisy input |" in body and "##" not in body
    from denoiser.report import ledger

    (row,) = ledger.read(tmp_path / "ledger.csv")  # the look at the test split, with its purpose
    assert row["purpose"].startswith("make gpu-check") and row["checkpoints"] == "gpu.ckpt"
    assert (tmp_path / "eval" / ".hydra" / "overrides.yaml").is_file()  # Hydra's record beside the metrics


def test_gpu_check_training_run_trains_from_the_checkout(tmp_path):
    """The training-run section runs the checkout's ``train.py`` (a tiny run on the CPU here) into
    <out>/train: a checkpoint, exit 0, the data module's rate. The module's path to the checkout
    once pointed into the package (``denoiser/train.py``, absent) after a move of the module."""
    from helpers.configs import compose_command
    from helpers.eval_data import write_dataset

    from denoiser.commands.tools.gpu_check import ROOT, Report, code_commit, train_run

    assert (ROOT / "train.py").is_file() and (ROOT / "pyproject.toml").is_file()
    root = write_dataset(tmp_path / "demo", split="train", sequences=1, frames=4, size=32)
    overrides = ["experiment=demo", "net=tiny", "kernel=student", "threads=1", "trainer.max_steps=2",
                 "trainer.enable_progress_bar=false", "callbacks.progress=null", "model.image_interval=0",
                 "data.extra_share=null", "data.extra_roots=[]", "data.window=2", "data.crop=16",
                 "data.batch_size=1", "data.num_workers=0", "data.pin_memory=false"]
    cfg = compose_command("gpu_check", [f"out={tmp_path}", "train_run.loader_batches=2"])
    cfg.train_run.overrides = overrides
    report = Report(tmp_path / "gpu.md")
    ckpt = train_run(cfg, root, tmp_path, [], report)
    body = report.sections["Training run"]
    assert ckpt == tmp_path / "train" / "checkpoints" / "last.ckpt" and ckpt.is_file(), body
    assert "exit 0" in body and "frames/s delivered" in body, body
    assert code_commit() not in ("", "unknown")  # this checkout's git commit
