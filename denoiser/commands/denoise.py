"""``denoiser-denoise``: denoise a directory of EXR frames with a trained checkpoint.

::

    denoiser-denoise ckpt=runs/student.ckpt input=renders/shot1 output=denoised/shot1
    denoiser-denoise ckpt=s.ckpt input=blender_out output=denoised layout=blender write=rgb

Input: one sequence directory in a layout of ``conf/layout/`` (``native``: ``frame_XXXX.exr``
with native channel names, ``sequence.json`` optional; ``blender``: Cycles multilayer EXRs in
``<input>/noisy/`` or ``<input>`` itself). The network needs ``color``, ``albedo``,
``normal``, ``depth`` and ``motion`` (``motion`` only with temporal recurrence); a missing
buffer is an error that lists the channels the file has.

Output: one EXR per input frame, same file name, in ``output``:

* ``write=buffers`` (default): every channel of the input frame file, plus the denoised
  image as ``<channel_prefix>.R/G/B`` (default ``denoised.R/G/B``);
* ``write=rgb``: a plain ``R, G, B`` file with the denoised image only.

Frames run in order with the recurrent state carried from frame to frame and reset at the
first frame and at camera cuts (``sequence.json`` ``cuts``). Frames stream one at a time: the
memory use does not grow with the sequence length. Writes are atomic (temporary name, then
rename). Before anything is written every frame to be processed is decoded once (``verify``),
so a damaged input frame stops the command with one error line and no output; this costs a
few percent of the run (decoding is ~1 % of a CPU network step).

Backend (``backend``): a name of the config group ``conf/backends/`` (one YAML per backend, the same
names as ``denoiser-bench``'s ``use_backends``; :func:`~denoiser.inference.backends.load_backend`), e.g.
``eager`` (PyTorch, ``Denoiser.step``), ``onnxruntime`` or ``openvino`` (``openvino_f32``/``openvino_bf16`` by ``precision``)
(the exported step graph, :mod:`denoiser.inference.step_graph`; exported once at start, OpenVINO compiles
it once for the frame size); null (default) picks ``openvino`` when it is installed (with
``onnx`` for the export) and the device is the CPU, else ``eager``. ``precision``: ``f32``
(the outputs match eager PyTorch within float32 rounding, see ``tests/inference/test_openvino.py``), ``bf16``
(OpenVINO's bf16 inference precision, eager's bfloat16 autocast; errors of a few 1e-3 relative;
faster on CPUs with AMX, not always with AVX512-BF16 alone) or ``auto``, OpenVINO's default: both are
timed on the first frame (:func:`denoiser.inference.backends.faster_precision`, a few steps each)
and the faster runs, with one line saying which and why; the choice is kept in the output
directory (``denoise_precision.json``) and a resumed run keeps it, so that resuming stays exact.
Other backends default to f32. With ``device=cuda``: ``cuda`` and
``cuda_compiled`` (:mod:`denoiser.inference.cuda_backend`: weights cast once to ``precision`` f32, bf16 or
fp16, the Triton filter; ``cuda_compiled`` replays a CUDA graph per frame size; docs/gpu.md).
Every backend steps through the one recurrent runner (:class:`~denoiser.recurrent.RecurrentRunner`).

Report (``report=true``, the default): at the end, ``report.json`` and ``report.md`` in ``output``: the
run (frames, seconds, frames/s, backend, precision, threads) and, when the input has motion, the
flicker of the noisy input and of the denoised output, frame by frame: the warp error of
:mod:`denoiser.metrics` (``warp``, no reference needed; :mod:`denoiser.report.flicker`), with
``flicker.png``, the two over frames, and the share of the run the measure took; it is measured
at every ``report_stride``-th pixel in x and y (null: :func:`auto_stride`, about 32768 pixels a
frame, every 8th at 1080p; :mod:`denoiser.report.flicker`). Frames replayed
for a resumed run's history count as measured.

Resuming: frames whose output file exists are not written again. Their outputs are still
needed as the recurrent history of the next frame, so the run restarts the network at the
last reset (first frame or camera cut) at or before the first missing frame and replays the
frames up to it without writing: the resumed frames are bit-identical to an uninterrupted
run. ``replay_frames=N`` bounds that replay to the N frames before the first missing one
(approximate: the history then starts N frames earlier than it would have).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm.auto import tqdm

from denoiser.atomic import atomic_write_text, remove_stale_temporaries
from denoiser.buffers import FRAME_INPUTS
from denoiser.errors import ConfigError, ExrError
from denoiser.recurrent import RecurrentRunner
from denoiser.report.flicker import FlickerMeter, flicker_buffers, read_motion
from denoiser.report.flicker_report import denoise_report

log = logging.getLogger(__name__)

WRITE_MODES = ("buffers", "rgb")
#: the network used without ckpt= (denoiser/models: the shipped release)
DEFAULT_CKPT = "release:student"


def openvino_installed() -> bool:
    import importlib.util

    return all(importlib.util.find_spec(m) is not None for m in ("openvino", "onnx"))


def make_backend(name: str | None, precision: str | None, device: torch.device):
    """The backend of ``backend=`` / ``precision=``: an option of the config group ``conf/backends/``
    (:func:`~denoiser.inference.backends.load_backend`), the precision mapped by
    :func:`~denoiser.inference.backends.resolve_backend` (``openvino`` + ``bf16`` -> ``openvino_bf16``);
    ``name`` None: ``openvino`` when installed and ``device`` is the CPU, else ``eager``. Torch backends run
    on ``device``. ``precision`` None: f32 for the names that take a precision (``eager``, ``openvino``,
    ``cuda``, ``cuda_compiled``), any other option its own. Returns ``(name, backend)``."""
    from denoiser.inference.backends import (
        PRECISION_ARGUMENT,
        PRECISION_OPTIONS,
        PRECISIONS,
        backend_config,
        load_backend,
        resolve_backend,
    )

    if name is None:
        name = "openvino" if device.type == "cpu" and openvino_installed() else "eager"
    if precision == AUTO:
        if name != "openvino":
            raise ConfigError(f"precision=auto: measures backend=openvino's f32 and bf16 only, not backend={name}")
        precision = "f32"  # checked as f32 here; run() times both on the first frame (auto_precision)
    if precision is not None and precision not in PRECISIONS:
        raise ConfigError(f"precision: {precision!r} is not one of {', '.join(PRECISIONS)}, {AUTO}")
    if precision is None and (name in PRECISION_OPTIONS or name in PRECISION_ARGUMENT):
        precision = "f32"
    option, overrides = resolve_backend(name, precision)
    config = backend_config(option)
    if _torch_backend(config["_target_"]):
        if str(config.get("device", "cpu")).startswith("cuda") and device.type != "cuda":
            raise ConfigError(f"backend={name} needs device=cuda")
        overrides.setdefault("device", str(device))
    elif device.type != "cpu":
        raise ConfigError(f"backend={name} runs on the CPU; use device=cpu or backend=eager")
    backend = load_backend(option, "backend", **overrides)
    reason = backend.available()
    if reason:
        raise ConfigError(f"backend={name} precision={precision}: {reason}")
    return name, backend


#: ``precision=`` that times OpenVINO's f32 and bf16 on the first frame and runs the faster
AUTO = "auto"


def auto_precision(name: str | None, precision: str | None, device: torch.device) -> bool:
    """Whether ``backend=name precision=precision`` leaves the precision to a measurement:
    ``precision=auto``, or the default (null) when the backend is OpenVINO (given or chosen)."""
    if precision == AUTO:
        return True
    return precision is None and (name == "openvino" or (name is None and device.type == "cpu"
                                                         and openvino_installed()))


#: in the output directory: the precision ``precision=auto`` chose, so that a resumed run keeps it
PRECISION_RECORD = "denoise_precision.json"


def auto_choice(out_dir: Path, net, frame: dict, threads: int, resuming: bool) -> tuple[str, object | None]:
    """``precision=auto``'s precision for ``out_dir``: on a fresh run, the faster of f32 and bf16
    measured on ``frame`` (:func:`~denoiser.inference.backends.faster_precision`), written to
    ``out_dir/denoise_precision.json``; on a resumed run (``resuming``: some frames are there), the
    precision recorded there, so that the resumed frames are those of an uninterrupted run (a
    precision measured afresh could differ). Prints one line saying which and why. Returns the
    precision and, when it was measured, its backend (graph exported), else None."""
    import json

    from denoiser.inference.backends import faster_precision

    record = out_dir / PRECISION_RECORD
    if resuming and record.is_file():
        try:
            precision = json.loads(record.read_text())["precision"]
        except (OSError, ValueError, KeyError, TypeError):
            precision = None
        if precision in ("f32", "bf16"):
            print(f"precision auto: {precision}, as the run that wrote the frames in {out_dir} chose ({record.name})")
            return precision, None
    choice = faster_precision(net, frame, threads)
    print(f"precision auto: {choice.reason}")
    atomic_write_text(record, json.dumps({"precision": choice.precision, "ms": choice.ms, "reason": choice.reason},
                                         indent=1) + "\n")
    return choice.precision, choice.backend


def _torch_backend(target: str) -> bool:
    """Whether a backend class steps torch modules on a torch device (its ``device`` argument)."""
    from hydra.utils import get_class

    from denoiser.inference.backends import TorchBackend
    from denoiser.inference.cuda_backend import CudaBackend

    try:
        return issubclass(get_class(target), (TorchBackend, CudaBackend))
    except Exception:  # noqa: BLE001 - an unknown _target_ is load_backend's one-line error
        return False


def to_hwc(output) -> np.ndarray:
    """The step's ``[1, 3, H, W]`` output (tensor or array) -> ``[H, W, 3]`` float32 array."""
    first = output[0]
    if isinstance(first, torch.Tensor):
        first = first.float().cpu().numpy()
    return np.ascontiguousarray(np.asarray(first, dtype=np.float32).transpose(1, 2, 0))


