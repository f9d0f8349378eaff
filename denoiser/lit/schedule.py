"""Learning-rate schedule that follows the training *progress*, in steps or in wall time.

``lr(p) = lr0 * (final_ratio + (1 - final_ratio) * 0.5 * (1 + cos(pi * min(p, 1))))`` after a
linear warm-up over ``warmup_steps`` steps, where the progress ``p`` in [0, 1] is the larger of
``global_step / trainer.max_steps`` and ``elapsed / trainer.max_time``. A CPU run bounded by
``max_time`` therefore anneals to the end of its time budget whatever the machine's speed;
without a time limit, or with ``follow_time=False`` (the demo: ``max_time`` is only a safety
cap there, so the result does not depend on the machine's load), it is a plain cosine over
``max_steps``.

The module binds the progress function (:meth:`ProgressCosineLR.bind_progress`) when it builds
the scheduler; unbound, progress is ``step / total_steps``.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch.optim.lr_scheduler import LambdaLR


class _Factor:
    """Picklable LR factor ``step -> multiplier`` (see the module docstring)."""

    def __init__(self, total_steps: int, final_ratio: float, warmup_steps: int):
        self.total_steps = max(int(total_steps), 1)
        self.final_ratio = float(final_ratio)
        self.warmup_steps = int(warmup_steps)
        self.progress: Callable[[], float] | None = None

    def __call__(self, step: int) -> float:
        p = self.progress() if self.progress is not None else step / self.total_steps
        p = min(max(p, 0.0), 1.0)
        factor = self.final_ratio + (1.0 - self.final_ratio) * 0.5 * (1.0 + math.cos(math.pi * p))
        if self.warmup_steps > 0 and step < self.warmup_steps:
            factor *= (step + 1) / self.warmup_steps
        return factor

    def __getstate__(self):  # the bound progress function belongs to the running trainer
        return {k: v for k, v in self.__dict__.items() if k != "progress"}

    def __setstate__(self, state):
        self.__dict__.update(state, progress=None)


class ProgressCosineLR(LambdaLR):
    """Cosine decay to ``final_ratio * lr`` over the training progress (steps or wall time)."""

    def __init__(self, optimizer: torch.optim.Optimizer, total_steps: int = 1000, final_ratio: float = 0.01,
                 warmup_steps: int = 0, follow_time: bool = True):
        self.factor = _Factor(total_steps, final_ratio, warmup_steps)
        self.follow_time = bool(follow_time)
        super().__init__(optimizer, lr_lambda=self.factor)

    def bind_progress(self, progress: Callable[[], float]) -> None:
        """Use ``progress() -> [0, 1]`` (e.g. the trainer's step and time fractions) from now on;
        ignored with ``follow_time=False`` (the schedule then follows ``step / total_steps`` only)."""
        if self.follow_time:
            self.factor.progress = progress

    def state_dict(self) -> dict:
        """Plain values only (checkpoints load with ``weights_only=True``): the factor's settings come
        from the config, its progress from the trainer."""
        state = {k: v for k, v in super().state_dict().items() if k != "factor"}
        state["lr_lambdas"] = [None]
        return state

    def load_state_dict(self, state_dict: dict) -> None:
        state = dict(state_dict)
        state.pop("lr_lambdas", None)
        self.__dict__.update({k: v for k, v in state.items() if k != "factor"})
