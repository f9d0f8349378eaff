"""Train a denoiser: the teacher, the student, or the student by distillation (docs/design.md §5).

    python train.py model=teacher|student|distill [net=... kernel=... ablation=... data=... trainer=...]
    python train.py experiment=demo_teacher                     # the demo's teacher (CPU widths)
    python train.py -m experiment=demo ablation=none,no_pyramid,no_temporal    # a sweep
    python train.py <overrides> hydra.run.dir=<run dir> ckpt_path=last         # resume that run
    python train.py --cfg job                                   # print the composed config

A Hydra app over ``conf/train.yaml``: the data module, the Lightning module (``model``), the
trainer, logger and callbacks are all built from their ``_target_`` configs. Everything a run
writes lives in its run directory: ``checkpoints/{last,best}.ckpt``, ``tb/`` (TensorBoard:
scalars, image panels, hparams with the final validation metrics) and ``.hydra/`` (the
composed config). See docs/training.md.
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path
from typing import Any

import hydra
from omegaconf import DictConfig, OmegaConf

from denoiser.commands.app import guarded, hydra_runtime
from denoiser.conf import CONF_DIR
from denoiser.configs import group_options, instantiate_config, job_dirname
from denoiser.errors import ConfigError

# conf/train.yaml's hydra.sweep.subdir: a multirun job's folder named from its overrides
OmegaConf.register_new_resolver("job_dirname", job_dirname, replace=True)
# conf/train.yaml's --help: each group's options, read from its folder (${options:<group>})
OmegaConf.register_new_resolver("options", group_options, replace=True)

#: prefix of the final validation metrics logged together with the hyperparameters
FINAL_PREFIX = "final/"


def in_submitit_job() -> bool:
    """True inside a job started by submitit (SLURM, or its local executor): ``SUBMITIT_EXECUTOR`` is set."""
    return bool(os.environ.get("SUBMITIT_EXECUTOR"))


def resolve_ckpt_path(ckpt_path: str | None, output_dir: str) -> str | None:
    """``None`` (fresh start; in a submitit job the same as ``auto``), ``last``
    (``<output_dir>/checkpoints/last.ckpt``, which must exist), ``auto`` (that file when it
    exists, else a fresh start) or an existing file."""
    if ckpt_path in (None, "", "null"):
        if not in_submitit_job():
            return None
        ckpt_path = "auto"  # a requeued SLURM job (preemption, timeout) continues where it stopped
    last = Path(output_dir) / "checkpoints" / "last.ckpt"
    if ckpt_path == "auto":
        return str(last) if last.is_file() else None
    path = last if ckpt_path == "last" else Path(ckpt_path)
    if not path.is_file():
        hint = " (resume a run with hydra.run.dir=<its run dir> ckpt_path=last)" if ckpt_path == "last" else ""
        raise ConfigError(f"ckpt_path={ckpt_path}: {path} does not exist{hint}")
    return str(path)


def flat_hparams(cfg: DictConfig) -> dict[str, Any]:
    """The resolved run config as ``{"model/loss/kd_weight": 1.0, ...}`` (lists as strings)."""
    def walk(node: Any, prefix: str, out: dict) -> dict:
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{prefix}{k}/", out)
        else:
            out[prefix[:-1]] = node if isinstance(node, (int, float, str, bool)) or node is None else str(node)
        return out

    container = OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)
    return {k: ("null" if v is None else v) for k, v in walk(container, "", {}).items()}


def final_metrics(trainer) -> dict[str, float]:
    """The last validation metrics ``{"val/psnr": ..}`` the trainer holds."""
    return {k: float(v) for k, v in trainer.callback_metrics.items() if k.startswith("val/")}


def measure_time(cfg: DictConfig, net) -> dict[str, float]:
    """The time objective (``objectives.time``): ms per frame of the trained ``net`` at
    ``objectives.time.size`` on its backend (a name of the config group ``conf/backends/``, as
    ``denoiser-pareto``'s ``backend``); ``{}`` when not configured."""
    from denoiser.inference.backends import backend_names, load_backend, resolve_backend
    from denoiser.report.pareto import time_network

    spec = (cfg.get("objectives") or {}).get("time")
    if not spec:
        return {}
    if not isinstance(spec.get("backend"), str):
        raise ConfigError(f"objectives.time.backend: a name of conf/backends/ ({', '.join(backend_names())}), "
                          f"got {spec.get('backend')!r}")
    name, overrides = resolve_backend(spec.backend, key="objectives.time.backend")
    backend = load_backend(name, "objectives.time.backend", **overrides)
    row = time_network(net, backend, list(spec.size), threads=spec.get("threads"), warmup=int(spec.get("warmup", 2)),
                       repeats=int(spec.get("repeats", 3)))
    if row["status"] != "ok":
        raise ConfigError(f"objectives.time.backend: {row['status']}")
    return {"time/ms": row["ms_median"], "time/ms_min": row["ms_min"]}


#: override keys that change how a run executes, not what it trains: a finished run asked for
#: again with other values of these is the same run (skip_done)
RUN_ENVIRONMENT = ("threads", "skip_done", "ckpt_path", "trust_checkpoint", "trainer.enable_progress_bar",
                   "callbacks.progress", "hydra")


def _environment(key: str) -> bool:
    return any(key == k or key.startswith((k + ".", k + "/")) for k in RUN_ENVIRONMENT)


def same_overrides(a: list[str], b: list[str]) -> bool:
    """Whether two command lines' overrides ask for the same run: the same set of (key, value)
    as Hydra parses them, less the :data:`RUN_ENVIRONMENT` keys, so ``skip_done=true`` (a single
    run, as typed) equals ``skip_done=True`` (the same value in a multirun job, which Hydra writes
    back), ``threads=1`` equals ``threads=2`` and the order does not count."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    def canonical(overrides: list[str]) -> list[str]:
        parser = OverridesParser.create()
        return sorted(repr((o.type.name, o.key_or_group, o.package, o.value()))
                      for o in parser.parse_overrides(overrides) if not _environment(o.key_or_group))

    try:
        return canonical(list(a)) == canonical(list(b))
    except Exception:  # noqa: BLE001 - an override Hydra cannot parse: the strings decide
        return list(a) == list(b)


def same_config(a: list[str], b: list[str], config_name: str = "train") -> bool:
    """Whether two override lists compose the same ``config_name`` config, less the
    :data:`RUN_ENVIRONMENT` keys (unresolved, so ``${...}`` compare as written): ``ablation=X``
    asks for the same run as no ablation once the recipe itself holds X's values."""
    from omegaconf import OmegaConf

    from denoiser.configs import compose_config

    def composed(overrides: list[str]) -> dict:
        cfg = OmegaConf.to_container(compose_config(overrides, config_name), resolve=False)
        for key in RUN_ENVIRONMENT:
            *parents, leaf = key.split(".")
            node = cfg
            for part in parents:
                node = node.get(part) if isinstance(node, dict) else None
            if isinstance(node, dict):
                node.pop(leaf, None)
        return cfg

    try:
        return composed(a) == composed(b)
    except Exception:  # noqa: BLE001 - stored overrides that no longer compose: not the same run
        return False


def stored_run(cfg: DictConfig) -> dict[str, float] | None:
    """With ``skip_done``, the metrics of a finished run of the same overrides in this run
    directory (DONE and metrics.json): :func:`same_overrides`, else overrides that compose the
    same config (:func:`same_config`); a run of another config there is an error."""
    from denoiser.report.pareto import DONE_FILE, METRICS_FILE, read_json

    out = Path(cfg.output_dir)
    if not cfg.get("skip_done") or not (out / DONE_FILE).is_file():
        return None
    stored = read_json(out / METRICS_FILE)
    overrides = hydra_runtime()[0]
    old = stored.get("overrides")
    if old is not None and not same_overrides(old, overrides) and not same_config(old, overrides):
        raise ConfigError(f"skip_done: {out} holds a finished run of other overrides ({' '.join(old)}); "
                          "use another hydra.sweep.dir")
    print(f"{out}: finished before, skipped (skip_done=true)", file=sys.stderr)
    return stored.get("metrics") or {}


def write_done(cfg: DictConfig, metrics: dict[str, float]) -> None:
    from denoiser.atomic import atomic_write_text
    from denoiser.report.pareto import DONE_FILE, METRICS_FILE

    out = Path(cfg.output_dir)
    atomic_write_text(out / METRICS_FILE, json.dumps({"overrides": hydra_runtime()[0], "metrics": metrics}, indent=1))
    (out / DONE_FILE).touch()


def train(cfg: DictConfig) -> dict[str, float]:
    """Run one training job from a composed config; returns the final validation metrics (and
    ``time/ms`` when ``objectives.time`` is set)."""
    import lightning.pytorch as pl
    import torch

    from denoiser.atomic import remove_stale_temporaries
    from denoiser.checkpoint import resume_weights_only

    stored = stored_run(cfg)
    if stored is not None:
        return stored

    if cfg.get("threads"):
        torch.set_num_threads(int(cfg.threads))
    pl.seed_everything(int(cfg.seed), workers=True)
    for stale in remove_stale_temporaries(Path(cfg.output_dir) / "checkpoints"):  # left by a killed write
        print(f"removed {stale} (a checkpoint write that was killed)", file=sys.stderr)
    ckpt_path = resolve_ckpt_path(cfg.get("ckpt_path"), cfg.output_dir)
    if ckpt_path:
        print(f"resuming from {ckpt_path}", file=sys.stderr)
    weights_only = resume_weights_only(ckpt_path, trust=bool(cfg.get("trust_checkpoint")))  # refuses pickled code
    datamodule = instantiate_config(cfg.data, "data")
    if hasattr(datamodule, "setup"):  # index and validate the data before any log or checkpoint is written
        datamodule.setup("fit")
    model = instantiate_config(cfg.model, "model")
    callbacks = [instantiate_config(c, f"callbacks.{name}") for name, c in (cfg.get("callbacks") or {}).items()
                 if c is not None]
    logger = instantiate_config(cfg.logger, "logger") if cfg.get("logger") else False
    trainer = instantiate_config(cfg.trainer, "trainer", callbacks=callbacks, logger=logger)

    trainer.fit(model, datamodule=datamodule, ckpt_path=ckpt_path, weights_only=weights_only)
    if trainer.interrupted:
        print("training interrupted; last.ckpt holds the last state", file=sys.stderr)
    validated_at = getattr(model, "validated_step", -1)
    if cfg.get("final_validation", True) and validated_at != trainer.global_step and not trainer.interrupted \
            and getattr(datamodule, "splits", {}).get("val") and not trainer.fast_dev_run:
        trainer.validate(model, datamodule=datamodule, verbose=False)
    metrics = final_metrics(trainer)
    if not trainer.interrupted:
        metrics.update(measure_time(cfg, model.net))  # after training, alone: nothing else runs in this job now
    if logger and metrics:  # TensorBoard HParams: the run's config with its final metrics (and time)
        logger.log_hyperparams(flat_hparams(cfg), metrics={FINAL_PREFIX + k.split("/", 1)[-1]: v
                                                           for k, v in metrics.items()})
        logger.finalize("success")
    if not trainer.interrupted:
        write_done(cfg, metrics)
    print(f"run directory: {cfg.output_dir}")
    print(f"  checkpoints: {Path(cfg.output_dir) / 'checkpoints'}   tensorboard: {Path(cfg.output_dir) / 'tb'}")
    if metrics:
        print("  final " + "  ".join(f"{k.split('/', 1)[-1]}={v:.4f}" for k, v in sorted(metrics.items())))
    return metrics


def objective_values(cfg: DictConfig, metrics: dict[str, float] | None) -> float | list[float] | None:
    """What a sweeper optimizes: val/psnr, or ``[val/psnr, time/ms]`` when ``objectives.time`` is set."""
    metrics = metrics or {}
    if (cfg.get("objectives") or {}).get("time"):
        return [metrics.get("val/psnr", float("nan")), metrics.get("time/ms", float("nan"))]
    return metrics.get("val/psnr")


@hydra.main(config_path=CONF_DIR, config_name="train", version_base="1.3")
def main(cfg: DictConfig) -> float | list[float] | None:
    """Hydra entry point; returns val/psnr (and ms per frame) for sweepers that optimize them."""
    return objective_values(cfg, guarded(train)(cfg))


if __name__ == "__main__":
    main()
