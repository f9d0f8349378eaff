"""A network between two checkpoints of the same network: ``python -m denoiser.commands.tools.interpolate``.

Usage::

    python -m denoiser.commands.tools.interpolate start=reports/demo/runs/student_distilled_s0 \\
        end=<its fine-tune's run>/checkpoints/last.ckpt alpha=0.5 out=mid.ckpt

A Hydra app over ``conf/interpolate.yaml``: writes ``out``, the weights ``(1 - alpha) * start +
alpha * end`` (:func:`denoiser.checkpoint.interpolate_checkpoints`), a checkpoint every command
loads (``denoiser-eval ckpt=mid.ckpt``). ``end`` is ``start``'s fine-tune (a training run with
``model.init_ckpt=<start>``, docs/training.md); where the fine-tune trades one kind of data for
another (issue 33 fine-tuned make demo's students on fast-moving objects: docs/results_log.md),
``alpha`` walks the line between the two and is chosen on val. No pipeline runs it. A user mistake
(a missing file, two networks, alpha outside [0, 1]) is one error line and exit code 2.
"""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from denoiser.checkpoint import TRUST_KEY, interpolate_checkpoints


def run(cfg: DictConfig) -> Path:
    """Write ``cfg.out``; returns its path."""
    path = interpolate_checkpoints(cfg.start, cfg.end, cfg.alpha, cfg.out, trust=bool(cfg.get(TRUST_KEY, False)))
    print(f"{path}: alpha {float(cfg.alpha):g} between {cfg.start} (0) and {cfg.end} (1)")
    return path


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "interpolate")()


if __name__ == "__main__":
    main()
