"""Run a pipeline: its stages in order, the jobs of a stage side by side, a time row per stage.

The pipeline's config (``conf/pipeline.yaml`` with a ``pipeline/`` choice) holds ``stages`` (see
:mod:`denoiser.pipeline.stages`), ``timings`` (the table's path), ``needs`` (``{path: what}``,
checked before anything runs) and ``finish`` (lines printed at the end, files whose text follows).
A stage's ``${...}`` values are resolved when it starts, so ``${best:<run dir>}`` is the
checkpoint an earlier stage left. Skipping and resuming belong to the commands where they can
(``denoiser-train``'s ``skip_done`` and ``ckpt_path=auto``, ``denoiser-render`` keeping frames);
a stage with ``produces`` is skipped here when it finished there on the same command lines.

A failed job stops the pipeline: jobs not yet started are not started, the running ones finish,
and :class:`StageFailed` names the stage, the job and its log.
"""

from __future__ import annotations

import glob
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import FIRST_EXCEPTION, ThreadPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

from denoiser.errors import ConfigError, UserError
from denoiser.pipeline.stages import Job, check_stage, choose_checkpoints, ckpt_override, expand, expand_needs
from denoiser.pipeline.timings import TimingTable

#: the file a ``produces`` folder holds once its stage finished: the stage's command lines
INPUTS_FILE = "pipeline_inputs.txt"
#: commands that take ``threads=N`` (their torch threads)
THREADED = frozenset({"train", "eval", "bench", "pareto"})


class StageFailed(UserError):
    """A stage's command failed: one line naming the stage (and job, and its log)."""

    def __init__(self, message: str, code: int = 3):
        super().__init__(message)
        self.code = code


@dataclass
class Context:
    """Where commands come from and how the run goes. ``bin_dir``: the folder of the console
    commands (``denoiser-train`` ...), by default the running Python's; ``python``: the interpreter
    for ``module`` stages; ``cores``: shared among side-by-side jobs; ``dry_run``: print the
    command lines, run nothing; ``say``: where progress lines go."""

    bin_dir: Path = field(default_factory=lambda: Path(sys.executable).parent)
    python: str = sys.executable
    cores: int = field(default_factory=lambda: os.cpu_count() or 1)
    dry_run: bool = False
    say: Callable[[str], None] = print
    live: set = field(default_factory=set)
    lock: threading.Lock = field(default_factory=threading.Lock)


def argv_of(stage: Mapping, job: Job, ctx: Context, threads: int | None) -> list[str]:
    """The command line of one job."""
    if stage.get("module"):
        head = [str(stage.get("python") or ctx.python), "-m", str(stage["module"])]
    elif stage.get("script"):
        head = [str(stage.get("python") or ctx.python), str(stage["script"])]
    else:
        head = [str(ctx.bin_dir / f"denoiser-{stage['command']}")]
    args = list(job.args) + list(job.extra)
    if threads is not None and stage.get("command") in THREADED:
        args.append(f"threads={threads}")
    if job.run_dir:
        args += ["skip_done=true", "ckpt_path=auto", f"hydra.run.dir={job.run_dir}"]
    return head + args


def job_threads(stage: Mapping, ctx: Context) -> int | None:
    threads = stage.get("threads")
    if threads in (None, "null"):
        return None
    if threads == "auto":
        return max(1, ctx.cores // max(1, int(stage.get("jobs") or 1)))
    return int(threads)


def _run_job(name: str, stage: Mapping, job: Job, ctx: Context, threads: int | None, log: Path | None) -> None:
    argv = argv_of(stage, job, ctx, threads)
    side_by_side = log is not None
    if side_by_side:
        ctx.say(f"==> [{job.name}]")
    env = dict(os.environ)
    if threads is not None:
        env["OMP_NUM_THREADS"] = str(threads)
    t0 = time.monotonic()
    if side_by_side:
        log.parent.mkdir(parents=True, exist_ok=True)
    out = open(log, "w") if side_by_side else None  # noqa: SIM115 - closed below
    try:
        # its own process group, so that a stopped pipeline stops the whole job (a command's children too)
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT if out else None, env=env,
                                start_new_session=True)
        with ctx.lock:
            ctx.live.add(proc)
        code = proc.wait()
        with ctx.lock:
            ctx.live.discard(proc)
    finally:
        if out:
            out.close()
    if code != 0:
        where = f", see {log}" if side_by_side else ""
        raise StageFailed(f"[{name}] {job.name} failed (exit {code}){where}")
    if job.run_dir and (Path(job.run_dir) / "COLLAPSED").is_file():
        line = (Path(job.run_dir) / "COLLAPSED").read_text().strip()
        if stage.get("on_collapse", "stop") == "stop":
            raise StageFailed(f"[{name}] {job.name}: {line}")
        ctx.say(f"warning: [{job.name}] {line} (kept, marked in the summary)")
    if side_by_side:
        ctx.say(f"<== [{job.name}] {time.monotonic() - t0:.0f}s")


