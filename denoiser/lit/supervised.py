"""Supervised training of one denoiser (the teacher or the student, chosen by ``net=``).

Truncated backpropagation through time: each batch is a window of ``T`` consecutive frames
(``T`` is the data config's window length); the network is unrolled over the window from an
empty history (``reset`` is True on the window's first frame) and the recurrent state is
detached every ``detach_every`` frames (model config; 0 = backpropagate through the whole
window). The loss (:class:`denoiser.lit.losses.DenoiseLoss`, weights in config) is taken on every
frame of the window against the reference; unlabeled items (``labeled`` False) are masked out.

Logged: ``train/loss`` and ``train/loss_<term>`` (weighted terms), validation metrics
(``val/psnr``, ``val/ssim``, ``val/tpsnr``, ``val/smape`` and the noisy input's
``val/input_psnr``/``val/input_ssim``), image panels (see :mod:`denoiser.lit.common`).

``init_ckpt`` (a checkpoint of the same architecture, or null) starts the network from that
checkpoint's weights instead of a random draw: fine-tuning (the optimizer, the schedule and the
step count start afresh; a resumed run's own checkpoint then replaces these weights).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch

from denoiser.checkpoint import load_weights
from denoiser.configs import plain
from denoiser.lit.common import DenoiserModule, labeled_mask
from denoiser.lit.losses import DenoiseLoss, masked_mean


class SupervisedModule(DenoiserModule):
    """Lightning module: ``net`` trained on references. See the module docstring.

    ``loss``: a :class:`DenoiseLoss` or its config (``_target_``). Other arguments: see
    :class:`denoiser.lit.common.DenoiserModule`.
    """

    def __init__(self, net: Mapping, loss: Mapping | DenoiseLoss, optimizer: Callable | Mapping,
                 scheduler: Callable | Mapping | None = None, scheduler_interval: str = "step",
                 detach_every: int = 0, warmup_frames: int = 2, image_interval: int = 100, grad_clip: float = 0.0,
                 logit_penalty: float = 0.0, performance: Mapping | None = None, init_ckpt: str | None = None):
        super().__init__(net, optimizer, scheduler, scheduler_interval, detach_every, warmup_frames,
                         image_interval, grad_clip, logit_penalty, performance)
        if init_ckpt:
            load_weights(self.net, init_ckpt)
        self.save_hyperparameters({
            "net": plain(net), "loss": plain(loss) if not callable(loss) else repr(loss),
            "optimizer": plain(optimizer) if not callable(optimizer) else repr(optimizer),
            "scheduler": plain(scheduler) if not callable(scheduler) else repr(scheduler),
            "scheduler_interval": scheduler_interval, "detach_every": detach_every,
            "warmup_frames": warmup_frames, "image_interval": image_interval, "grad_clip": grad_clip,
            "logit_penalty": logit_penalty, "init_ckpt": init_ckpt,
        })
        self.loss = self._factory(loss) if not isinstance(loss, DenoiseLoss) else loss

    def forward(self, batch: Mapping[str, Any]) -> torch.Tensor:
        """Denoise a window: batch -> outputs ``[B, T, 3, H, W]`` linear HDR."""
        return self.run_net(self.net, batch)[0]

    def loss_terms(self, batch: Mapping[str, Any], outputs: torch.Tensor) -> dict[str, torch.Tensor]:
        """Weighted scalar loss terms over the labeled items of the batch."""
        mask = labeled_mask(batch)
        if "reference" not in batch or not bool(mask.any()):
            return {"smape": outputs.sum() * 0.0}  # nothing to learn from; keeps the graph connected
        terms = self.loss(outputs, batch["reference"], batch["motion"], batch["reset"])
        return {k: masked_mean(v, mask) for k, v in terms.items()}

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        outputs, extras = self.run_net(self.net, batch, detach_every=self.detach_every)
        terms = self.loss_terms(batch, outputs)
        logit = self.logit_term(extras)
        if logit is not None:
            terms["logit"] = logit
        loss = torch.stack(list(terms.values())).sum()
        b = outputs.shape[0]
        self.log("train/loss", loss, prog_bar=True, batch_size=b)
        for k, v in terms.items():
            self.log(f"train/loss_{k}", v, batch_size=b)
        self.maybe_log_train_panel(batch, outputs, batch.get("reference"))
        return loss

    def on_before_optimizer_step(self, optimizer) -> None:
        if self.grad_clip > 0:
            self.clip_norm(optimizer)

    def configure_optimizers(self):
        return self.build_optimizer(self.net.parameters())
