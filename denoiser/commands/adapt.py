"""``denoiser-adapt``: the student adapted to one animation from its noisy frames (issue 67).

::

    denoiser-adapt input=renders/shot1 layout=blender out=adapted/shot1
    denoiser-adapt input=shot1 out=adapted student=release:student teacher=release:teacher steps=300 mix=0.25
    denoiser-denoise ckpt=adapted/shot1/student.ckpt input=renders/shot1 layout=blender output=denoised/shot1

The teacher's output on the given frames is the target (no reference is read): windows of
``window`` frames, ``crop`` x ``crop`` crops, from all but the last frames, mixed with ``mix`` of
release training windows (``mix_root``), for ``steps`` Lightning steps
(:func:`denoiser.lit.adapt.adapt`). Before and after, the teacher-student gap on the held-out last
frames (student vs teacher PSNR) is printed and written to ``<out>/adapt.json``; if adapting made
it worse the start student's weights are the result. ``<out>/student.ckpt`` is written atomically
at the end; an interrupted run goes on from ``<out>/run/checkpoints/last.ckpt`` when asked again.

Bad input (no frames, a pass the networks need missing, too few frames): one line, exit 2, no
checkpoint.
"""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from denoiser.errors import ConfigError, UserError

#: ``mix=null``'s share when the release training data is there
DEFAULT_MIX = 0.25


def mix_share(cfg: DictConfig) -> float:
    """``mix`` as given, or :data:`DEFAULT_MIX` when null and ``<mix_root>/train`` exists, else 0
    (one line says so); a positive ``mix`` without that folder is an error."""
    root = Path(str(cfg.mix_root)) / "train"
    if cfg.get("mix") is None:
        if root.is_dir():
            return DEFAULT_MIX
        print(f"denoiser-adapt: no release training windows at {root}: mix=0 (the student may drift toward this "
              "shot only; give mix_root=<release data root> to mix them in)", file=sys.stderr)
        return 0.0
    mix = float(cfg.mix)
    if mix > 0 and not root.is_dir():
        raise ConfigError(f"mix={mix:g}: {root} does not exist (mix_root=<release data root>, or mix=0)")
    return mix


def run(cfg: DictConfig) -> dict:
    """The ``denoiser-adapt`` task; returns the record of ``<out>/adapt.json``."""
    import lightning.pytorch as pl
    import torch

    from denoiser.configs import instantiate_config, load_layout
    from denoiser.lit.adapt import adapt

    for key in ("input", "out"):
        if not cfg.get(key):
            raise ConfigError(f"{key}: required (denoiser-adapt input=<noisy frames> out=<dir>)")
    src, out = Path(cfg.input), Path(cfg.out)
    if not src.is_dir():
        raise UserError(f"{src}: not a directory (input=<a folder of one sequence's noisy frames>)")
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    pl.seed_everything(int(cfg.seed), verbose=False)
    layout = instantiate_config(cfg.layout, "layout")
    source = layout.open_sequence(src)
    if source.frames < 1:
        raise UserError(f"{src}: no frames")
    mix = mix_share(cfg)
    record = adapt(source, layout, out, student=str(cfg.student), teacher=str(cfg.teacher), steps=int(cfg.steps),
                   optimizer=OmegaConf.to_container(cfg.optimizer, resolve=True),
                   trainer=OmegaConf.to_container(cfg.trainer, resolve=True),
                   loss=OmegaConf.to_container(cfg.loss, resolve=True) if cfg.get("loss") else None,
                   window=int(cfg.window), crop=int(cfg.crop), batch_size=int(cfg.batch_size),
                   heldout_share=float(cfg.heldout_share), heldout_crops=int(cfg.heldout_crops), mix=mix,
                   mix_root=str(cfg.mix_root), mix_layout=load_layout(str(cfg.mix_layout)) if mix > 0 else None,
                   checkpoint_every=int(cfg.checkpoint_every), resume=bool(cfg.get("resume", True)),
                   trust=bool(cfg.get("trust_checkpoint")))
    print(f"wrote {out / 'student.ckpt'} ({record['kept']} student) and {out / 'adapt.json'} in "
          f"{record['seconds']:.0f} s; denoise with: denoiser-denoise ckpt={out / 'student.ckpt'} input={src} "
          "output=<dir>")
    return record


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "adapt")()


if __name__ == "__main__":
    main()