def _log_path(name: str, job: Job, report: Path) -> Path:
    return Path(job.run_dir + ".log") if job.run_dir else report / "logs" / f"{name}_{job.name}.log"


def run_jobs(name: str, stage: Mapping, jobs: list[Job], ctx: Context, report: Path) -> None:
    """Every job of a stage, ``stage['jobs']`` side by side (each with its log beside its run)."""
    width = max(1, int(stage.get("jobs") or 1))
    threads = job_threads(stage, ctx)
    if width == 1 or len(jobs) == 1:
        for job in jobs:
            _run_job(name, stage, job, ctx, threads, None)  # one at a time: its output inline
        return
    with ThreadPoolExecutor(max_workers=width) as pool:
        futures = [pool.submit(_run_job, name, stage, job, ctx, threads, _log_path(name, job, report)) for job in jobs]
        done, pending = wait(futures, return_when=FIRST_EXCEPTION)
        failed = [f for f in done if f.exception() is not None]
        if failed:
            for f in pending:
                f.cancel()  # not started: never started; running: finish
            wait(pending)
            raise failed[0].exception()


def _copy(stage: Mapping, name: str) -> None:
    for pair in stage.get("copy") or []:
        if not isinstance(pair, (list, tuple)) or len(pair) != 2:
            raise ConfigError(f"stages.{name}.copy: {pair!r}: give [source, destination] pairs")
        source, destination = str(pair[0]), Path(pair[1])
        if glob.has_magic(str(source)):
            matches = sorted(glob.glob(str(source)))
            if matches:
                destination.mkdir(parents=True, exist_ok=True)
            for match in matches:
                shutil.copy2(match, destination / Path(match).name)
            continue
        source = Path(source)
        if not source.exists():
            raise StageFailed(f"[{name}] {source}: does not exist (nothing to copy to {destination})")
        destination.parent.mkdir(parents=True, exist_ok=True)
        if source.is_dir():
            shutil.rmtree(destination, ignore_errors=True)
            shutil.copytree(source, destination)
        else:
            shutil.copy2(source, destination)


def _inputs_text(stage: Mapping, jobs: list[Job], ctx: Context) -> str:
    threads = job_threads(stage, ctx)
    return "".join(shlex.join(argv_of(stage, job, ctx, threads)[1:]) + "\n" for job in jobs)


def done_before(folder: Path, text: str) -> bool:
    """``folder`` holds :data:`INPUTS_FILE` with ``text`` and no checkpoint ``text`` names is newer."""
    record = folder / INPUTS_FILE
    if not record.is_file() or record.read_text() != text:
        return False
    stamp = record.stat().st_mtime
    for token in shlex.split(text.replace("\n", " ")):
        for part in token.replace("{", " ").replace("}", " ").replace(",", " ").split():
            part = part.split("=", 1)[-1]
            if part.endswith(".ckpt") and Path(part).exists() and Path(part).stat().st_mtime > stamp:
                return False
    return True


def reused_work(folder: str, pattern: str, since: float) -> bool:
    """``folder`` holds files matching ``pattern`` and none was written at ``since`` or later: the
    stage's command reused an earlier run's work (one walk over the folder)."""
    if not Path(folder).is_dir():
        return False
    times = [p.stat().st_mtime for p in Path(folder).rglob(pattern)]
    return bool(times) and max(times) < since


def resolved_stage(cfg, name: str) -> dict:
    """Stage ``name`` of ``cfg.stages`` as plain data, its ``${...}`` resolved now."""
    from omegaconf import OmegaConf

    stage = OmegaConf.to_container(cfg.stages[name], resolve=True)
    check_stage(name, stage)
    return stage


def check_needs(needs) -> None:
    """UserError (one line: the path and what it is) for the first ``needs`` entry missing."""
    for path, what in expand_needs(needs):
        if not Path(path).exists():
            raise UserError(f"{path}: {what} missing")


def check_existing(name: str, stage: Mapping, jobs: list[Job]) -> None:
    """Runs made elsewhere (``existing``): each must be finished, else one line with the message."""
    for job in jobs:
        if not job.run_dir or not (Path(job.run_dir) / "DONE").is_file():
            raise UserError(f"{job.run_dir or job.name}: {stage['existing']}")


def _interrupted(signum, frame):
    raise KeyboardInterrupt  # a killed pipeline stops its running commands (they resume next time)


