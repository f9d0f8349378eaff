"""Quality of methods on labeled sequences: every method runs over the same frames, and one
:class:`~denoiser.metrics.MetricAccumulator` per method keeps the per-frame metrics (means per
sequence, then over sequences). Used by ``denoiser-eval`` (:mod:`denoiser.commands.evaluate`).

A *method* is anything with ``reset()`` and ``method(frame, reset) -> [1, 3, H, W]``
(:mod:`denoiser.methods.baselines`): the noisy input, OIDN, a trained network through the recurrent
runner.

With ``warp`` among the metrics, one :class:`~denoiser.report.flicker.FlickerMeter` per sequence
measures every method's output and the reference along the frames' motion (the same visibility
mask for all of them), and each method's accumulator gets ``warp`` (its own) and ``warp_ref``
(the reference's, the floor that real shading changes alone give) frame by frame.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path

import torch

from denoiser.data.evalset import read_frame, sequence_reference
from denoiser.errors import ConfigError, UserError
from denoiser.metrics import COLUMNS, MetricAccumulator, flip_exposure, psnr
from denoiser.report.flicker import FlickerMeter, flicker_buffers, read_motion
from denoiser.report.plot_crops import crop_box, to_display
from denoiser.tables import markdown_table, read_csv


class Evaluation:
    """Runs methods over sequences and keeps one :class:`MetricAccumulator` per method."""

    def __init__(self, methods: Mapping[str, object], metrics, warmup: int):
        self.methods = OrderedDict(methods)
        self.metrics = list(metrics)
        if "warp" in self.metrics and "warp_ref" not in self.metrics:  # the reference's own value beside it
            self.metrics.insert(self.metrics.index("warp") + 1, "warp_ref")
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
        meter = FlickerMeter([*self.methods, REFERENCE]) if "warp" in self.metrics else None
        flicker = flicker_buffers(dataset.reader.layout, source) if meter is not None else None
        panels = None
        for index in range(frames):
            inputs, reference, reset = read_frame(dataset, source, index)
            without_samples = {k: v for k, v in inputs.items() if k != "samples"}  # only ONND reads them
            outputs = {}
            for label, method in self.methods.items():
                start = time.perf_counter()
                out = method(inputs if getattr(method, "uses_samples", False) else without_samples, reset)
                self.seconds[label].setdefault(name, []).append(time.perf_counter() - start)
                if not torch.isfinite(out).all():
                    raise RuntimeError(f"{label} produced NaN/Inf on {name} frame {index}")
                outputs[label] = out
                if exr_dir is not None:
                    write_denoised(exr_dir / label.replace("/", "_") / name / f"frame_{index:04d}.exr", out)
            warp = {}
            if meter is not None:
                extra = read_motion(dataset.reader.layout, source, index, inputs, flicker)
                warp = meter.update({**outputs, REFERENCE: reference}, extra["motion"], reset, extra["aux"],
                                    extra["next_motion"])
            for label, out in outputs.items():
                values = {"warp": [warp[label]], "warp_ref": [warp[REFERENCE]]} if warp else None
                self.acc[label].update(out, reference, name, frame_index=[index], reset=[reset], values=values)
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
                             "frames": values["frames"], **{m: values[m] for m in acc.columns},
                             "ms_per_frame": 1000.0 * sum(secs) / max(len(secs), 1)})
            overall = acc.compute(subsets=True)
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
                            **{m: _mean([r[m] for r in rs]) for m in self.columns}})
        return out

    @property
    def columns(self) -> list[str]:
        """The metric columns of the tables: the metrics, then their frame subsets (``psnr_f2``)."""
        return next(iter(self.acc.values())).columns

    def frame_rows(self) -> list[dict]:
        return [{"method": label, **row} for label, acc in self.acc.items() for row in acc.frame_rows()]


#: the flicker meter's stream of the reference frames (``warp_ref``)
REFERENCE = "reference"


def _mean(values) -> float:
    vals = [v for v in values if not (isinstance(v, float) and math.isnan(v))]
    return float(sum(vals) / len(vals)) if vals else float("nan")


def write_denoised(path: Path, output: torch.Tensor) -> None:
    """Write ``output`` ``[1, 3, H, W]`` as an EXR with a ``denoised`` buffer (atomic)."""
    from denoiser.data.exr import write_frame

    write_frame(path, {"denoised": output[0].permute(1, 2, 0).cpu().numpy()})


#: format spec and header of every column of the evaluation's tables (:data:`denoiser.metrics.COLUMNS`)
METRIC_FORMATS = {**{c: spec.fmt for c, spec in COLUMNS.items()}, "ms_per_frame": ".1f"}
METRIC_HEADERS = {**{c: spec.header for c, spec in COLUMNS.items()}, "ms_per_frame": "ms/frame (eval run)"}


def markdown_report(ev: Evaluation, rows: list[dict], header: str) -> str:
    """The three Markdown tables: overall, per scene, per sequence."""
    metrics = ev.columns
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


def eval_means(path) -> dict[str, dict]:
    """``{method: {"psnr": ..., ...}}`` from the ``mean`` rows of ``denoiser-eval``'s metrics.csv
    (``{}`` for no path); a CSV without the ``method`` and ``sequence`` columns is a UserError."""
    if not path:
        return {}
    rows = read_csv(path)
    if rows and ("method" not in rows[0] or "sequence" not in rows[0]):
        raise UserError(f"{path}: not a denoiser-eval metrics.csv (needs columns method and sequence)")
    return {str(r["method"]): r for r in rows if r["sequence"] == "mean"}
