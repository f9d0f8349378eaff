"""``denoiser-eval``: quality of trained checkpoints and of the baselines on the test sequences.

::

    denoiser-eval ckpt=[runs/a.ckpt,runs/b.ckpt] data=demo purpose=report
    denoiser-eval 'ckpt={teacher: t.ckpt, student: s.ckpt}' out_dir=eval/ purpose=report  # names from a dict
    denoiser-eval ckpt=s.ckpt split=val '~baselines.oidn_balanced' metrics=[psnr,ssim] max_frames=8

A split named ``test`` needs ``purpose=``; each look at one is a row of the test ledger (``ledger=``;
by default :func:`denoiser.report.ledger.default_ledger`: the project's tracked
``docs/results/test_ledger.csv`` for its own datasets, ``<data.root>/test_ledger.csv`` for a user's).

Config: ``conf/eval.yaml`` (composes the groups ``data``: root and test split, ``layout``, and
``baselines``). Methods: the baselines of ``baselines`` (``conf/baselines/default.yaml``, Hydra
``_target_`` entries: the noisy input and OIDN fast/balanced/high, see :mod:`denoiser.methods.baselines`)
followed by the checkpoints, in the order given. Every method sees the same frames; networks
run recurrently over each whole sequence in order (state carried, reset at the first frame and
at camera cuts).

Frames stream from disk one at a time (memory does not grow with sequence length); the
reference is read once more beforehand when FLIP is requested, to fix the sequence's FLIP
exposure range from all its reference frames.

Outputs in ``out_dir``:

* ``metrics.csv`` - one row per method and sequence (scene, kept frames, metrics, ms per
  frame of this run) plus one ``sequence=mean`` row per method (mean over sequences); beside
  ``psnr`` (frames kept after the warm-up), ``psnr_all`` (every frame) and ``psnr_f2``: PSNR over
  frames 2+ of each sequence (1-based: every frame but the first, warm-up or not;
  :data:`denoiser.metrics.FRAME_SUBSETS`);
* ``frames.csv`` - one row per method and frame (warm-up frames flagged);
* ``metrics.md`` - the overall table (methods x metrics), the per-scene table and the
  per-sequence table;
* ``images/<split>_<sequence>.png`` - tonemapped crops side by side (methods, then the
  reference) of one frame per sequence;
* ``evaluation.json`` - its provenance (:func:`denoiser.report.ledger.provenance`): the commit it ran
  at, the UTC date, the data root, the split and its SHA-256, and for a test split the look it
  recorded in the test ledger (the summaries name this commit and look);
* ``exr/<method>/<split>/<sequence>/frame_XXXX.exr`` - denoised frames (``save_exr=true``).
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections import OrderedDict
from pathlib import Path

import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from denoiser.atomic import atomic_write_text, remove_stale_temporaries
from denoiser.checkpoint import checkpoint_paths, load_denoiser
from denoiser.data.evalset import open_test_split
from denoiser.errors import ConfigError
from denoiser.methods.baselines import NetworkMethod, build_baselines
from denoiser.metrics import METRICS
from denoiser.report import ledger
from denoiser.report.evaluation import METRIC_FORMATS, METRIC_HEADERS, Evaluation, markdown_report
from denoiser.report.plot_crops import save_crops
from denoiser.report.provenance import git_commit, tree_hash
from denoiser.tables import markdown_table, write_csv

log = logging.getLogger(__name__)



# ----------------------------------------------------------------------------- configuration


def build_methods(cfg: DictConfig, device: str = "cpu") -> OrderedDict[str, object]:
    """Baselines (instantiated from ``cfg.baselines``) then checkpoints: ``{label: method}``."""
    methods = build_baselines(cfg.get("baselines"))
    for name, path in checkpoint_paths(cfg.get("ckpt")).items():
        if name in methods:
            raise ConfigError(f"ckpt: name {name!r} is already used by a baseline")
        methods[name] = NetworkMethod(load_denoiser(path, device, trust=bool(cfg.get("trust_checkpoint"))),
                                      label=name, device=device)
    if not methods:
        raise ConfigError("eval: nothing to evaluate (no ckpt and no baselines)")
    return methods


def set_threads(threads: int | None) -> int:
    """Set torch's intra-op threads (when given); returns the count in use (OIDN gets the same)."""
    if threads:
        torch.set_num_threads(int(threads))
    return torch.get_num_threads()


# ----------------------------------------------------------------------------- data


# ----------------------------------------------------------------------------- evaluation