def run_pipeline(cfg, ctx: Context | None = None) -> Path | None:
    """Run every stage of ``cfg`` (see the module docstring); returns the time table's path (None
    in a dry run). Raises :class:`StageFailed` for a failed stage, ConfigError for a bad stage."""
    ctx = ctx or Context()
    if not cfg.get("stages"):
        raise ConfigError("stages: the pipeline has no stages")
    from omegaconf import OmegaConf

    if not ctx.dry_run and cfg.get("needs"):
        check_needs(OmegaConf.to_container(cfg.needs, resolve=True))
    report = Path(cfg.report)
    table = None if ctx.dry_run else TimingTable(Path(cfg.timings))
    jobs_of: dict[str, list[Job]] = {}

    def jobs(stage_name: str) -> list[Job]:
        if stage_name not in jobs_of:
            jobs_of[stage_name] = expand(stage_name, resolved_stage(cfg, stage_name))
        return jobs_of[stage_name]

    previous = {signal.SIGTERM: signal.getsignal(signal.SIGTERM)} if threading.current_thread() is threading.main_thread() else {}
    if previous:
        signal.signal(signal.SIGTERM, _interrupted)
    try:
        for name in cfg.stages:
            stage = resolved_stage(cfg, name)
            if stage.get("if_exists") and not Path(stage["if_exists"]).exists():
                for path in stage.get("otherwise_remove") or []:
                    shutil.rmtree(path, ignore_errors=True) if Path(path).is_dir() else Path(path).unlink(missing_ok=True)
                ctx.say(f"==> [{name}] skipped: {stage['if_exists']} does not exist")
                continue
            if stage.get("unless_exists") and Path(stage["unless_exists"]).exists():
                ctx.say(f"==> [{name}] skipped: {stage['unless_exists']} exists")
                continue
            if "when" in stage and not stage["when"]:
                ctx.say(f"==> [{name}] skipped: its when is false")
                continue
            stage_jobs = [] if stage.get("copy") else expand(name, stage)
            jobs_of[name] = stage_jobs
            if stage.get("existing"):
                if not ctx.dry_run:
                    check_existing(name, stage, stage_jobs)
                continue
            if stage.get("checkpoints"):
                chosen = choose_checkpoints(stage["checkpoints"], {s: jobs(s) for s in stage["checkpoints"].get("stages") or []})
                for job in stage_jobs:
                    job.extra.append(ckpt_override(chosen))
            _run_stage(name, stage, stage_jobs, ctx, report, table)
    except KeyboardInterrupt:
        with ctx.lock:
            for proc in list(ctx.live):
                try:
                    os.killpg(proc.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        raise
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if table is None:
        return None
    path = table.end()
    for line in cfg.get("finish") or []:
        ctx.say(str(line))
    return path


def _run_stage(name: str, stage: Mapping, jobs: list[Job], ctx: Context, report: Path, table) -> None:
    if ctx.dry_run:
        threads = job_threads(stage, ctx)
        for job in jobs:
            ctx.say(f"[{name}] {shlex.join(argv_of(stage, job, ctx, threads))}")
        if stage.get("copy"):
            ctx.say(f"[{name}] copy {stage['copy']}")
        return
    produces = Path(stage["produces"]) if stage.get("produces") else None
    inputs = _inputs_text(stage, jobs, ctx) if produces else ""
    if produces and done_before(produces, inputs):
        ctx.say(f"==> [{name}] {produces}: the same command lines, done before")
        table.add(name, 0, reused=True)
        return
    first = jobs[0] if jobs else None
    shown = shlex.join(argv_of(stage, first, ctx, job_threads(stage, ctx))) if first else f"copy {stage['copy']}"
    ctx.say(f"==> [{name}] {shown}" + (f" (and {len(jobs) - 1} more, {stage.get('jobs') or 1} at a time)" if len(jobs) > 1 else ""))
    t0, wall = time.monotonic(), time.time()
    reuse = stage.get("reuse")
    try:
        if stage.get("copy"):
            _copy(stage, name)
        else:
            run_jobs(name, stage, jobs, ctx, report)
    except StageFailed:
        ctx.say(f"<== [{name}] failed after {time.monotonic() - t0:.0f}s")
        raise
    seconds = time.monotonic() - t0
    reused = bool(reuse) and reused_work(reuse["dir"], reuse["pattern"], wall)
    table.add(name, seconds, reused=reused)
    if produces:
        produces.mkdir(parents=True, exist_ok=True)
        (produces / INPUTS_FILE).write_text(inputs)
    ctx.say(f"<== [{name}] {seconds:.0f}s" + (" (an earlier run's work, reused)" if reused else ""))
