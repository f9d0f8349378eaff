"""``denoiser-eval``: quality of trained checkpoints and of the baselines on the test sequences.

::

    denoiser-eval ckpt=[runs/a.ckpt,runs/b.ckpt] data=demo
    denoiser-eval 'ckpt={teacher: t.ckpt, student: s.ckpt}' out_dir=eval/  # names from a dict
    denoiser-eval ckpt=s.ckpt '~baselines.oidn_balanced' metrics=[psnr,ssim] max_frames=8

Config: ``conf/eval.yaml`` (composes the ``data`` group: root, layout, test split).
Methods: the baselines of ``baselines`` (Hydra ``_target_`` entries: the noisy input and
OIDN fast/balanced/high, see :mod:`denoiser.baselines`) followed by the checkpoints, in the
order given. Every method sees the same frames; networks run recurrently over each whole
sequence in order (state carried, reset at the first frame and at camera cuts).

Frames stream from disk one at a time (memory does not grow with sequence length); the
reference is read once more beforehand when FLIP is requested, to fix the sequence's FLIP
exposure range from all its reference frames.

Outputs in ``out_dir``:

* ``metrics.csv`` - one row per method and sequence (scene, kept frames, metrics, ms per
  frame of this run) plus one ``sequence=mean`` row per method (mean over sequences);
* ``frames.csv`` - one row per method and frame (warm-up frames flagged);
* ``metrics.md`` - the overall table (methods x metrics), the per-scene table and the
  per-sequence table;
* ``images/<split>_<sequence>.png`` - tonemapped crops side by side (methods, then the
  reference) of one frame per sequence;
* ``exr/<method>/<split>/<sequence>/frame_XXXX.exr`` - denoised frames (``save_exr=true``).
"""

from __future__ import annotations

import logging
import math
import os
import shutil
import time
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path

import torch
from omegaconf import DictConfig, ListConfig, OmegaConf
from tqdm.auto import tqdm

from denoiser.baselines import NetworkMethod
from denoiser.checkpoint import load_denoiser
from denoiser.errors import ConfigError, UserError
from denoiser.metrics import METRICS, MetricAccumulator, flip_exposure, psnr
from denoiser.plot_crops import crop_box, save_crops, to_display
from denoiser.report import markdown_table, write_csv

log = logging.getLogger(__name__)

#: buffers every method may read (networks need all five; OIDN color, albedo, normal)
INPUT_BUFFERS = ("color", "albedo", "normal", "depth", "motion")


# ----------------------------------------------------------------------------- configuration


def checkpoint_paths(spec) -> OrderedDict[str, Path]:
    """``ckpt`` config -> ordered ``{name: path}``.

    ``spec``: None/empty, one path, a list of paths (names are the file stems, made unique
    with the parent directory when two stems clash) or a mapping ``{name: path}``.
    """
    if isinstance(spec, (DictConfig, ListConfig)):
        spec = OmegaConf.to_container(spec, resolve=True)
    if spec is None or spec == "" or spec == []:
        return OrderedDict()
    if isinstance(spec, (str, os.PathLike)):
        spec = [spec]
    if isinstance(spec, Mapping):
        return OrderedDict((str(k), Path(v)) for k, v in spec.items())
    if not isinstance(spec, (list, tuple)):
        raise ConfigError(f"ckpt: expected a path, a list of paths or a mapping name -> path, got {spec!r}")
    paths = [Path(p) for p in spec]
    stems = [p.stem for p in paths]
    out: OrderedDict[str, Path] = OrderedDict()
    for p in paths:
        name = p.stem if stems.count(p.stem) == 1 else f"{p.parent.name}/{p.stem}"
        if name in out:
            raise ConfigError(f"ckpt: {p} is given twice")
        out[name] = p
    return out


def build_methods(cfg: DictConfig, device: str = "cpu") -> OrderedDict[str, object]:
    """Baselines (instantiated from ``cfg.baselines``) then checkpoints: ``{label: method}``."""
    from hydra.utils import instantiate

    methods: OrderedDict[str, object] = OrderedDict()
    for key, node in (cfg.get("baselines") or {}).items():
        if node is None:
            continue
        method = instantiate(node)
        methods[getattr(method, "label", key)] = method
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


def open_test_split(data_cfg: DictConfig, split: str, sequences=None):
    """``(layout, sources, dataset)`` for the labeled sequences of ``<data.root>/<split>``."""
    from hydra.utils import instantiate

    from denoiser.data.dataset import SequenceDataset, index_split

    layout = instantiate(data_cfg.layout)
    sources = index_split(layout, data_cfg.root, split)
    if sequences:
        wanted = [str(s) for s in sequences]
        by_name = {s.name.split("/", 1)[-1]: s for s in sources}
        missing = [w for w in wanted if w not in by_name and w not in {s.name for s in sources}]
        if missing:
            raise UserError(f"{Path(data_cfg.root) / split}: no sequence(s) {', '.join(missing)}; "
                            f"present: {', '.join(sorted(by_name))}")
        sources = [s for s in sources if s.name in wanted or s.name.split("/", 1)[-1] in wanted]
    unlabeled = [s for s in sources if not s.labeled]
    if unlabeled:
        raise UserError(f"{unlabeled[0].directory}: sequence has no reference buffer; evaluation needs "
                        "a labeled split")
    dataset = SequenceDataset(sources, layout, list(INPUT_BUFFERS), window=1, labeled=True, cache_dir=None)
    return layout, sources, dataset


