"""The device check of a lent GPU: ``python -m denoiser.commands.tools.gpu_check`` (``scripts/gpu_check.sh``,
``make gpu-check``; docs/gpu.md).

A Hydra app over ``conf/gpu_check.yaml``. In one process, within ``budget_s``, it writes
``<out>/gpu.md`` (rewritten after every section, so a run cut short still reports what it
measured) and ``<out>/rows.csv``:

1. the device: GPU, driver, torch, CUDA, cuDNN and Triton versions
   (:func:`denoiser.inference.cuda_backend.device_report`), and the card's fp16/bf16 matmul and copy
   bandwidth measured now (:func:`~denoiser.inference.cuda_backend.gpu_peaks`);
2. inference at ``inference.size`` (1080p): each row a backend of ``conf/backends/`` (the
   eager autocast baseline, ``cuda`` and ``cuda_compiled`` with the torch and the Triton filter,
   the teacher) timed with CUDA events (:func:`~denoiser.inference.cuda_backend.cuda_event_times`, median
   of ``repeats`` after ``warmup`` steps on frames already on the GPU), GFLOP per frame
   (:func:`denoiser.measure.count_flops`), achieved TFLOP/s and its share of the measured matmul
   peak, the bytes a step must move (:func:`~denoiser.inference.cuda_backend.step_traffic`: ``floor``) and
   the time that takes at the measured bandwidth as a share of the step, the op-by-op traffic of
   eager execution, peak GPU memory, and the largest relative difference from eager fp32 on the
   GPU over ``parity_frames`` frames;
3. training steps (batch 8, window 4, 128x128, bf16 autocast; forward, ``DenoiseLoss``, backward,
   AdamW) of the paper student and the teacher, with channels-last, fused AdamW and compile as
   rows;
4. a short training run of the paper student (``python train.py``, ``train_run.overrides``) on
   the data under ``data_root``, and the frames/s the data module delivers alone against the
   frames/s the training step needs;
5. the checkpoint of that run evaluated on the CPU (``denoiser-eval device=cpu``, the checkpoint
   loaded with ``map_location=cpu``).
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import time
import traceback
from pathlib import Path

import torch
from omegaconf import DictConfig

from denoiser.errors import ConfigError

ROOT = Path(__file__).resolve().parents[3]  # the checkout


#: sections of gpu.md that its README block (``<!-- gpu:begin -->``, copied by ``make readme``) repeats
README_SECTIONS = ("Inference", "Training step", "Training run", "CPU evaluation of the GPU-trained checkpoint")
#: the Device lines the README block names the card and the software with
README_DEVICE = ("gpu", "driver", "torch", "cuda", "triton")


class Report:
    """``gpu.md``: sections in order, the file rewritten whenever one is set, and a README block
    after them: the card and versions, then :data:`README_SECTIONS`."""

    def __init__(self, path: Path, keep: bool = False):
        """``keep``: start from the sections of an existing ``path`` (a check resumed in a second lease)."""
        self.path = path
        self.sections: dict[str, str] = {}
        if keep and path.exists():
            for chunk in path.read_text().split("<!-- gpu:begin -->")[0].split("\n## ")[1:]:
                title, _, body = chunk.partition("\n\n")
                self.sections[title.strip()] = body.rstrip() + "\n"

    def set(self, title: str, body: str) -> None:
        self.sections[title] = body.rstrip() + "\n"
        text = "# GPU check\n\n" + "\n".join(f"## {t}\n\n{b}" for t, b in self.sections.items()) + self.block()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.path.write_text(text)
        print(f"== {title}\n{body}", flush=True)

    def block(self) -> str:
        """The README block: the card and versions (:data:`README_DEVICE` of the Device section), then
        each of :data:`README_SECTIONS` that is set, its title in bold."""
        device = [line for line in self.sections.get("Device", "").splitlines()
                  if line.startswith(tuple(f"- {k}:" for k in README_DEVICE))]
        parts = ["; ".join(line[2:] for line in device)] if device else []
        parts += [f"**{t}.**" + ("\n\n" if self.sections[t].startswith("|") else " ") + self.sections[t].rstrip()
                  for t in README_SECTIONS if t in self.sections]  # a table starts on its own line
        return "\n<!-- gpu:begin -->\n" + "\n\n".join(parts) + "\n<!-- gpu:end -->\n" if parts else ""


def code_commit() -> str:
    """The commit of the code that runs: git's, else the one ``scripts/gpu_carry.sh`` wrote into
    ``.gpu_carry/commit`` (the working tree travels to a lent machine without ``.git``)."""
    from denoiser.report.provenance import git_commit

    commit = git_commit()  # "unknown" outside a git checkout
    carried = ROOT / ".gpu_carry" / "commit"
    if commit == "unknown" and carried.is_file():
        commit = carried.read_text().strip() or "unknown"
    return commit


def timed_out(deadline: float, report: Report, title: str) -> bool:
    if time.monotonic() < deadline:
        return False
    report.set(title, "not run: time budget spent")
    return True


def error_line(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"[:200]


# ----------------------------------------------------------------------------- inference


def inference_rows(cfg: DictConfig, peaks: dict, deadline: float, report: Report) -> list[dict]:
    from denoiser.configs import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.inference.backends import load_backend
    from denoiser.inference.cuda_backend import cuda_event_times, step_traffic
    from denoiser.measure import count_flops, summarize
    from denoiser.recurrent import RecurrentRunner
    from denoiser.tables import markdown_table

    inf = cfg.inference
    h, w = (int(v) for v in inf.size)
    frames = [{k: v.cuda() for k, v in random_frame(1, h, w, seed=s).items()} for s in range(2)]
    parity = [(frames[i % 2], i == 0) for i in range(int(inf.parity_frames))]
    nets, flops, references, traffic, rows = {}, {}, {}, {}, []
    columns = ["method", "backend", "ms", "target_ms", "gflop", "tflop_s", "share_peak", "floor_mb", "share_bw",
               "ops_gb", "mem_gib", "rel_err", "wall_s", "status"]
    for spec in inf.rows:
        spec = dict(spec)
        row = {"method": spec.pop("method"), "backend": spec.get("label", spec["backend"]),
               "target_ms": spec.pop("target_ms", None), "status": "ok"}
        name = spec.pop("net")
        rows.append(row)
        if time.monotonic() > deadline:
            row["status"] = "not run: time budget"
            continue
        try:
            if name not in nets:
                torch.manual_seed(0)
                nets[name] = build_net(compose_net_config(name)).eval()
                flops[name] = count_flops(nets[name], h, w) / 1e9
                with torch.inference_mode():
                    fp32 = copy.deepcopy(nets[name]).cuda()
                    references[name] = [o.clone() for o in RecurrentRunner(fp32.step).run(parity)]
                    del fp32
                torch.cuda.empty_cache()
            key = spec.pop("backend")
            backend = load_backend(key, f"inference.rows: {key}", **spec)
            row["backend"] = backend.label
            reason = backend.available()
            if reason:
                row["status"] = f"skipped: {reason}"
                continue
            dtype = getattr(backend, "dtype", "fp32")
            if (name, dtype) not in traffic:
                traffic[(name, dtype)] = step_traffic(nets[name], h, w, dtype if dtype in ("fp16", "bf16") else "fp32")
            torch.cuda.reset_peak_memory_stats()
            started = time.monotonic()
            stepper = backend.prepare(nets[name], frames[0], 1)
            ms = summarize(cuda_event_times(stepper, frames, int(inf.warmup), int(inf.repeats)))["median"]
            outputs = list(RecurrentRunner(stepper.step).run(parity))
            err = max(((o.float() - r).abs().max() / r.abs().max()).item() for o, r in zip(outputs, references[name]))
            floor = traffic[(name, dtype)]["floor"]
            peak = peaks.get("tflops_bf16" if dtype == "bf16" else "tflops_fp16", float("nan"))
            row.update(ms=ms, gflop=flops[name], tflop_s=flops[name] / ms, share_peak=flops[name] / ms / peak,
                       floor_mb=floor / 1e6, share_bw=floor / (peaks["gbps"] * 1e6) / ms,
                       ops_gb=traffic[(name, dtype)]["ops"] / 1e9, mem_gib=torch.cuda.max_memory_allocated() / 2**30,
                       rel_err=err, wall_s=time.monotonic() - started)
            del stepper
        except Exception as exc:  # noqa: BLE001 - one row's failure is reported, the others go on
            row["status"] = error_line(exc)
            traceback.print_exc()
        torch.cuda.empty_cache()
        report.set("Inference", inference_text(rows, columns, h, w, markdown_table))
    return rows


def inference_text(rows, columns, h, w, markdown_table) -> str:
    return (f"One recurrent step with history at {w}x{h}, frames already on the GPU; ms: CUDA events, median. "
            "share_peak: TFLOP/s over the measured matmul peak of the row's precision; floor_mb: bytes a step must "
            "move (weights, inputs, state in and out, output); share_bw: the time those take at the measured copy "
            "bandwidth over the step's time; ops_gb: op-by-op traffic of eager execution; rel_err: max |out - "
            "eager fp32| / max |eager fp32| over the parity frames; wall_s includes warm-up, compilation and "
            "capture.\n\n" + markdown_table(rows, columns, {
                "ms": ".2f", "gflop": ".1f", "tflop_s": ".1f", "share_peak": ".1%", "floor_mb": ".0f",
                "share_bw": ".1%", "ops_gb": ".1f", "mem_gib": ".2f", "rel_err": ".1e", "wall_s": ".0f"}))


# ----------------------------------------------------------------------------- training


def train_step(net: torch.nn.Module, opt: torch.optim.Optimizer, loss_fn: torch.nn.Module, window: dict,
               reference: torch.Tensor, reset: torch.Tensor):
    """One training step as a closure returning the loss (a detached scalar): forward under bf16 autocast
    on the window's device, ``DenoiseLoss`` (its per-item terms ``[B]`` averaged over the batch and
    summed, as the Lightning module does), backward, optimizer step.

    ``window``: the frame buffers ``[B, T, C, H, W]``; ``reference: [B, T, 3, H, W]``; ``reset: [B, T]``.
    """
    def step() -> torch.Tensor:
        with torch.autocast(reference.device.type, dtype=torch.bfloat16):
            outputs, _, _ = net(window, reset=reset)
        terms = loss_fn(outputs.float(), reference, window["motion"], reset)
        loss = sum(term.mean() for term in terms.values())
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        return loss.detach()
    return step


def train_step_rows(cfg: DictConfig, deadline: float, report: Report) -> list[dict]:
    from denoiser.configs import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.lit.losses import DenoiseLoss
    from denoiser.measure import summarize
    from denoiser.tables import markdown_table

    ts = cfg.train_step
    b, t, s = int(ts.batch), int(ts.window), int(ts.crop)
    seq = [random_frame(b, s, s, seed=i, kind="hard") for i in range(t)]
    window = {k: torch.stack([f[k] for f in seq], dim=1).cuda() for k in seq[0]}
    reference = window["color"] * 0.5
    reset = torch.zeros(b, t, dtype=torch.bool, device="cuda")
    reset[:, 0] = True
    loss_fn = DenoiseLoss().cuda()
    rows = []
    for spec in ts.rows:
        row = {**dict(spec), "status": "ok"}
        rows.append(row)
        if time.monotonic() > deadline:
            row["status"] = "not run: time budget"
            continue
        try:
            torch.manual_seed(0)
            net = build_net(compose_net_config(spec.net)).cuda().train()
            if spec.channels_last:
                net = net.to(memory_format=torch.channels_last)
            opt = torch.optim.AdamW(net.parameters(), lr=1e-4, fused=bool(spec.fused))
            if spec.compile:
                net.compile()

            step = train_step(net, opt, loss_fn, window, reference, reset)
            started = time.monotonic()
            times = []
            for i in range(int(ts.warmup) + int(ts.repeats)):
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                step()
                end.record()
                end.synchronize()
                if i >= int(ts.warmup):
                    times.append(start.elapsed_time(end))
            row.update(ms=summarize(times)["median"], frames_s=b * t / summarize(times)["median"] * 1e3,
                       mem_gib=torch.cuda.max_memory_allocated() / 2**30, wall_s=time.monotonic() - started)
        except Exception as exc:  # noqa: BLE001
            row["status"] = error_line(exc)
            traceback.print_exc()
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
        report.set("Training step", f"Batch {b}, window {t}, {s}x{s}, bf16 autocast: forward, DenoiseLoss, "
                   "backward, AdamW; CUDA events, median of the timed steps.\n\n" + markdown_table(
                       rows, ["net", "channels_last", "fused", "compile", "ms", "target_ms", "frames_s", "mem_gib",
                              "wall_s", "status"], {"ms": ".1f", "frames_s": ".0f", "mem_gib": ".2f", "wall_s": ".0f"}))
    return rows


def loader_rate(overrides: list[str], batches: int) -> float:
    """Frames/s the training data module delivers alone (after its first batch)."""
    from denoiser.configs import compose_config, instantiate_config

    cfg = compose_config(overrides, "train")
    dm = instantiate_config(cfg.data, "data")
    dm.setup("fit")

    def cycle():  # epochs after epochs: a few short sequences give fewer batches than asked for
        while True:
            yield from dm.train_dataloader()

    loader = cycle()
    next(loader)
    frames, started = 0, time.monotonic()
    for _ in range(batches):
        batch = next(loader)
        frames += batch["color"].shape[0] * batch["color"].shape[1]
    return frames / (time.monotonic() - started)


def train_run(cfg: DictConfig, root: Path, out: Path, step_rows: list[dict], report: Report) -> Path | None:
    """The short training run; returns its last checkpoint (None when there is none)."""
    run_dir = out / "train"
    overrides = [*cfg.train_run.overrides, f"data.root={root}"]
    if not (root / "val").is_dir():
        overrides.append("data.val_split=null")
    lines = [f"`python train.py {' '.join(overrides)}`", ""]
    started = time.monotonic()
    try:
        proc = subprocess.run([sys.executable, str(ROOT / "train.py"), *overrides, f"hydra.run.dir={run_dir}"],
                              check=False, capture_output=True, text=True, timeout=int(cfg.train_run.timeout_s),
                              cwd=ROOT)
        (out / "train.log").write_text(proc.stdout + proc.stderr)
        lines.append(f"exit {proc.returncode} after {time.monotonic() - started:.0f} s (log: train.log)")
        if proc.returncode:
            lines += ["", "```", *(proc.stderr.strip().splitlines()[-8:]), "```"]
    except subprocess.TimeoutExpired:
        lines.append(f"killed after {cfg.train_run.timeout_s} s")
    ckpt = run_dir / "checkpoints" / "last.ckpt"
    lines.append(f"checkpoint: {'train/checkpoints/last.ckpt' if ckpt.exists() else 'none'}")
    try:
        delivered = loader_rate(overrides, int(cfg.train_run.loader_batches))
        needed = next((r["frames_s"] for r in step_rows if r.get("frames_s") and r["net"] == "student"
                       and r["channels_last"] and not r["compile"]), None)
        lines.append(f"data module alone: {delivered:.0f} frames/s delivered; the student's training step "
                     f"needs {needed:.0f} frames/s (training-step table, 128x128 crops)" if needed else
                     f"data module alone: {delivered:.0f} frames/s delivered")
    except Exception as exc:  # noqa: BLE001
        lines.append(f"data module rate: {error_line(exc)}")
    report.set("Training run", "\n".join(lines))
    return ckpt if ckpt.exists() else None


def overall_table(metrics_md: str) -> str:
    """The table of the "Overall" section of denoiser-eval's ``metrics.md``."""
    section = metrics_md.split("## Overall", 1)[-1]
    return "\n".join(line for line in section.split("\n## ", 1)[0].splitlines() if line.startswith("|"))


