"""What the supervised and the distillation Lightning modules share.

* :func:`network_inputs` picks the network's inputs out of a batch (never the reference);
* :class:`DenoiserModule` builds the trained denoiser from its resolved net config (kept as
  attribute ``net``; the config is saved in the hyperparameters under ``net``, see
  docs/contracts.md), runs validation over whole sequences with
  :class:`denoiser.metrics.MetricAccumulator` (PSNR, SSIM, tPSNR, SMAPE; the first
  ``warmup_frames`` after a reset excluded; mean per sequence, then over sequences; under DDP
  each rank validates whole sequences and the per-sequence sums are gathered), logs
  image panels (noisy | output | reference, tonemapped) to TensorBoard every
  ``image_interval`` training steps and once per validation, and builds optimizers and
  schedulers from ``_partial_: true`` configs. Beside the network's ``val/psnr`` and the noisy
  input's ``val/input_psnr`` it logs ``val/oidn_fast_psnr``: OIDN-fast
  (:class:`~denoiser.methods.baselines.OidnDenoiser`) on the same frames, crops and warm-up, computed
  at the first validation of the run and cached (the val split does not change), so every run's
  curve shows where OIDN stands; without ``pyoidn`` one line says it is not logged.
"""

from __future__ import annotations

import functools
import inspect
import math
import sys
from collections.abc import Callable, Mapping
from typing import Any

import lightning.pytorch as pl
import torch
from hydra.utils import instantiate

from denoiser.buffers import NETWORK_INPUTS
from denoiser.checkpoint import current_targets
from denoiser.configs import build_net, plain
from denoiser.metrics import MetricAccumulator, combine_sequence_sums, tonemap

#: Metrics computed in validation (names of denoiser.metrics.METRICS); logged as ``val/<name>``.
VAL_METRICS = ("psnr", "ssim", "tpsnr", "smape")
#: the OIDN quality whose val PSNR is logged beside the network's, as ``val/oidn_<quality>_psnr``
VAL_OIDN_QUALITY = "fast"


def network_inputs(batch: Mapping[str, Any]) -> dict[str, torch.Tensor]:
    """The network inputs of a batch: ``color [B,T,3,H,W]``, ``albedo``, ``normal``, ``depth [B,T,1,H,W]``,
    ``motion [B,T,2,H,W]`` and, when present, ``samples [B,T,S,3,H,W]``."""
    return {k: batch[k] for k in NETWORK_INPUTS if k in batch}


def labeled_mask(batch: Mapping[str, Any]) -> torch.Tensor:
    """bool ``[B]``: True for items with a reference (``labeled`` flag; all False without ``reference``)."""
    b = batch["color"].shape[0]
    device = batch["color"].device
    if "reference" not in batch:
        return torch.zeros(b, dtype=torch.bool, device=device)
    if "labeled" in batch:
        return torch.as_tensor(batch["labeled"], device=device).bool().reshape(b)
    return torch.ones(b, dtype=torch.bool, device=device)


def gather_objects(obj: Any) -> list[Any]:
    """``[obj of rank 0, obj of rank 1, ...]`` (``torch.distributed.all_gather_object``); ``[obj]``
    in a single process. A collective: every rank must call it."""
    import torch.distributed as dist

    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return [obj]
    parts: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(parts, obj)
    return parts


def image_panel(*images: torch.Tensor) -> torch.Tensor:
    """Side-by-side tonemapped panel: each ``[3, H, W]`` linear HDR -> ``[3, H, n*W]`` in [0, 1]."""
    return torch.cat([tonemap(img.detach().float().cpu()) for img in images], dim=-1).clamp(0, 1)


