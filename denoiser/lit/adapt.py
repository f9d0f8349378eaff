"""Render-aware adaptation (issue 67): a student tuned to one animation from its noisy frames alone.

The teacher labels the user's frames (no reference is read): :class:`~denoiser.lit.distill.DistillationModule`
distils it into the student, which starts from the student checkpoint's weights (``init_ckpt``), on
windows cut from the given frames, mixed with a share of the release training windows (with their
references) so that the student does not forget. Lightning's ``Trainer`` runs ``max_steps`` steps.

* :func:`split_frames`: the frames ``[0, train)`` give training windows (random crops), the last
  ``heldout`` frames the held-out check; neither ever spans the other.
* :func:`own_windows`: the training windows, random ``crop`` x ``crop`` crops (1080p frames stay
  memory-bounded: a batch is ``[B, window, C, crop, crop]`` whatever the frame size).
* :func:`heldout_items`: the held-out frames at fixed crop positions (at most ``crops`` of them,
  spread over the frame): items ``{buffer: [1, T, C, crop, crop], reset: [1, T]}``.
* :func:`teacher_gap`: the reference-free measure, the mean PSNR (dB, :func:`denoiser.metrics.psnr`)
  of the student's output against the teacher's on the held-out items; higher is closer.
* :func:`adapt`: the whole run; if the adapted student's gap is worse than the start student's it
  keeps the start student's weights (safe by construction). The result is written atomically
  (:func:`denoiser.checkpoint.save_checkpoint`), in the checkpoint format ``denoiser-denoise ckpt=`` takes.

Resuming: the trainer writes ``<run_dir>/checkpoints/last.ckpt`` (atomically, every
``checkpoint_every`` steps and at the end); a run asked again with ``ckpt_path`` that file goes on
from it. Nothing under the result's name exists until the final write.
"""

from __future__ import annotations

import copy
import json
import math
import os
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import ConcatDataset, DataLoader

from denoiser.buffers import FRAME_INPUTS
from denoiser.data.collate import collate_items
from denoiser.data.dataset import WindowDataset, index_split
from denoiser.data.layouts.base import Layout, SequenceSource
from denoiser.data.sampler import ShareSampler
from denoiser.errors import ConfigError, UserError

#: the file the adapted (or kept) student goes to, and the record beside it
RESULT = "student.ckpt"
RECORD = "adapt.json"


def split_frames(frames: int, window: int, heldout_share: float) -> tuple[int, int]:
    """``(train, heldout)`` frame counts of a ``frames``-long sequence: the last
    ``max(window, round(frames * heldout_share))`` frames are held out, the others give windows of
    ``window`` frames. UserError when fewer than ``2 * window`` frames leave no room for both."""
    heldout = max(int(window), round(frames * float(heldout_share)))
    train = frames - heldout
    if train < window:
        raise UserError(f"{frames} frame(s): adaptation needs at least {2 * window} (windows of {window} to train "
                        f"on, the last {heldout} held out for the check); give more frames or a smaller window=")
    return train, heldout


def crop_size(source: SequenceSource, crop: int) -> tuple[int, int]:
    """The ``(h, w)`` crop of ``source``'s frames: ``crop`` each way, the frame's size where smaller."""
    return min(int(crop), source.height), min(int(crop), source.width)


def own_windows(source: SequenceSource, layout: Layout, window: int, train_frames: int, crop: tuple[int, int],
                fill_reference: bool) -> WindowDataset:
    """Training windows of frames ``[0, train_frames)`` of ``source`` (no reference read; with
    ``fill_reference`` a zero ``reference`` and ``labeled`` False, to batch with labeled windows).
    UserError naming the folder when a buffer the networks need is missing."""
    ds = WindowDataset([source], layout, FRAME_INPUTS, window, crop=list(crop), labeled=False,
                       fill_reference=fill_reference)
    ds.windows = [(i, t) for i, t in ds.windows if t + window <= train_frames]
    return ds