def cpu_eval(cfg: DictConfig, root: Path, ckpt: Path, out: Path, report: Report) -> None:
    """``ckpt`` evaluated on this machine's CPU (CUDA hidden) on the first split of ``root`` there is."""
    from denoiser.machine import cpu_model

    split = next((s for s in ("test", "val", "train") if (root / s).is_dir()), "train")
    overrides = ["data=demo", f"data.root={root}", f"split={split}", f"ckpt={{gpu_student: {ckpt}}}",
                 "device=cpu", f"out_dir={out / 'eval'}", f"hydra.run.dir={out / 'eval'}", f"purpose='{cfg.eval.purpose}'",
                 *([f"ledger={cfg.eval.ledger}"] if cfg.eval.get("ledger") else []), *cfg.eval.overrides]
    env = {**os.environ, "CUDA_VISIBLE_DEVICES": ""}  # the CPU: the checkpoint loads with map_location=cpu
    try:
        proc = subprocess.run([sys.executable, "-m", "denoiser.commands.evaluate", *overrides], check=False,
                              capture_output=True, text=True, timeout=int(cfg.eval.timeout_s), cwd=ROOT, env=env)
        table = out / "eval" / "metrics.md"
        body = overall_table(table.read_text()) if proc.returncode == 0 and table.exists() else \
            "```\n" + "\n".join(proc.stderr.strip().splitlines()[-8:]) + "\n```"
        report.set("CPU evaluation of the GPU-trained checkpoint",
                   f"`{ckpt.name}` on {cpu_model()}, CUDA hidden; split {split} of `{root.name}`, exit "
                   f"{proc.returncode}\n\n{body}")
    except subprocess.TimeoutExpired:
        report.set("CPU evaluation of the GPU-trained checkpoint", f"killed after {cfg.eval.timeout_s} s")