def read_frame(dataset, source, index: int) -> tuple[dict, torch.Tensor, bool]:
    """Frame ``index`` of ``source``: ``(inputs {buffer: [1, C, H, W]}, reference [1, 3, H, W], reset)``."""
    item = dataset.load(source, index, 1, None)
    inputs = {b: item[b] for b in INPUT_BUFFERS}
    reset = index == 0 or index in source.cuts
    return inputs, item["reference"], reset


def sequence_reference(dataset, source, frames: int) -> torch.Tensor:
    """All reference frames ``[T, 3, H, W]`` of ``source`` (for the FLIP exposure range)."""
    return torch.stack([torch.from_numpy(dataset.reader.read(source, i, ["reference"])["reference"])
                        for i in range(frames)])


# ----------------------------------------------------------------------------- evaluation


class Evaluation:
    """Runs methods over sequences and keeps one :class:`MetricAccumulator` per method."""

    def __init__(self, methods: Mapping[str, object], metrics, warmup: int):
        self.methods = OrderedDict(methods)
        self.metrics = list(metrics)
        self.acc = {label: MetricAccumulator(self.metrics, warmup) for label in self.methods}
        self.seconds = {label: {} for label in self.methods}  # label -> {sequence: [s per frame]}
        self.scenes: dict[str, str] = {}

    def run_sequence(self, dataset, source, frames: int, image_frame: int | None, image_cfg,
                     exr_dir: Path | None, progress) -> dict | None:
        """Evaluate every method on ``frames`` frames of ``source``; returns image panels or None."""
        name = source.name
        self.scenes[name] = source.meta.scene_name or name.split("/", 1)[-1]
        if "flip" in self.metrics:
            exposure = flip_exposure(sequence_reference(dataset, source, frames))
            for acc in self.acc.values():
                acc.set_flip_exposure(name, exposure)
        for method in self.methods.values():
            method.reset()
        panels = None
        for index in range(frames):
            inputs, reference, reset = read_frame(dataset, source, index)
            outputs = {}
            for label, method in self.methods.items():
                start = time.perf_counter()
                out = method(inputs, reset)
                self.seconds[label].setdefault(name, []).append(time.perf_counter() - start)
                if not torch.isfinite(out).all():
                    raise RuntimeError(f"{label} produced NaN/Inf on {name} frame {index}")
                self.acc[label].update(out, reference, name, frame_index=[index], reset=[reset])
                outputs[label] = out
                if exr_dir is not None:
                    write_denoised(exr_dir / label.replace("/", "_") / name / f"frame_{index:04d}.exr", out)
            if index == image_frame:
                panels = self.crop_panels(outputs, reference, image_cfg)
            progress.update(1)
        return panels

    def crop_panels(self, outputs: Mapping[str, torch.Tensor], reference: torch.Tensor, image_cfg) -> dict:
        """Tonemapped crops of the image frame: ``{"panels": {label: [h, w, 3]}, "notes": {...}}``."""
        shown = list(image_cfg.get("methods") or outputs)
        unknown = [m for m in shown if m not in outputs]
        if unknown:
            raise ConfigError(f"images.methods: unknown method(s) {unknown}; known: {list(outputs)}")
        box = crop_box(reference.shape[-2], reference.shape[-1], int(image_cfg.size), image_cfg.get("center"))
        panels = {label: to_display(outputs[label], box) for label in shown}
        notes = {label: f"{float(psnr(outputs[label], reference)[0]):.2f} dB" for label in shown}
        panels["reference"] = to_display(reference, box)
        return {"panels": panels, "notes": notes, "box": box}

    # ----------------------------------------------------------------- tables

    def sequence_rows(self) -> list[dict]:
        """One row per method and sequence, then one ``mean`` row per method."""
        rows = []
        for label, acc in self.acc.items():
            per_seq = acc.per_sequence()
            for seq, values in per_seq.items():
                secs = self.seconds[label].get(seq, [])
                rows.append({"method": label, "scene": self.scenes.get(seq, ""), "sequence": seq,
                             "frames": values["frames"], **{m: values[m] for m in acc.metrics},
                             "ms_per_frame": 1000.0 * sum(secs) / max(len(secs), 1)})
            overall = acc.compute()
            all_secs = [s for v in self.seconds[label].values() for s in v]
            rows.append({"method": label, "scene": "mean", "sequence": "mean",
                         "frames": sum(v["frames"] for v in per_seq.values()), **overall,
                         "ms_per_frame": 1000.0 * sum(all_secs) / max(len(all_secs), 1)})
        return rows

    def scene_rows(self, rows: list[dict]) -> list[dict]:
        """Per method and scene: mean over that scene's sequences."""
        out = []
        for label in self.methods:
            by_scene: OrderedDict[str, list[dict]] = OrderedDict()
            for r in rows:
                if r["method"] == label and r["sequence"] != "mean":
                    by_scene.setdefault(r["scene"], []).append(r)
            for scene, rs in by_scene.items():
                out.append({"method": label, "scene": scene, "sequences": len(rs),
                            **{m: _mean([r[m] for r in rs]) for m in self.metrics}})
        return out

    def frame_rows(self) -> list[dict]:
        return [{"method": label, **row} for label, acc in self.acc.items() for row in acc.frame_rows()]


