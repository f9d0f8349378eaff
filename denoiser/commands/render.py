"""``denoiser-render``: render scenes into the native sequence layout (Hydra app, ``conf/render.yaml``).

One scene::

    denoiser-render scene=cornell split=train sequences=2 frames=8 spp=4 ref_spp=256 width=128 height=128

A render preset (``conf/render_set/*.yaml``, its jobs under ``render_set.jobs``) renders several
scenes and splits in one command::

    denoiser-render render_set=demo         # -> data/demo/{train,val,test,unlabeled}/<scene>_<k>/

Output root: ``root`` (default ``data/<name>``, ``name`` = the preset's name or ``default``).
Resumable: finished frames are skipped. Scenes marked ``test_only`` are refused for the
train/val/unlabeled splits unless ``allow_test_only=true``. A preset describes its splits whole:
a sequence in one of them that the preset does not list (e.g. a test seed retired by a new
``first_sequence``) stops the render with one line naming it.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from denoiser.commands.app import hydra_command
from denoiser.errors import ConfigError
from denoiser.render.build import scene_dict
from denoiser.render.catalog import load_scene_config
from denoiser.render.job import RenderSettings, render_sequence
from denoiser.render.seeds import sequence_seed
from denoiser.render.spec import build_scene

SPLITS = ("train", "val", "test", "unlabeled")
JOB_KEYS = {"split", "scenes", "sequences", "frames", "spp", "ref_spp", "width", "height", "save_samples",
            "first_sequence", "aux"}


@dataclass
class SequenceJob:
    """One sequence to render."""

    split: str
    scene_config: Any
    index: int
    settings: RenderSettings

    @property
    def scene_name(self) -> str:
        return str(self.scene_config.get("name"))

    @property
    def directory(self) -> str:
        return f"{self.split}/{self.scene_name}_{self.index:03d}"


def _settings(cfg: DictConfig, job: dict, split: str) -> RenderSettings:
    def get(key):
        return job[key] if key in job else cfg[key]

    values = {k: get(k) for k in ("frames", "spp", "ref_spp", "width", "height")}
    for k, v in values.items():
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ConfigError(f"render: key '{k}' must be a positive integer, got {v!r}")
    return RenderSettings(**values, labeled=split != "unlabeled", save_samples=bool(get("save_samples")),
                          half=bool(cfg.half), aux=str(get("aux")))  # RenderSettings checks aux


def plan(cfg: DictConfig) -> list[SequenceJob]:
    """Expand the config (one scene, or the jobs of ``render_set``) into sequences to render."""
    if cfg.get("render_set"):
        jobs = [OmegaConf.to_container(j, resolve=True) for j in cfg.render_set.jobs]
    else:
        jobs = [{"split": cfg.split, "scenes": [cfg.scene]}]
    out: list[SequenceJob] = []
    for i, job in enumerate(jobs):
        unknown = set(job) - JOB_KEYS
        if unknown:
            raise ConfigError(f"render_set.jobs[{i}]: unknown key(s) {', '.join(sorted(unknown))}")
        split = job.get("split", cfg.split)
        if split not in SPLITS:
            raise ConfigError(f"render: key 'split' must be one of {', '.join(SPLITS)}, got {split!r}")
        settings = _settings(cfg, job, split)
        first = int(job.get("first_sequence", cfg.first_sequence))
        for scene in job.get("scenes", []):
            scene_cfg = load_scene_config(scene) if isinstance(scene, str) else scene
            if scene_cfg.get("test_only", False) and split != "test" and not cfg.allow_test_only:
                raise ConfigError(f"scene '{scene_cfg.get('name')}' is test_only and cannot be rendered into split "
                                  f"'{split}' (set allow_test_only=true to override)")
            for k in range(int(job.get("sequences", cfg.sequences))):
                out.append(SequenceJob(split, scene_cfg, first + k, settings))
    return out


def check_no_stale_sequences(root: Path, jobs: list[SequenceJob], preset: str) -> None:
    """A preset describes its splits whole: a sequence directory (one with a ``sequence.json``)
    in a split the preset renders, but not among its ``jobs``, is left from an older version of
    the preset (a retired test seed, a removed scene) or was added by hand, and training and
    evaluation would read it as part of the split. Raises :class:`ConfigError` naming the first."""
    planned = {j.directory for j in jobs}
    for split in sorted({j.split for j in jobs}):
        for meta in sorted((root / split).glob("*/sequence.json")):
            directory = f"{split}/{meta.parent.name}"
            if directory not in planned:
                raise ConfigError(f"{root / directory}: a sequence that render_set={preset} does not describe (retired by "
                                  f"a change of the preset, or added by hand); move it out of {root / split}, or "
                                  "training and evaluation read it as part of the split")


def run(cfg: DictConfig) -> None:
    """Render everything ``cfg`` asks for, with one progress bar over all frames."""
    from denoiser.render.variant import activate

    jobs = plan(cfg)
    root = Path(cfg.root)
    if cfg.get("render_set"):
        check_no_stale_sequences(root, jobs, cfg.name)
    # Build every scene first: configuration mistakes surface before any rendering.
    specs = [build_scene(j.scene_config, sequence_seed(cfg.seed, j.scene_name, j.split, j.index)) for j in jobs]
    mi = activate(cfg.variant)
    for spec in specs:  # materials, textures, lights and shapes are checked by building them once
        scene_dict(mi, spec, 0.0, 8, 8)
    total = sum(j.settings.frames for j in jobs)
    skipped = 0
    with tqdm(total=total, unit="frame", desc="render", dynamic_ncols=True) as bar:
        for job, spec in zip(jobs, specs):
            bar.set_postfix_str(job.directory)

            def on_frame(t: int, was_done: bool) -> None:
                nonlocal skipped
                skipped += was_done
                bar.update(1)

            donor = Path(cfg.reference_from) / job.directory if cfg.get("reference_from") else None
            render_sequence(mi, spec, root / job.directory, job.settings,
                            sequence_seed(cfg.seed, job.scene_name, job.split, job.index),
                            overwrite=bool(cfg.overwrite), on_frame=on_frame, reference_from=donor)
    print(f"rendered {total - skipped} frame(s), skipped {skipped} finished, {len(jobs)} sequence(s) in {root}",
          file=sys.stderr)


main = hydra_command(run, "render")


if __name__ == "__main__":
    main()