def needed_buffers(net) -> list[str]:
    """Buffers ``net`` reads: all of :data:`~denoiser.buffers.FRAME_INPUTS`, ``motion`` only with recurrence."""
    temporal = getattr(net, "temporal", None) is not None
    return [b for b in FRAME_INPUTS if b != "motion" or temporal]


def check_input_buffers(layout, source, needed: list[str]) -> None:
    """UserError naming the first frame file and its channels if a needed buffer is missing."""
    missing = [b for b in needed if b not in source.buffers]
    if not missing:
        return
    from denoiser.data import exr

    first = layout.file_for(source, 0, "color")
    present = exr.list_channels(first)
    wanted = "; ".join(f"{b} ({' or '.join(','.join(a) for a in layout.specs[b].alternatives)})" for b in missing
                       if b in layout.specs)
    raise ExrError(first, f"missing buffer(s) {wanted or ', '.join(missing)}; present channels: "
                          f"{', '.join(sorted(present))}")


def frame_tensors(arrays: dict[str, np.ndarray], device) -> dict[str, torch.Tensor]:
    """``{buffer: [H, W, C]}`` arrays -> ``{buffer: [1, C, H, W]}`` float32 tensors on ``device``."""
    return {k: torch.from_numpy(np.ascontiguousarray(v.transpose(2, 0, 1)))[None].to(device) for k, v in arrays.items()}


