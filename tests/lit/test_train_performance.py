"""Training performance options (model.performance, trainer=gpu; docs/gpu.md): the configs
compose, the defaults change nothing on the CPU, channels_last and compile act on the trained
network, and the fused optimizer is chosen on CUDA only."""

from __future__ import annotations

import pytest
import torch
from helpers.configs import compose_command

from denoiser.configs import instantiate_config
from denoiser.frames import random_frame

TINY = ["net=tiny", "kernel=student"]


def module(overrides):
    cfg = compose_command("train", ["experiment=demo", *TINY, *overrides])
    return cfg, instantiate_config(cfg.model, "model")


def window(frames=2, size=16):
    seq = [random_frame(2, size, size, seed=s, kind="hard") for s in range(frames)]
    return {k: torch.stack([f[k] for f in seq], dim=1) for k in seq[0]}


def test_gpu_trainer_composes_and_defaults_leave_the_cpu_run_unchanged():
    cfg, model = module(["trainer=gpu"])
    assert cfg.trainer.accelerator == "gpu" and cfg.trainer.precision == "bf16-mixed"
    assert dict(cfg.model.performance) == {"channels_last": False, "fused_optimizer": True, "compile": None}
    assert all(p.is_contiguous() for p in model.net.parameters())  # NCHW, as before the options
    assert model.net._compiled_call_impl is None
    optimizer = model.configure_optimizers()["optimizer"]
    assert not optimizer.defaults.get("fused")  # parameters on the CPU: not fused


@pytest.mark.slow  # dynamo traces the window's unroll: about 30 s on 2 cores
def test_channels_last_and_compile_keep_the_numbers():
    _, plain = module([])
    _, fast = module(["+model.performance.compile={backend: eager}", "model.performance.channels_last=true"])
    fast.net.load_state_dict(plain.net.state_dict())
    assert all(p.is_contiguous(memory_format=torch.channels_last) for p in fast.net.parameters() if p.dim() == 4)
    assert fast.net._compiled_call_impl is not None  # nn.Module.compile
    assert set(fast.net.state_dict()) == set(plain.net.state_dict())  # checkpoint keys unchanged
    with torch.no_grad():
        a, b = plain.net(window())[0], fast.net(window())[0]
    assert torch.allclose(a, b, rtol=1e-4, atol=1e-5)


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_fused_optimizer_on_cuda():
    _, model = module(["trainer=gpu"])
    model.net.cuda()
    assert model.configure_optimizers()["optimizer"].defaults["fused"] is True


def test_fused_optimizer_clips_under_bf16_mixed():
    """A fused AdamW with grad_clip under bf16-mixed: Lightning's precision plugin refuses to clip
    for an optimizer that unscales internally (a lent H200's training run stopped on it), though
    bf16 has no scaler. The norm is clipped directly, to grad_clip."""
    import lightning

    _, model = module(["model.grad_clip=1.0"])  # the distillation module clips through the same clip_norm
    model.trainer = lightning.Trainer(accelerator="cpu", precision="bf16-mixed", logger=False,
                                      enable_checkpointing=False, enable_progress_bar=False)
    params = list(model.net.parameters())
    optimizer = torch.optim.AdamW(params, lr=1e-3, fused=True)
    assert optimizer._step_supports_amp_scaling  # the case the plugin refuses
    (model.net(window())[0].square().mean() * 1e6).backward()
    assert torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in params if p.grad is not None])) > 10
    model.on_before_optimizer_step(optimizer)
    norm = torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in params if p.grad is not None]))
    assert norm == pytest.approx(1.0, rel=1e-3)