def run(cfg: DictConfig) -> dict:
    """The ``denoiser-eval`` task; returns ``{label: overall metrics}``."""
    metrics = [str(m) for m in cfg.metrics]
    unknown = [m for m in metrics if m not in METRICS]
    if unknown:
        raise ConfigError(f"metrics: unknown {unknown}; known: {list(METRICS)}")
    looked = ledger.is_test_split(cfg.split)
    if looked and not str(cfg.get("purpose") or "").strip():
        where = cfg.get("ledger") or ledger.default_ledger(cfg.data.root)
        raise ConfigError(f"split={cfg.split}: purpose= is required. Every look at a test split is a row of the test "
                          f"ledger ({ledger.named(where)}); say why, e.g. "
                          "purpose='final judgement of recipe X', 'report' or 'debug'")
    commit = git_commit()  # the code that evaluates, taken before it runs
    threads = set_threads(cfg.get("threads"))
    out_dir = Path(cfg.out_dir)
    for stale in remove_stale_temporaries(out_dir, partial_dirs=".eval-*.partial"):  # left by a killed run
        log.warning("removed %s (left by an evaluation that was killed)", stale)
    _, sources, dataset = open_test_split(cfg.data, cfg.split, cfg.get("sequences"))
    methods = build_methods(cfg, cfg.get("device", "cpu"))
    if any(getattr(m, "uses_samples", False) for m in methods.values()):  # ONND: per-sample radiance too
        _, sources, dataset = open_test_split(cfg.data, cfg.split, cfg.get("sequences"), samples=True)
    max_frames = cfg.get("max_frames")
    lengths = [min(s.frames, int(max_frames)) if max_frames else s.frames for s in sources]
    ev = Evaluation(methods, metrics, int(cfg.warmup))
    # images and EXRs go to a staging directory first and move into out_dir only when every
    # sequence succeeded: a bad frame in a later sequence leaves no partial output behind
    staging = out_dir / f".eval-{os.getpid()}.partial"
    exr_dir = staging / "exr" if cfg.get("save_exr") else None
    try:
        with tqdm(total=sum(lengths), desc="eval", unit="frame") as progress:
            for source, frames in zip(sources, lengths):
                progress.set_postfix_str(source.name)
                image_frame = _image_frame(cfg.images, frames)
                panels = ev.run_sequence(dataset, source, frames, image_frame, cfg.images, exr_dir, progress)
                if panels is not None:
                    top, left, h, w = panels["box"]
                    save_crops(staging / "images" / f"{source.name.replace('/', '_')}.png", panels["panels"],
                               panels["notes"], title=f"{source.name} frame {image_frame}, crop {w}x{h} at "
                               f"(x={left}, y={top}); PSNR of the whole frame")
        # the outputs are replaced from here on: the provenance of the ones before goes first, and the
        # new one is written last (a run killed in between leaves none: a summary says so)
        (out_dir / ledger.PROVENANCE).unlink(missing_ok=True)
        _move_tree(staging, out_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    date, digest = ledger.utc_now(), tree_hash(Path(cfg.data.root) / cfg.split)
    drawn = ledger.split_ids(Path(cfg.data.root) / cfg.split)
    look_line, look, where = "", None, None
    if looked:  # after a complete evaluation: the look happened
        where = cfg.get("ledger") or ledger.default_ledger(cfg.data.root)
        named = checkpoint_paths(cfg.get("ckpt"))
        checkpoints = [ledger.run_id(p) for p in named.values()]
        baselines = [name for name in methods if name not in named]
        look = ledger.record(str(cfg.data.root), str(cfg.split), digest, len(sources), checkpoints, baselines,
                             commit, str(cfg.purpose).strip(), where, date=date, split_id=drawn)
        look_line = ledger.look_sentence(look, digest, where, drawn)
        print(look_line)
    rows = ev.sequence_rows()
    write_csv(out_dir / "metrics.csv", rows, ["method", "scene", "sequence", "frames", *ev.columns, "ms_per_frame"])
    write_csv(out_dir / "frames.csv", ev.frame_rows(), ["method", "sequence", "frame", "warmup", *ev.metrics])
    header = (f"# Evaluation on {Path(cfg.data.root) / cfg.split}\n\n{len(sources)} sequence(s), "
              f"warm-up {cfg.warmup} frame(s) excluded after each reset, {threads} thread(s). Metrics: "
              "PSNR/SSIM/tPSNR on ACES+sRGB tonemapped frames, HDR-FLIP with a per-sequence exposure range, "
              "relMSE and SMAPE on linear HDR; warp err: the flicker without a reference (Lai et al.'s warping error "
              "along the frames' motion, pixels visible in both frames; its reference's value is the floor that "
              "shading changes alone give) (see denoiser/metrics.py). \"all frames\": warm-up included; "
              "\"frames 2+\": every frame of a sequence but its first (frames counted from 1), warm-up or not.\n\n"
              + (look_line + "\n\n" if look_line else ""))
    atomic_write_text(out_dir / "metrics.md", markdown_report(ev, rows, header))
    provenance = ledger.provenance(commit, date, str(cfg.data.root), str(cfg.split), digest, len(sources), look, where,
                                   drawn)
    atomic_write_text(out_dir / ledger.PROVENANCE, json.dumps(provenance, indent=2) + "\n")
    overall = {r["method"]: {m: r[m] for m in ev.columns} for r in rows if r["sequence"] == "mean"}
    print(markdown_table([r for r in rows if r["sequence"] == "mean"], ["method", *ev.columns, "ms_per_frame"],
                         METRIC_FORMATS, METRIC_HEADERS))
    print(f"wrote {out_dir / 'metrics.csv'}, {out_dir / 'metrics.md'}, {out_dir / ledger.PROVENANCE} and "
          f"{out_dir / 'images'}")
    return overall


def _move_tree(src: Path, dest: Path) -> None:
    """Move every file under ``src`` to the same relative path under ``dest`` (replacing files)."""
    for path in sorted(src.rglob("*")):
        if path.is_file():
            target = dest / path.relative_to(src)
            target.parent.mkdir(parents=True, exist_ok=True)
            os.replace(path, target)


def _image_frame(images_cfg, frames: int) -> int | None:
    """Index of the frame shown as crops (negative counts from the end); None when disabled."""
    if images_cfg is None or images_cfg.get("frame") is None:
        return None
    idx = int(images_cfg.frame)
    idx = idx + frames if idx < 0 else idx
    return min(max(idx, 0), frames - 1)


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "eval")()


if __name__ == "__main__":
    main()