def resume_plan(outputs: list[Path], cuts, replay_frames: int | None) -> tuple[int, int] | None:
    """``(start, first_missing)``: where to start the network and the first frame to write.

    None when every output exists. ``start`` is the last reset (frame 0 or a cut) at or before
    ``first_missing``, or ``first_missing - replay_frames`` when that is later.
    """
    missing = [i for i, p in enumerate(outputs) if not p.exists()]
    if not missing:
        return None
    first = missing[0]
    resets = [0, *[c for c in cuts if c <= first]]
    start = max(resets)
    if replay_frames is not None:
        start = max(start, first - int(replay_frames))
    return start, first


def output_channels(mode: str, input_file: Path, denoised: np.ndarray, prefix: str) -> dict[str, np.ndarray]:
    """Channels to write: the input file's channels plus ``<prefix>.R/G/B``, or plain ``R/G/B``."""
    from denoiser.data import exr

    if mode == "rgb":
        return {c: denoised[..., i] for i, c in enumerate("RGB")}
    channels = exr.read_channels(input_file)
    names = [f"{prefix}.{c}" for c in "RGB"]
    clash = [n for n in names if n in channels]
    if clash:
        raise ConfigError(f"{input_file}: already has channel(s) {', '.join(clash)}; choose another channel_prefix")
    channels.update({n: denoised[..., i] for i, n in enumerate(names)})
    return channels


