"""``denoiser-flicker``: how much folders of denoised frames flicker, side by side, without a reference.

::

    denoiser-flicker denoised/oidn_fast denoised/ours layout=blender motion=renders/shot1
    denoiser-flicker out_a out_b motion=renders/shot1 out=reports/flicker

Each folder holds one sequence's denoised frames as EXR files (frame order: the number in the
file name), whoever wrote them: Blender with its OIDN denoiser (``Combined`` is then the denoised
image), ``denoiser-denoise`` (``denoised.R/G/B``, or plain ``R/G/B`` with ``write=rgb``), another
tool; the first of ``channels`` that a file holds is read. The motion vectors come from the noisy
render of the same frames, ``motion=`` (a sequence folder in the layout ``layout=``: Blender's
``Vector`` pass, or the native ``motion.X/Y``), or, without it, from the first folder itself
(``denoiser-denoise write=buffers`` keeps every input channel). Every folder must have as many
frames as that render.

The measure is the warp error of :mod:`denoiser.metrics` (``warp``; Lai et al. 2018): per frame,
the mean over the pixels visible in both frames of the squared distance between the tonemapped
frame and the previous one warped along the motion vectors (×1e3, lower is steadier), with the
visibility test of :mod:`denoiser.report.flicker` (forward-backward where the render has motion in
both directions, else the disocclusion gate's depth/normal/albedo test). With ``input=true`` (the
default) the noisy render's own value is the first row. It also counts real changes of shading, so
compare folders of the same frames with each other, not with 0.

Prints one table (per folder: the mean, the share of pixels kept, the frames measured, the test)
and writes one plot (the warp error over frames, one line per folder) to ``out/flicker.png``
(or Hydra's run directory without ``out``); with ``out=<dir>`` also ``flicker.json``: per folder its
name as given, the mean and the per-frame values (null on the first frame and at cuts).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from denoiser.atomic import atomic_write_text
from denoiser.configs import instantiate_config
from denoiser.data import exr
from denoiser.data.layouts.blender import exr_files
from denoiser.errors import ConfigError, ExrError, UserError
from denoiser.report.flicker import FlickerMeter, flicker_buffers, read_motion
from denoiser.report.flicker_report import json_values, plot_flicker, summary_rows, summary_table

#: the row of the noisy render's own frames (``input=true``)
INPUT_ROW = "noisy input"


def frame_files(folder: Path) -> list[Path]:
    """The EXR frames of a folder of denoised frames, in frame order; a UserError if there are none."""
    if not folder.is_dir():
        raise UserError(f"{folder}: folder does not exist")
    files = exr_files(folder)
    if not files:
        raise UserError(f"{folder}: no .exr frames")
    return files


def read_color(path: Path, alternatives) -> torch.Tensor:
    """The denoised image ``[1, 3, H, W]`` of one file: the first channel triple of ``alternatives``
    it holds (an ExrError naming the file and its channels otherwise). Not sanitised: the
    measure masks non-finite pixels."""
    present = set(exr.list_channels(path))
    for names in alternatives:
        if all(n in present for n in names):
            ch = exr.read_channels(path, names)
            return torch.from_numpy(np.stack([ch[n] for n in names]).astype(np.float32))[None]
    tried = " or ".join(",".join(a) for a in alternatives)
    raise ExrError(path, f"no denoised image (channels {tried}); present: {', '.join(sorted(present))} "
                         "(set channels=[[R,G,B]] to the names)")


def run(cfg: DictConfig) -> dict:
    """The ``denoiser-flicker`` task; returns ``{name: {"mean", "kept", "per_frame"}}``."""
    dirs = [str(d) for d in (cfg.get("dirs") or [])]
    if not dirs:
        raise ConfigError("dirs: give one or more folders of denoised frames (denoiser-flicker <dir> [<dir> ...] "
                          "motion=<noisy render>)")
    if len(set(dirs)) != len(dirs):
        raise ConfigError(f"dirs: a folder is given twice ({', '.join(dirs)})")
    alternatives = [tuple(str(c) for c in a) for a in cfg.channels]
    files = {d: frame_files(Path(d)) for d in dirs}
    layout = instantiate_config(cfg.layout, "layout")
    motion_dir = Path(cfg.motion) if cfg.get("motion") else Path(dirs[0])
    if not motion_dir.is_dir():
        raise UserError(f"{motion_dir}: motion folder does not exist (motion= names the noisy render)")
    source = layout.open_sequence(motion_dir)
    if "motion" not in source.buffers:
        raise ExrError(layout.file_for(source, 0, "color"), "no motion pass (the flicker measure needs the "
                       "renderer's motion vectors: Blender's Vector pass, or the native motion.X/Y; motion= names "
                       "the noisy render)")
    for d, fs in files.items():
        if len(fs) != source.frames:
            raise UserError(f"{d}: {len(fs)} frame(s), but the motion render {motion_dir} has {source.frames}")
    if source.frames < 2:
        raise UserError(f"{motion_dir}: one frame; flicker needs two or more")
    names = ([INPUT_ROW] if cfg.get("input", True) else []) + dirs
    if len(set(names)) != len(names):
        raise ConfigError(f"dirs: a folder may not be called {INPUT_ROW!r} with input=true")
    meter = FlickerMeter(names)
    cuts = set(source.cuts)
    buffers = flicker_buffers(layout, source)
    for i in tqdm(range(source.frames), desc="flicker", unit="frame", leave=False):
        frames = {d: read_color(files[d][i], alternatives) for d in dirs}
        arrays, _ = layout.read_frame(source, i, [*(["color"] if cfg.get("input", True) else []), *buffers])
        if cfg.get("input", True):
            frames[INPUT_ROW] = torch.from_numpy(np.ascontiguousarray(arrays["color"].transpose(2, 0, 1)))[None]
        shapes = {d: tuple(f.shape[-2:]) for d, f in frames.items()}
        if len(set(shapes.values())) != 1 or shapes[dirs[0]] != (source.height, source.width):
            bad = next(d for d, s in shapes.items() if s != (source.height, source.width))
            raise UserError(f"{files[bad][i] if bad in files else motion_dir}: frame {i + 1} is "
                            f"{shapes[bad][1]}x{shapes[bad][0]}, the motion render {source.width}x{source.height}")
        extra = read_motion(layout, source, i, arrays, buffers)
        meter.update(frames, extra["motion"], i == 0 or i in cuts, extra["aux"], extra["next_motion"])
    results = {n: meter.result(n) for n in names}
    try:
        rows = summary_rows(results)
    except ValueError as err:
        raise UserError(f"{motion_dir}: {err}") from None
    print(f"Flicker of {len(dirs)} folder(s) over {source.frames} frames of {motion_dir} (warp error ×1e3, lower is "
          "steadier; it also counts real shading changes: compare the rows with each other):")
    print(summary_table(results))
    out = Path(cfg.out) if cfg.get("out") else None
    plot_dir = out if out is not None else run_directory()
    plot = plot_flicker(plot_dir / "flicker.png", results, f"warp error over frames, motion of {motion_dir}")
    record = {"motion": str(motion_dir), "frames": source.frames, "mask": meter.mask,
              "folders": [{"name": r["name"], "mean": r["mean"], "kept": r["kept"],
                           "per_frame": json_values(results[r["name"]].per_frame)} for r in rows]}
    if out is not None:
        atomic_write_text(out / "flicker.json", json.dumps(record, indent=1, allow_nan=False) + "\n")
        print(f"wrote {out / 'flicker.json'} and {plot}")
    else:
        print(f"wrote {plot}")
    return {r["name"]: {"mean": r["mean"], "kept": r["kept"], "per_frame": results[r["name"]].per_frame}
            for r in rows}


def run_directory() -> Path:
    """Hydra's run directory (``hydra.run.dir``), or the working directory outside a Hydra app."""
    from hydra.core.hydra_config import HydraConfig

    return Path(HydraConfig.get().runtime.output_dir) if HydraConfig.initialized() else Path.cwd()


def dirs_argv(argv: list[str]) -> list[str]:
    """The command line with its plain arguments (folders: no ``=``, no leading ``-``) gathered
    into one Hydra override ``dirs=[...]`` (each quoted), so ``denoiser-flicker a b key=v`` works."""
    dirs = [a for a in argv if "=" not in a and not a.startswith("-")]
    rest = [a for a in argv if a not in dirs]
    if not dirs:
        return rest
    quoted = ",".join("'" + d.replace("\\", "\\\\").replace("'", "\\'") + "'" for d in dirs)
    return [*rest, f"dirs=[{quoted}]"]


def main() -> None:
    from denoiser.commands.app import hydra_command

    sys.argv = [sys.argv[0], *dirs_argv(sys.argv[1:])]
    hydra_command(run, "flicker")()


if __name__ == "__main__":
    main()