class DenoiserModule(pl.LightningModule):
    """Base Lightning module holding ``net`` (a :class:`denoiser.nn.denoiser.Denoiser`).

    Subclasses implement ``training_step``. Arguments shared by both modules:

    * ``net``: resolved net config (dict with ``_target_``), instantiated here;
    * ``optimizer``: callable ``params -> torch.optim.Optimizer`` (a ``_partial_: true`` config);
    * ``scheduler``: callable ``optimizer -> LR scheduler`` or None, stepped every
      ``scheduler_interval`` (``step`` or ``epoch``);
    * ``detach_every``: truncated BPTT, the recurrent state is detached every k frames (0: never);
    * ``warmup_frames``: frames after a reset excluded from validation metrics;
    * ``image_interval``: training steps between image panels (0: never; validation panels
      are logged once per validation run regardless);
    * ``logit_penalty``: weight of the ``logit`` loss term, the mean square of the trained
      network's head outputs (:func:`denoiser.nn.denoiser.logit_energy`; 0: off). It keeps the
      scale of the activations from drifting up without bound (docs/training.md, "Collapse").
    * ``performance`` (docs/gpu.md): ``channels_last`` (the trained network's weights in NHWC
      memory format: cuDNN's fast layout under bf16), ``fused_optimizer`` (``fused=True`` for an
      optimizer that takes it, when its parameters are on CUDA: no effect on the CPU), ``compile``
      (null, or true or a dict of ``torch.compile`` arguments: the trained network's forward is
      compiled in place, ``nn.Module.compile``; the checkpoint's keys do not change).
    """

    def __init__(self, net: Mapping, optimizer: Callable | Mapping, scheduler: Callable | Mapping | None = None,
                 scheduler_interval: str = "step", detach_every: int = 0, warmup_frames: int = 2,
                 image_interval: int = 100, grad_clip: float = 0.0, logit_penalty: float = 0.0,
                 performance: Mapping | None = None):
        super().__init__()
        self.net = build_net(net, "model.net")
        performance = dict(performance or {})
        if performance.get("channels_last"):
            self.net = self.net.to(memory_format=torch.channels_last)
        if performance.get("compile"):
            options = performance["compile"]
            self.net.compile(**(dict(options) if isinstance(options, Mapping) else {}))
        self.fused_optimizer = bool(performance.get("fused_optimizer", False))
        self._optimizer_factory = self._factory(optimizer)
        self._scheduler_factory = self._factory(scheduler)
        self.scheduler_interval = scheduler_interval
        self.detach_every = int(detach_every)
        self.warmup_frames = int(warmup_frames)
        self.image_interval = int(image_interval)
        self.grad_clip = float(grad_clip or 0.0)
        self.logit_penalty = float(logit_penalty or 0.0)
        self.val_metrics = MetricAccumulator(VAL_METRICS, warmup=self.warmup_frames)
        self.val_input_metrics = MetricAccumulator(("psnr", "ssim"), warmup=self.warmup_frames)
        self.val_oidn_metrics = MetricAccumulator(("psnr",), warmup=self.warmup_frames)
        #: the val split's OIDN PSNR once computed (cached for the run); None before
        self.val_oidn_psnr: float | None = None
        self._oidn = None            # the OidnDenoiser, built at the first validation
        self._oidn_missing = False   # pyoidn not installed: said once, nothing logged
        #: global step of the last (non-sanity) validation, -1 before any
        self.validated_step = -1
        self._val_carry: tuple[list[str], dict] | None = None  # (sequence names, state) of the last val batch

    @staticmethod
    def _factory(cfg: Callable | Mapping | None) -> Callable | None:
        """A ``_partial_: true`` config (or an already built callable) -> callable, or None; a
        stored config's old ``_target_`` paths are mapped (:func:`denoiser.checkpoint.current_targets`)."""
        if cfg is None or callable(cfg):
            return cfg
        return instantiate(current_targets(plain(cfg)))

    # ----------------------------------------------------------------- running the net

    def run_net(self, net: torch.nn.Module, batch: Mapping[str, Any], detach_every: int = 0):
        """Unroll ``net`` over a window: -> ``(outputs [B,T,3,H,W], extras_list)`` (one extras dict per frame)."""
        outputs, _, extras = net(network_inputs(batch), state=None, reset=batch["reset"], detach_every=detach_every)
        return outputs, extras

    def logit_term(self, extras: list[dict]) -> torch.Tensor | None:
        """``logit_penalty`` times the mean over frames and items of the trained network's
        ``logit_energy`` (extras of :meth:`run_net`); None when off or the network has no heads."""
        if self.logit_penalty <= 0 or not extras or "logit_energy" not in extras[0]:
            return None
        return self.logit_penalty * torch.stack([e["logit_energy"] for e in extras]).mean()

    # ----------------------------------------------------------------- optimizers

    def clip_norm(self, optimizer) -> None:
        """Clip the gradient norm of ``optimizer``'s parameters to ``grad_clip`` (called from
        ``on_before_optimizer_step``, after the precision plugin has unscaled them). Lightning's
        plugin refuses any optimizer that unscales internally (a fused AdamW), even under bf16-mixed,
        which has no scaler: there nothing is scaled, and the norm is clipped directly."""
        scaler = getattr(self.trainer.precision_plugin, "scaler", None)
        if getattr(optimizer, "_step_supports_amp_scaling", False) and scaler is None:
            params = [p for group in optimizer.param_groups for p in group["params"] if p.grad is not None]
            torch.nn.utils.clip_grad_norm_(params, self.grad_clip)
        else:
            self.clip_gradients(optimizer, gradient_clip_val=self.grad_clip, gradient_clip_algorithm="norm")

    def build_optimizer(self, params, factory: Callable | None = None) -> dict:
        """``{"optimizer": .., "lr_scheduler": ..}`` for Lightning from the configured factories."""
        make = factory or self._optimizer_factory
        params = list(params)
        trainer = self._trainer  # under 16-mixed a fused optimizer's gradients cannot be clipped unscaled
        scaled = trainer is not None and getattr(trainer.precision_plugin, "scaler", None) is not None
        if self.fused_optimizer and not (scaled and self.grad_clip > 0) and params and \
                all(p.is_cuda for p in params) and \
                "fused" in inspect.signature(getattr(make, "func", make)).parameters:
            make = functools.partial(make, fused=True)
        opt = make(params)
        out: dict = {"optimizer": opt}
        if self._scheduler_factory is not None and factory is None:
            scheduler = self._scheduler_factory(opt)
            if hasattr(scheduler, "bind_progress"):  # e.g. denoiser.lit.schedule.ProgressCosineLR
                scheduler.bind_progress(self.training_progress)
            out["lr_scheduler"] = {"scheduler": scheduler, "interval": self.scheduler_interval}
        return out

    def training_progress(self) -> float:
        """Fraction of the training budget used: max of ``global_step / max_steps`` and
        ``elapsed / max_time`` (Lightning's Timer callback), in [0, 1]."""
        from lightning.pytorch.callbacks import Timer

        trainer = self._trainer
        if trainer is None:
            return 0.0
        fractions = []
        if trainer.max_steps and trainer.max_steps > 0:
            fractions.append(trainer.global_step / trainer.max_steps)
        for cb in trainer.callbacks:
            if isinstance(cb, Timer) and cb._duration:
                fractions.append(cb.time_elapsed("train") / cb._duration)
        return min(max(fractions, default=0.0), 1.0)

    # ----------------------------------------------------------------- images

    def log_panel(self, tag: str, noisy: torch.Tensor, output: torch.Tensor, reference: torch.Tensor | None) -> None:
        """Log ``noisy | output | reference`` (each ``[3, H, W]`` linear HDR) as one TensorBoard image."""
        experiment = getattr(self.logger, "experiment", None) if self.logger is not None else None
        if experiment is None or not hasattr(experiment, "add_image"):
            return
        images = [noisy, output] + ([reference] if reference is not None else [])
        experiment.add_image(tag, image_panel(*images), global_step=self.global_step)

    def maybe_log_train_panel(self, batch: Mapping[str, Any], outputs: torch.Tensor, target: torch.Tensor | None) -> None:
        """Every ``image_interval`` steps: panel of the last frame of the first item."""
        if self.image_interval <= 0 or self.global_step % self.image_interval != 0:
            return
        if self.trainer is not None and getattr(self.trainer, "sanity_checking", False):
            return
        ref = target[0, -1] if target is not None else None
        self.log_panel("train/panel", batch["color"][0, -1], outputs[0, -1], ref)

    # ----------------------------------------------------------------- validation

    def on_validation_epoch_start(self) -> None:
        self._val_carry = None
        self.val_metrics.reset()
        self.val_input_metrics.reset()
        self.val_oidn_metrics.reset()

    def oidn_for_validation(self, batch: Mapping[str, Any]):
        """The OIDN denoiser of the val baseline (built once, with albedo and normal when the batch has
        them); None when its PSNR is cached, in a sanity check, or without ``pyoidn`` (one line, once)."""
        if self.val_oidn_psnr is not None or self._oidn_missing or getattr(self.trainer, "sanity_checking", False):
            return None
        if self._oidn is None:
            try:
                from denoiser.methods.baselines import OidnDenoiser

                self._oidn = OidnDenoiser(VAL_OIDN_QUALITY, use_aux="albedo" in batch and "normal" in batch)
            except ImportError as exc:
                self._oidn_missing = True
                print(f"val/oidn_{VAL_OIDN_QUALITY}_psnr not logged: {exc.name or 'pyoidn'} is not installed "
                      "(pip install pyoidn)", file=sys.stderr)
                return None
        return self._oidn

    @torch.no_grad()
    def oidn_outputs(self, oidn, batch: Mapping[str, Any]) -> torch.Tensor:
        """OIDN on every frame of a val batch: ``[B, T, 3, H, W]`` from ``color``, ``albedo``, ``normal``
        ``[B, T, 3, H, W]`` (single frames: OIDN has no state)."""
        b, t = batch["color"].shape[:2]
        keys = ("color", "albedo", "normal") if oidn.use_aux else ("color",)
        frames = [[oidn({k: batch[k][i, j][None] for k in keys})[0] for j in range(t)] for i in range(b)]
        return torch.stack([torch.stack(f) for f in frames])

    def validation_step(self, batch: Mapping[str, Any], batch_idx: int) -> None:
        """Whole sequences, or their pieces in order (``data.val_window``, batch size 1: the state is
        carried from piece to piece unless the piece starts with a reset): metrics of the output and
        of the noisy input."""
        names = list(batch.get("sequence", [f"val/{batch_idx}_{i}" for i in range(batch["color"].shape[0])]))
        carried = self._val_carry[1] if self._val_carry is not None and self._val_carry[0] == names else None
        outputs, state, _ = self.net(network_inputs(batch), state=carried, reset=batch["reset"])
        self._val_carry = (names, state) if len(names) == 1 else None
        reference = batch["reference"]
        kwargs = {"frame_index": batch.get("frame_index"), "reset": batch["reset"]}
        self.val_metrics.update(outputs.float(), reference.float(), names, **kwargs)
        self.val_input_metrics.update(batch["color"].float(), reference.float(), names, **kwargs)
        oidn = self.oidn_for_validation(batch)
        if oidn is not None:
            self.val_oidn_metrics.update(self.oidn_outputs(oidn, batch).float(), reference.float(), names, **kwargs)
        if batch_idx == 0 and not getattr(self.trainer, "sanity_checking", False):
            t = outputs.shape[1] // 2
            self.log_panel("val/panel", batch["color"][0, t], outputs[0, t], reference[0, t])

    def on_validation_epoch_end(self) -> None:
        """Metrics over all processes' sequences (each process validated whole sequences, see
        :class:`denoiser.data.sampler.SequenceShardSampler`): per-sequence sums and counts are
        gathered, then averaged per sequence and over sequences, identically on every rank."""
        parts = gather_objects((self.val_metrics.sequence_sums(), self.val_input_metrics.sequence_sums(),
                                self.val_oidn_metrics.sequence_sums()))
        if not any(out or inp for out, inp, _ in parts):
            return
        values = {f"val/{k}": v for k, v in combine_sequence_sums([p[0] for p in parts], self.val_metrics.metrics).items()}
        values.update({f"val/input_{k}": v for k, v in
                       combine_sequence_sums([p[1] for p in parts], self.val_input_metrics.metrics).items()})
        if self.val_oidn_psnr is None and any(p[2] for p in parts):  # the first validation: cached from now on
            self.val_oidn_psnr = combine_sequence_sums([p[2] for p in parts], ("psnr",))["psnr"]
            if self._oidn is not None:
                self._oidn.close()
                self._oidn = None
        if self.val_oidn_psnr is not None:
            values[f"val/oidn_{VAL_OIDN_QUALITY}_psnr"] = self.val_oidn_psnr
        values = {k: float(v) for k, v in values.items() if not math.isnan(v)}  # drop NaN (e.g. tPSNR on 1-frame sequences)
        for k, v in values.items():  # the same values on every rank: sync_dist's mean leaves them unchanged
            self.log(k, v, prog_bar=k in ("val/psnr", "val/ssim"), sync_dist=True)
        if not getattr(self.trainer, "sanity_checking", False):
            self.validated_step = int(self.global_step)
