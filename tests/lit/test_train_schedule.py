"""ProgressCosineLR: cosine over steps, or over any bound progress (wall time); checkpointable."""

from __future__ import annotations

import math
import pickle

import pytest
import torch

from denoiser.lit.schedule import ProgressCosineLR


def make(total=100, final_ratio=0.01, warmup=0):
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    return opt, ProgressCosineLR(opt, total_steps=total, final_ratio=final_ratio, warmup_steps=warmup)


def test_cosine_over_steps_with_warmup():
    opt, sched = make(total=100, warmup=10)
    lrs = []
    for _ in range(100):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] == pytest.approx(0.1, rel=1e-3)  # warm-up: (0 + 1) / 10
    assert lrs[50] == pytest.approx(0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * 0.5)), rel=1e-6)
    assert opt.param_groups[0]["lr"] == pytest.approx(0.01)  # the end of the schedule


def test_bound_progress_wins_over_steps():
    opt, sched = make(total=1000)
    progress = {"p": 0.0}
    sched.bind_progress(lambda: progress["p"])
    progress["p"] = 1.0  # e.g. max_time is used up after a few steps
    opt.step()
    sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(0.01)
    # the state dict holds no reference to the progress function (nor to a Lightning module)
    state = sched.state_dict()
    pickle.dumps(state)
    _, fresh = make(total=1000)
    fresh.load_state_dict(state)
    assert fresh.last_epoch == sched.last_epoch and fresh.factor.progress is None


def test_state_dict_loads_with_weights_only(tmp_path):
    _, sched = make()
    torch.save(sched.state_dict(), tmp_path / "s.pt")
    assert torch.load(tmp_path / "s.pt", weights_only=True)["last_epoch"] == sched.last_epoch


def test_steps_only_schedule_ignores_the_time_progress():
    """follow_time=False (the demo): a used-up max_time does not move the LR; steps alone do."""
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=1.0)
    sched = ProgressCosineLR(opt, total_steps=100, final_ratio=0.01, follow_time=False)
    sched.bind_progress(lambda: 1.0)
    opt.step()
    sched.step()
    assert opt.param_groups[0]["lr"] == pytest.approx(0.01 + 0.99 * 0.5 * (1 + math.cos(math.pi * 0.01)))
    _, timed = make(total=100)
    timed.bind_progress(lambda: 1.0)
    timed.optimizer.step()
    timed.step()
    assert timed.optimizer.param_groups[0]["lr"] == pytest.approx(0.01)  # the control: time wins there