def _mean(values) -> float:
    vals = [v for v in values if not (isinstance(v, float) and math.isnan(v))]
    return float(sum(vals) / len(vals)) if vals else float("nan")


def write_denoised(path: Path, output: torch.Tensor) -> None:
    """Write ``output`` ``[1, 3, H, W]`` as an EXR with a ``denoised`` buffer (atomic)."""
    from denoiser.data.exr import write_frame

    write_frame(path, {"denoised": output[0].permute(1, 2, 0).cpu().numpy()})


METRIC_FORMATS = {"psnr": ".2f", "ssim": ".4f", "tpsnr": ".2f", "flip": ".4f", "relmse": ".4g", "smape": ".4f",
                  "ms_per_frame": ".1f"}
METRIC_HEADERS = {"psnr": "PSNR dB ↑", "ssim": "SSIM ↑", "tpsnr": "tPSNR dB ↑", "flip": "FLIP ↓",
                  "relmse": "relMSE ↓", "smape": "SMAPE ↓", "ms_per_frame": "ms/frame (eval run)"}


def markdown_report(ev: Evaluation, rows: list[dict], header: str) -> str:
    """The three Markdown tables: overall, per scene, per sequence."""
    metrics = ev.metrics
    overall = [r for r in rows if r["sequence"] == "mean"]
    per_seq = [r for r in rows if r["sequence"] != "mean"]
    parts = [header,
             "## Overall (mean over sequences of per-sequence means)\n",
             markdown_table(overall, ["method", "frames", *metrics, "ms_per_frame"], METRIC_FORMATS, METRIC_HEADERS),
             "\n## Per scene\n",
             markdown_table(ev.scene_rows(rows), ["scene", "method", "sequences", *metrics], METRIC_FORMATS,
                            METRIC_HEADERS),
             "\n## Per sequence\n",
             markdown_table(per_seq, ["sequence", "method", "frames", *metrics], METRIC_FORMATS, METRIC_HEADERS)]
    return "\n".join(parts)


def run(cfg: DictConfig) -> dict:
    """The ``denoiser-eval`` task; returns ``{label: overall metrics}``."""
    metrics = [str(m) for m in cfg.metrics]
    unknown = [m for m in metrics if m not in METRICS]
    if unknown:
        raise ConfigError(f"metrics: unknown {unknown}; known: {list(METRICS)}")
    threads = set_threads(cfg.get("threads"))
    out_dir = Path(cfg.out_dir)
    _, sources, dataset = open_test_split(cfg.data, cfg.split, cfg.get("sequences"))
    methods = build_methods(cfg, cfg.get("device", "cpu"))
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
        _move_tree(staging, out_dir)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    rows = ev.sequence_rows()
    write_csv(out_dir / "metrics.csv", rows, ["method", "scene", "sequence", "frames", *metrics, "ms_per_frame"])
    write_csv(out_dir / "frames.csv", ev.frame_rows(), ["method", "sequence", "frame", "warmup", *metrics])
    header = (f"# Evaluation on {Path(cfg.data.root) / cfg.split}\n\n{len(sources)} sequence(s), "
              f"warm-up {cfg.warmup} frame(s) excluded after each reset, {threads} thread(s). Metrics: "
              "PSNR/SSIM/tPSNR on ACES+sRGB tonemapped frames, HDR-FLIP with a per-sequence exposure range, "
              "relMSE and SMAPE on linear HDR (see denoiser/metrics.py).\n\n")
    from denoiser.report import atomic_write_text

    atomic_write_text(out_dir / "metrics.md", markdown_report(ev, rows, header))
    overall = {r["method"]: {m: r[m] for m in metrics} for r in rows if r["sequence"] == "mean"}
    print(markdown_table([r for r in rows if r["sequence"] == "mean"], ["method", *metrics, "ms_per_frame"],
                         METRIC_FORMATS, METRIC_HEADERS))
    print(f"wrote {out_dir / 'metrics.csv'}, {out_dir / 'metrics.md'} and {out_dir / 'images'}")
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
    from denoiser.cli import hydra_command

    hydra_command(run, "eval")()


if __name__ == "__main__":
    main()