def heldout_items(reader: WindowDataset, source: SequenceSource, start: int, crop: tuple[int, int],
                  crops: int = 4) -> list[dict]:
    """Frames ``start ..`` (to the end) of ``source`` at up to ``crops`` fixed crop positions (a grid
    over the frame, corners first), read by ``reader`` (:func:`own_windows`'s dataset): batched
    items ``{buffer: [1, T, C, h, w], reset: bool [1, T]}``."""
    h, w = crop
    tops = sorted({0, source.height - h, (source.height - h) // 2})
    lefts = sorted({0, source.width - w, (source.width - w) // 2})
    positions = [(t, l) for t in (tops[0], tops[-1]) for l in (lefts[0], lefts[-1])]
    positions += [(t, l) for t in tops for l in lefts if (t, l) not in positions]
    seen: list[tuple[int, int]] = []
    for p in positions:
        if p not in seen:
            seen.append(p)
    items = []
    for top, left in seen[:max(1, int(crops))]:
        item = reader.load(source, start, source.frames - start, (top, left, h, w))
        items.append(collate_items([item]))
    return items


def teacher_gap(module, items: list[dict]) -> float:
    """Mean PSNR (dB) of ``module.net``'s output against ``module.teacher``'s over every frame of
    ``items`` (:func:`heldout_items`); NaN when an output is not finite."""
    from denoiser.metrics import psnr

    was_training = module.net.training
    module.net.eval()
    values = []
    try:
        with torch.no_grad():
            for item in items:
                student, _ = module.run_net(module.net, item)
                teacher, _ = module.run_teacher(item)
                if not (bool(torch.isfinite(student).all()) and bool(torch.isfinite(teacher).all())):
                    return float("nan")
                values.append(psnr(student.flatten(0, 1), teacher.flatten(0, 1)))
    finally:
        module.net.train(was_training)
    return float(torch.cat(values).mean())


def mix_windows(root: str | os.PathLike, layout: Layout, window: int, crop: tuple[int, int]) -> WindowDataset:
    """The labeled training windows of ``<root>/train`` (with references), cropped like the own windows."""
    sources = index_split(layout, root, "train")
    return WindowDataset(sources, layout, FRAME_INPUTS, window, crop=list(crop), labeled=True, fill_reference=True)


def train_loader(own: WindowDataset, mix: WindowDataset | None, share: float, batch_size: int) -> DataLoader:
    """Shuffled batches of ``own`` windows, ``share`` of them drawn from ``mix`` instead
    (:class:`~denoiser.data.sampler.ShareSampler`); an epoch is as long as ``own`` (at least one batch)."""
    length = max(len(own), batch_size)
    if mix is None or share <= 0:
        dataset, groups, shares = own, [list(range(len(own)))], [1.0]
    else:
        dataset = ConcatDataset([own, mix])
        groups = [list(range(len(own))), list(range(len(own), len(own) + len(mix)))]
        shares = [1.0 - share, share]
        length = round(length / (1.0 - share)) if share < 1 else length
    return DataLoader(dataset, batch_size=batch_size, sampler=ShareSampler(groups, shares, length),
                      collate_fn=collate_items)


def student_config(student: str | os.PathLike, trust: bool = False) -> dict:
    """The resolved net config stored in the student checkpoint (``release:student`` or a file)."""
    from denoiser.checkpoint import net_config, read_checkpoint, resolve_checkpoint

    path = resolve_checkpoint(student)
    return net_config(read_checkpoint(path, "cpu", trust=trust), path)


def adapt(source: SequenceSource, layout: Layout, out: str | os.PathLike, *, student: str, teacher: str,
          steps: int, optimizer: Mapping, trainer: Mapping, loss: Mapping | None = None, window: int = 4,
          crop: int = 96, batch_size: int = 2, heldout_share: float = 0.25, heldout_crops: int = 4,
          mix: float = 0.0, mix_root: str | None = None, mix_layout: Layout | None = None,
          checkpoint_every: int = 50, resume: bool = True, trust: bool = False,
          log=print) -> dict[str, Any]:
    """Adapt ``student`` toward ``teacher`` on ``source``'s frames; returns the record written to
    ``<out>/adapt.json`` (gaps before and after in dB, which weights were kept, the sizes used).

    ``optimizer``: a partial optimizer config (``_target_``, ``_partial_``); ``trainer``: the
    Lightning Trainer config (its ``max_steps`` is ``steps``); ``resume``: go on from
    ``<out>/run/checkpoints/last.ckpt`` when it exists (``ckpt_path=auto`` of ``denoiser-train``). ``mix``: share of the batches' windows drawn from ``<mix_root>/train``.
    """
    from lightning.pytorch.callbacks import ModelCheckpoint

    from denoiser.atomic import atomic_write_text, remove_stale_temporaries
    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import instantiate_config
    from denoiser.lit.distill import DistillationModule

    if int(steps) < 1:
        raise ConfigError(f"steps: must be >= 1, got {steps}")
    if not 0.0 <= float(mix) < 1.0:
        raise ConfigError(f"mix: the share of release training windows, in [0, 1), got {mix}")
    out, started = Path(out), time.perf_counter()
    train_frames, heldout = split_frames(source.frames, window, heldout_share)
    hw = crop_size(source, crop)
    own = own_windows(source, layout, window, train_frames, hw, fill_reference=mix > 0)
    mixed = mix_windows(mix_root, mix_layout or layout, window, hw) if mix > 0 else None
    loader = train_loader(own, mixed, float(mix), int(batch_size))
    items = heldout_items(own, source, train_frames, hw, heldout_crops)

    net_cfg = student_config(student, trust)
    module = DistillationModule(net=net_cfg, optimizer=dict(optimizer), teacher_ckpt=str(teacher),
                                loss={"kd_weight": 1.0, "gt_weight": 1.0, "feature_weight": 0.0,
                                      "adversarial_weight": 0.0, **dict(loss or {})},
                                init_ckpt=str(student), trust_teacher_ckpt=trust, image_interval=0,
                                logit_penalty=0.0)
    start_state = copy.deepcopy(module.net.state_dict())
    before = teacher_gap(module, items)
    log(f"teacher-student gap before: {before:.2f} dB (student vs teacher PSNR on {len(items)} held-out crop(s) "
        f"{hw[1]}x{hw[0]} of the last {heldout} frame(s); higher is closer)")

    run_dir = out / "run"
    for stale in remove_stale_temporaries(run_dir / "checkpoints"):  # left by a killed write
        log(f"removed {stale} (a checkpoint write that was killed)")
    last = run_dir / "checkpoints" / "last.ckpt"
    resume_from = str(last) if resume and last.is_file() else None
    if resume_from:
        print(f"resuming from {resume_from}", file=sys.stderr)
    ckpt = ModelCheckpoint(dirpath=run_dir / "checkpoints", save_last=True, save_top_k=0,
                           every_n_train_steps=max(1, int(checkpoint_every)))
    fit = instantiate_config({**dict(trainer), "max_steps": int(steps), "default_root_dir": str(run_dir)},
                             "trainer", callbacks=[ckpt])
    fit.fit(module, train_dataloaders=loader, ckpt_path=resume_from)
    if fit.interrupted:
        raise UserError(f"{run_dir / 'checkpoints' / 'last.ckpt'}: adaptation interrupted at step {fit.global_step}; "
                        f"run the same command again to go on from there (no {RESULT} written)")
    after = teacher_gap(module, items)
    kept = "adapted" if math.isfinite(after) and after >= before else "start"
    log(f"teacher-student gap after {fit.global_step} step(s): {after:.2f} dB ({after - before:+.2f} dB)")
    if kept == "start":
        log(f"the adapted student is further from the teacher than the start student ({after:.2f} < {before:.2f} dB): "
            f"kept the start student's weights in {out / RESULT}")
        module.net.load_state_dict(start_state)
    save_checkpoint(out / RESULT, module.net, net_cfg)
    record = {"gap_before_db": before, "gap_after_db": after, "kept": kept, "steps": int(fit.global_step),
              "frames": source.frames, "train_frames": train_frames, "heldout_frames": heldout,
              "heldout_crops": len(items), "crop": list(hw), "window": int(window), "batch_size": int(batch_size),
              "train_windows": len(own), "mix": float(mix), "mix_root": str(mix_root) if mix > 0 else None,
              "student": str(student), "teacher": str(teacher), "seconds": time.perf_counter() - started,
              "size": [source.height, source.width]}
    atomic_write_text(out / RECORD, json.dumps(record, indent=1) + "\n")
    return record


__all__ = ["RECORD", "RESULT", "adapt", "crop_size", "heldout_items", "mix_windows", "own_windows", "split_frames",
           "student_config", "teacher_gap", "train_loader"]
