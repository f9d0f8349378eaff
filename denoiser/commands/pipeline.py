"""``denoiser-pipeline``: run a pipeline of ``conf/pipeline/`` (make demo, ablations, compare,
pareto, paper) as one Hydra command; its keys are config keys on the command line::

    denoiser-pipeline pipeline=demo 'seeds=[0,1,2,3,4]' jobs=2
    denoiser-pipeline pipeline=ablations 'variants=[no_pyramid,direct]'
    denoiser-pipeline pipeline=demo dry_run=true      # print the command lines, run nothing

The stages, their skipping and resuming, and the stage-time table: :mod:`denoiser.pipeline`.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

from omegaconf import DictConfig

import denoiser.pipeline  # noqa: F401 - registers ${best:<run dir>} before Hydra composes


def context(cfg: DictConfig):
    """The runner's :class:`~denoiser.pipeline.runner.Context` from the config's ``bin_dir``,
    ``python``, ``cores`` and ``dry_run`` (null: the running interpreter's, all cores)."""
    from denoiser.pipeline.runner import Context

    ctx = Context(dry_run=bool(cfg.get("dry_run", False)))
    if cfg.get("bin_dir"):
        ctx.bin_dir = Path(cfg.bin_dir)
    if cfg.get("python"):
        ctx.python = str(cfg.python)
    if cfg.get("cores"):
        ctx.cores = int(cfg.cores)
    ctx.say = say
    return ctx


def say(line: str) -> None:
    """Print a progress line; a closed stdout (``denoiser-pipeline ... dry_run=true | head``) is
    not an error: the rest goes to /dev/null and the pipeline carries on."""
    try:
        print(line, flush=True)
    except BrokenPipeError:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())


def run(cfg: DictConfig):
    """Run ``cfg``'s stages; a failed stage ends the process with its one line and exit 3."""
    from denoiser.pipeline.runner import StageFailed, run_pipeline

    try:
        table = run_pipeline(cfg, context(cfg))
    except StageFailed as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(exc.code)
    if table is not None:
        print(table.read_text(), end="")
        for path in cfg.get("show") or []:
            if Path(path).is_file():
                print(Path(path).read_text(), end="")
    return table


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "pipeline")()


if __name__ == "__main__":
    main()