def run(cfg: DictConfig) -> dict:
    """The ``denoiser-denoise`` task; returns ``{"written": n, "skipped": n, "replayed": n}``."""
    from denoiser.checkpoint import load_denoiser
    from denoiser.configs import instantiate_config
    from denoiser.data import exr

    for key in ("input", "output"):
        if not cfg.get(key):
            raise ConfigError(f"{key}: required (denoiser-denoise input=<dir> output=<dir> [ckpt=<file>])")
    ckpt = cfg.get("ckpt") or DEFAULT_CKPT
    if not cfg.get("ckpt"):
        print(f"denoiser-denoise: no ckpt= given: the shipped release student ({DEFAULT_CKPT}, "
              "denoiser/models/README.md)", file=sys.stderr)
    mode = str(cfg.write)
    if mode not in WRITE_MODES:
        raise ConfigError(f"write: {mode!r} is not one of {', '.join(WRITE_MODES)}")
    src_dir, out_dir = Path(cfg.input), Path(cfg.output)
    if src_dir.resolve() == out_dir.resolve():
        raise ConfigError(f"output: {out_dir} is the input directory; choose another one")
    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    device = torch.device(cfg.get("device") or "cpu")
    for stale in remove_stale_temporaries(out_dir):  # frames whose write was killed
        log.warning("removed %s (a frame write that was killed)", stale)
    backend_name, backend = make_backend(cfg.get("backend"), cfg.get("precision"), device)
    measure_precision = auto_precision(cfg.get("backend"), cfg.get("precision"), device)

    net = load_denoiser(ckpt, device, trust=bool(cfg.get("trust_checkpoint")))
    layout = instantiate_config(cfg.layout, "layout")
    source = layout.open_sequence(src_dir)
    needed = needed_buffers(net)
    check_input_buffers(layout, source, needed)
    color_files = [layout.file_for(source, i, "color") for i in range(source.frames)]
    outputs = [out_dir / f.name for f in color_files]
    plan = resume_plan(outputs, source.cuts, cfg.get("replay_frames"))
    if plan is None:
        print(f"all {source.frames} output frames exist in {out_dir}: nothing to do")
        return {"written": 0, "skipped": source.frames, "replayed": 0}
    start, first = plan
    todo = range(start, source.frames)

    if cfg.get("verify", True):  # decode everything first: a bad frame must not leave partial output
        for i in tqdm(todo, desc="verify input", unit="frame", leave=False):
            layout.read_frame(source, i, needed)

    counts = {"written": 0, "skipped": sum(p.exists() for p in outputs[start:]) + start, "replayed": 0}
    cuts = set(source.cuts)
    threads = int(cfg.threads) if cfg.get("threads") else torch.get_num_threads()
    if measure_precision:  # the faster of f32 and bf16 on this machine, at this size
        precision, backend = auto_choice(out_dir, net, frame_tensors(layout.read_frame(source, start, needed)[0],
                                                                      device),
                                         threads, resuming=any(p.exists() for p in outputs))
        if backend is None:  # the recorded precision of a resumed run
            backend_name, backend = make_backend(backend_name, precision, device)
    runner = RecurrentRunner(backend.prepare(net, None, threads).step)
    # the flicker of the input and the output (report.json/md, flicker.png), where the frames have motion
    stride = int(cfg.report_stride) if cfg.get("report_stride") else auto_stride(source.height, source.width)
    meter = (FlickerMeter(["input", "output"], stride)
             if cfg.get("report", True) and "motion" in source.buffers else None)
    extra = [b for b in flicker_buffers(layout, source) if b not in needed] if meter is not None else []
    measure_seconds = 0.0
    started = time.perf_counter()
    with torch.inference_mode(), tqdm(todo, desc=f"denoise ({backend.label})", unit="frame") as progress:
        for i in progress:
            arrays, bad = layout.read_frame(source, i, [*needed, *extra])  # one decode for both
            if any(bad.values()):
                log.warning("%s: replaced %d NaN/Inf value(s)", color_files[i], sum(bad.values()))
            reset = i == start or i in cuts
            frame = frame_tensors({k: v for k, v in arrays.items() if k in needed}, device)
            output = runner(frame, reset)
            if meter is not None:
                tick = time.perf_counter()
                flicker_frame(meter, layout, source, i, frame, arrays, output, reset)
                measure_seconds += time.perf_counter() - tick
            if outputs[i].exists():
                counts["replayed"] += int(i < first)
                continue
            denoised = to_hwc(output)
            channels = output_channels(mode, color_files[i], denoised, str(cfg.channel_prefix))
            exr.write_channels(outputs[i], channels, half=bool(cfg.half), compression=str(cfg.compression))
            counts["written"] += 1
    seconds = time.perf_counter() - started
    print(f"denoised {counts['written']} frame(s) of {src_dir} into {out_dir} in {seconds:.1f} s "
          f"({counts['skipped']} already there, {counts['replayed']} replayed for the recurrent history; "
          f"backend {backend_name}, precision {backend.dtype})")
    if cfg.get("report", True):
        info = {"input": str(src_dir), "frames": len(todo), "seconds": seconds, "measure_seconds": measure_seconds,
                "backend": backend_name, "precision": str(backend.dtype), "threads": threads,
                "size": [source.height, source.width], "written": counts["written"], "replayed": counts["replayed"]}
        record = denoise_report(meter, [i + 1 for i in todo], info, out_dir)
        if record["flicker"] and record["flicker"]["output"]["mean"] is not None:
            fl = record["flicker"]
            print(f"flicker (warp error ×1e3, lower is steadier): input {fl['input']['mean']:.3f}, "
                  f"output {fl['output']['mean']:.3f} ({record['measure_share']:.1%} of the run)")
        print(f"wrote {out_dir / 'report.md'} and report.json" + (" and flicker.png" if meter is not None else ""))
    return counts


