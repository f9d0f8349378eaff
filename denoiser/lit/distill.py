"""Distillation: a frozen teacher teaches the student on the same recurrent windows.

The teacher is loaded from ``teacher_ckpt`` with :func:`denoiser.checkpoint.load_denoiser`
(safe loader; ``trust_teacher_ckpt=True`` also loads a teacher holding pickled objects) (frozen: eval mode, ``requires_grad=False``, run under ``torch.no_grad``) and unrolled over the
same window as the student (same resets; the student's state is detached every
``detach_every`` frames). Loss terms, each with a weight in ``loss`` (a term whose weight is 0
is not computed, not logged and absent from :meth:`DistillationModule.loss_terms`):

* ``kd_*`` (``loss.kd_weight``): pixel-level distillation, the student output against the
  teacher output on *every* frame of *every* item (labeled or not), with the terms of
  ``loss.kd`` (:class:`denoiser.lit.losses.DenoiseLoss`: SMAPE, gradient, and the temporal term
  on warped consecutive frames);
* ``gt_*`` (``loss.gt_weight``): the same kind of terms (``loss.gt``) against the reference on
  items that have one (batch ``labeled`` flag). Unlabeled sequences (data ``use_unlabeled``)
  therefore learn from the teacher's output alone;
* ``feature`` (``loss.feature_weight``): feature distillation, mean over the paired U-Net
  levels and frames of :func:`denoiser.lit.losses.feature_loss` between 1x1-adapted student maps
  (:class:`denoiser.lit.adapters.FeatureAdapters`, trained with the student) and teacher maps;
* ``adversarial`` (``loss.adversarial_weight``): image-level term, the generator loss of a
  patch critic (``critic``, e.g. :class:`denoiser.nn.critic.PatchCritic`) that learns to tell
  the student's outputs from the teacher's (both log-compressed, ``log1p(max(x, 0))``, frames
  flattened to ``[B*T, 3, H, W]``). The objective (``adversarial``: hinge or WGAN-GP) is a
  ``_target_`` config. The critic has its own optimizer (``critic_optimizer``) and takes
  ``critic_steps`` steps per student step (manual optimization). Its steps go through
  Lightning's strategy and precision plugin (under ``16-mixed``: unscaled, skipped on
  non-finite gradients) but do not advance ``global_step``, which counts student steps only
  (so ``max_steps`` and resuming mean the same as in supervised training). ``grad_clip``
  clips the student's gradients after unscaling (``on_before_optimizer_step``).

``param_transfer`` (a ``_target_`` config such as :class:`denoiser.lit.transfer.L1ChannelTransfer`,
or null) initializes the student from the teacher's weights before training. ``init_ckpt`` (a
checkpoint of the student's own architecture, or null) starts it from that checkpoint's weights
instead: fine-tuning a trained student under another teacher or data (the critic, the feature
adapters, the optimizer and the schedule start afresh). The two are exclusive.

The teacher is loaded only when a term or the transfer needs it (``no_kd`` trains the student
on references alone, without a teacher).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import torch
from torch import nn

from denoiser.checkpoint import load_denoiser, load_weights
from denoiser.configs import plain
from denoiser.errors import ConfigError
from denoiser.lit.adapters import FeatureAdapters
from denoiser.lit.common import DenoiserModule, labeled_mask
from denoiser.lit.losses import feature_loss, log_compress, masked_mean

DEFAULT_LOSS = {"kd_weight": 1.0, "gt_weight": 1.0, "feature_weight": 0.0, "adversarial_weight": 0.0,
                "kd": {"_target_": "denoiser.lit.losses.DenoiseLoss"}, "gt": {"_target_": "denoiser.lit.losses.DenoiseLoss"}}


def _no_closure() -> None:
    """The closure of a manual-optimization step: the backward pass already ran."""


class DistillationModule(DenoiserModule):
    """Lightning module distilling a frozen ``teacher`` into ``net``. See the module docstring.

    Attributes (docs/contracts.md): ``net`` (student), ``teacher`` (frozen, or None when no term
    needs it), ``critic`` (or None without adversarial term), ``adapters`` (or None),
    ``critic_updates`` (number of critic optimizer steps taken, for tests and logs).
    """

    def __init__(self, net: Mapping, optimizer: Callable | Mapping, teacher_ckpt: str | None = None,
                 loss: Mapping | None = None, critic: Mapping | None = None,
                 critic_optimizer: Callable | Mapping | None = None, adversarial: Mapping | None = None,
                 critic_steps: int = 1, param_transfer: Mapping | None = None,
                 scheduler: Callable | Mapping | None = None, scheduler_interval: str = "step",
                 detach_every: int = 0, warmup_frames: int = 2, image_interval: int = 100, grad_clip: float = 0.0,
                 trust_teacher_ckpt: bool = False, logit_penalty: float = 0.0, performance: Mapping | None = None,
                 init_ckpt: str | None = None):
        super().__init__(net, optimizer, scheduler, scheduler_interval, detach_every, warmup_frames,
                         image_interval, grad_clip, logit_penalty, performance)
        if init_ckpt and param_transfer:
            raise ConfigError("model.init_ckpt and model.param_transfer: give one (init_ckpt starts the student "
                              "from a checkpoint, param_transfer from the teacher; set model.param_transfer=null)")
        self.automatic_optimization = False
        loss_cfg = {**DEFAULT_LOSS, **(plain(loss) or {})}
        self.save_hyperparameters({
            "net": plain(net), "optimizer": plain(optimizer), "teacher_ckpt": teacher_ckpt, "loss": loss_cfg,
            "critic": plain(critic), "critic_optimizer": plain(critic_optimizer),
            "adversarial": plain(adversarial), "critic_steps": critic_steps, "param_transfer": plain(param_transfer),
            "scheduler": plain(scheduler), "scheduler_interval": scheduler_interval, "detach_every": detach_every,
            "warmup_frames": warmup_frames, "image_interval": image_interval, "grad_clip": grad_clip,
            "logit_penalty": logit_penalty, "init_ckpt": init_ckpt,
        })
        self.weights = {k: float(loss_cfg[f"{k}_weight"]) for k in ("kd", "gt", "feature", "adversarial")}
        self.kd_loss = self._factory(loss_cfg["kd"])
        self.gt_loss = self._factory(loss_cfg["gt"])
        self.critic_steps = int(critic_steps)
        self.critic_updates = 0

        needs_teacher = any(self.weights[k] > 0 for k in ("kd", "feature", "adversarial")) or param_transfer
        self.teacher: nn.Module | None = None
        if needs_teacher:
            if not teacher_ckpt:
                raise ConfigError("model.teacher_ckpt: distillation needs a teacher checkpoint "
                                  "(e.g. model.teacher_ckpt=outputs/.../checkpoints/last.ckpt)")
            self.teacher = load_denoiser(teacher_ckpt, trust=trust_teacher_ckpt, trust_key="model.trust_teacher_ckpt")
            self.teacher.requires_grad_(False)
            self.teacher.eval()
        if param_transfer and self.teacher is not None:
            self._factory(param_transfer)(self.teacher, self.net)
        if init_ckpt:
            load_weights(self.net, init_ckpt)

        self.adapters = FeatureAdapters.between(self.net, self.teacher) if self.weights["feature"] > 0 else None
        self.critic: nn.Module | None = None
        self.adversarial = None
        self._critic_optimizer_factory = None
        if self.weights["adversarial"] > 0:
            if critic is None or adversarial is None or critic_optimizer is None:
                raise ConfigError("model.critic / model.adversarial / model.critic_optimizer: all needed when "
                                  "model.loss.adversarial_weight > 0")
            self._critic_cfg = plain(critic)  # built in configure_model (see there)
            self.adversarial = self._factory(adversarial)
            self._critic_optimizer_factory = self._factory(critic_optimizer)

    def configure_model(self) -> None:
        """Build the critic here, in the process that trains: its spectral-norm parametrizations
        cannot be pickled, which DDP's spawn start method would need. Runs before checkpoint restore."""
        if self.weights["adversarial"] > 0 and self.critic is None:
            self.critic = self._factory(self._critic_cfg)

    def train(self, mode: bool = True):
        """Switch modes, keeping the teacher in eval mode whatever Lightning asks."""
        super().train(mode)
        if self.teacher is not None:
            self.teacher.eval()
        return self

    # ----------------------------------------------------------------- losses

    def run_teacher(self, batch: Mapping[str, Any]) -> tuple[torch.Tensor, list[dict]]:
        """Frozen teacher over the window: ``(outputs [B, T, 3, H, W], extras per frame)``."""
        with torch.no_grad():
            return self.run_net(self.teacher, batch)

    def loss_terms(self, batch: Mapping[str, Any], student: torch.Tensor, s_extras: list[dict],
                   teacher: torch.Tensor | None, t_extras: list[dict] | None) -> dict[str, torch.Tensor]:
        """Weighted scalar terms of the student objective (only terms with weight > 0).

        ``student, teacher: [B, T, 3, H, W]`` linear HDR; extras: per-frame dicts with ``features``.
        """
        terms: dict[str, torch.Tensor] = {}
        motion, reset = batch["motion"], batch["reset"]
        if self.weights["kd"] > 0:
            for k, v in self.kd_loss(student, teacher, motion, reset).items():
                terms[f"kd_{k}"] = self.weights["kd"] * v.mean()
        mask = labeled_mask(batch)
        if self.weights["gt"] > 0 and bool(mask.any()):
            for k, v in self.gt_loss(student, batch["reference"], motion, reset).items():
                terms[f"gt_{k}"] = self.weights["gt"] * masked_mean(v, mask)
        if self.weights["feature"] > 0 and len(self.adapters.levels) > 0:
            values = []
            for se, te in zip(s_extras, t_extras):
                adapted = self.adapters(se["features"])
                values += [feature_loss(a, te["features"][i]) for a, i in zip(adapted, self.adapters.levels)]
            terms["feature"] = self.weights["feature"] * torch.stack(values).mean()
        if self.weights["adversarial"] > 0:
            self.critic.requires_grad_(False)
            fake = log_compress(student).flatten(0, 1)
            terms["adversarial"] = self.weights["adversarial"] * self.adversarial.generator_loss(self.critic, fake)
            self.critic.requires_grad_(True)
        logit = self.logit_term(s_extras)
        if logit is not None:
            terms["logit"] = logit
        if not terms:  # e.g. no_kd on a batch of unlabeled items: nothing to learn, keep the graph
            terms["none"] = student.sum() * 0.0
        return terms

    def critic_update(self, student: torch.Tensor, teacher: torch.Tensor, optimizer) -> torch.Tensor:
        """``critic_steps`` critic steps (teacher outputs real, student outputs fake); returns the last loss."""
        real = log_compress(teacher).flatten(0, 1)
        fake = log_compress(student.detach()).flatten(0, 1)
        loss = torch.zeros((), device=student.device)
        for _ in range(self.critic_steps):
            loss = self.adversarial.critic_loss(self.critic, real, fake)
            optimizer.zero_grad()
            self.manual_backward(loss)  # scaled by the precision plugin's GradScaler under 16-mixed
            # Stepped through the strategy and its precision plugin (under 16-mixed: unscale, skip the
            # step on non-finite gradients, update the scale), not through LightningOptimizer.step(),
            # which would also count an optimizer step: global_step counts student steps only.
            self.trainer.strategy.optimizer_step(optimizer.optimizer, closure=_no_closure, model=self)
            self.critic_updates += 1
        return loss.detach()

    # ----------------------------------------------------------------- training

    def training_step(self, batch: Mapping[str, Any], batch_idx: int) -> torch.Tensor:
        optimizers = self.optimizers()
        optimizers = optimizers if isinstance(optimizers, list) else [optimizers]
        opt_student = optimizers[0]
        b = batch["color"].shape[0]
        student, s_extras = self.run_net(self.net, batch, detach_every=self.detach_every)
        teacher, t_extras = self.run_teacher(batch) if self.teacher is not None else (None, None)
        if self.critic is not None:
            self.log("train/critic_loss", self.critic_update(student, teacher, optimizers[1]), batch_size=b)
        terms = self.loss_terms(batch, student, s_extras, teacher, t_extras)
        loss = torch.stack(list(terms.values())).sum()
        opt_student.zero_grad()
        self.manual_backward(loss)
        opt_student.step()  # clipping: on_before_optimizer_step, after the precision plugin unscaled
        scheduler = self.lr_schedulers()
        if scheduler is not None and self.scheduler_interval == "step":
            scheduler.step()
        self.log("train/loss", loss.detach(), prog_bar=True, batch_size=b)
        for k, v in terms.items():
            self.log(f"train/loss_{k}", v.detach(), batch_size=b)
        target = batch.get("reference") if bool(labeled_mask(batch)[0]) else teacher
        self.maybe_log_train_panel(batch, student, target)
        return loss.detach()

    def on_before_optimizer_step(self, optimizer) -> None:
        """Clip the student's gradients (``grad_clip``; the critic is not clipped). Lightning calls
        this inside the optimizer step, after the precision plugin has unscaled the gradients
        (clipping before ``step()`` would clip the scaled gradients under 16-mixed)."""
        if self.grad_clip > 0 and (self.critic is None or optimizer is self._student_optimizer()):
            self.clip_norm(optimizer)

    def _student_optimizer(self):
        optimizers = self.optimizers(use_pl_optimizer=False)
        return optimizers[0] if isinstance(optimizers, list) else optimizers

    def on_train_epoch_end(self) -> None:
        scheduler = self.lr_schedulers()
        if scheduler is not None and self.scheduler_interval == "epoch":
            scheduler.step()

    def configure_optimizers(self):
        params = list(self.net.parameters()) + (list(self.adapters.parameters()) if self.adapters is not None else [])
        student = self.build_optimizer(params)
        if self.critic is None:
            return student
        return [student, {"optimizer": self._critic_optimizer_factory(self.critic.parameters())}]