# ----------------------------------------------------------------------------- the check


def run(cfg: DictConfig) -> dict:
    from denoiser.inference.cuda_backend import device_report, gpu_peaks
    from denoiser.tables import write_csv

    out = Path(cfg.out)
    report = Report(out / "gpu.md", keep=bool(cfg.keep_report))
    root = Path(cfg.data_root or os.path.join(os.environ.get("DENOISER_DATA", "data"), "demo")).resolve()
    if list(cfg.sections) == ["cpu_eval"]:  # a checkpoint the GPU trained, evaluated where this runs
        if not cfg.eval_ckpt:
            raise ConfigError("sections=[cpu_eval] needs eval_ckpt=<the GPU-trained checkpoint>")
        cpu_eval(cfg, root, Path(cfg.eval_ckpt).resolve(), out, report)
        return {"ckpt": str(cfg.eval_ckpt)}
    info = {"run id": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()), "commit": code_commit(),
            **device_report()}
    report.set("Device", "\n".join(f"- {k}: {v}" for k, v in info.items()))
    if not torch.cuda.is_available():
        report.set("Result", "no CUDA device: nothing measured")
        return {"device": info}
    deadline = time.monotonic() + float(cfg.budget_s)
    peaks = gpu_peaks()
    report.set("Device", "\n".join(f"- {k}: {v}" for k, v in info.items()) + "\n" + "\n".join(
        [f"- measured fp16 matmul: {peaks['tflops_fp16']:.0f} TFLOP/s, bf16: {peaks['tflops_bf16']:.0f} TFLOP/s",
         f"- measured copy bandwidth: {peaks['gbps']:.0f} GB/s (read + write)"]))
    sections = set(cfg.sections)
    rows = inference_rows(cfg, peaks, deadline, report) if "inference" in sections else []
    step_rows = [] if "train_step" not in sections or timed_out(deadline, report, "Training step") \
        else train_step_rows(cfg, deadline, report)
    write_csv(out / "rows.csv", [{"section": "inference", **r} for r in rows] +
              [{"section": "train_step", **r} for r in step_rows])
    if "train_run" not in sections:
        return {"device": info, "inference": rows, "train_step": step_rows}
    if not (root / "train").is_dir():
        report.set("Training run", f"not run: no {root}/train")
        return {"device": info, "inference": rows, "train_step": step_rows}
    if timed_out(deadline, report, "Training run"):
        return {"device": info, "inference": rows, "train_step": step_rows}
    ckpt = train_run(cfg, root, out, step_rows, report)
    if ckpt is not None:
        cpu_eval(cfg, root, ckpt, out, report)
    return {"device": info, "inference": rows, "train_step": step_rows, "ckpt": str(ckpt)}


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "gpu_check")()


if __name__ == "__main__":
    main()