#: pixels the report's flicker measures per frame with ``report_stride=null`` (about; :func:`auto_stride`)
REPORT_POINTS = 32768


def auto_stride(height: int, width: int) -> int:
    """The report's stride at ``height`` x ``width``: about :data:`REPORT_POINTS` pixels measured per
    frame (every pixel up to 181x181, every 8th in x and y at 1080p), so its cost does not grow
    with the frame."""
    return max(1, round(math.sqrt(height * width / REPORT_POINTS)))


def flicker_frame(meter, layout, source, index: int, frame: dict, arrays: dict, output, reset: bool) -> None:
    """Add frame ``index`` (its input ``frame`` ``{buffer: [1, C, H, W]}``, every buffer read
    ``arrays`` ``{buffer: [H, W, C]}`` and the network's ``output`` ``[1, 3, H, W]``) to the flicker
    ``meter`` (:class:`~denoiser.report.flicker.FlickerMeter`)."""
    out = output if isinstance(output, torch.Tensor) else torch.from_numpy(np.asarray(output))
    extra = read_motion(layout, source, index, arrays)
    meter.update({"input": frame["color"].cpu(), "output": out.float().cpu()}, extra["motion"], reset,
                  extra["aux"], extra["next_motion"])


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "denoise")()


if __name__ == "__main__":
    main()
