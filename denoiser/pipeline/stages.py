"""A pipeline's stages as data: what each one runs, its jobs, and the checkpoints they leave.

A pipeline (``conf/pipeline/<name>.yaml``) is an ordered mapping ``stages: {name: stage}``; a
stage is a mapping with these keys (all optional but one of ``command``, ``module``, ``copy``):

- ``command``: a console command of the package, ``train`` -> ``denoiser-train`` (also ``eval``,
  ``bench``, ``render``, ``pareto``, ``pipeline``); ``module``: ``python -m <module>`` instead;
  ``script``: ``python <file>`` (a script of the checkout, e.g. ``scripts/blender_sequences.py``); ``python``:
  the interpreter of this stage's ``module`` or ``script`` (e.g. ``.venv-blender/bin/python``, where ``bpy`` is);
  ``copy``: ``[[source, destination], ...]`` files or folders (a glob source copies every match
  into a destination folder), no command;
- ``args``: the command's ``key=value`` overrides (a list value, ``${axes}``, is spread in place;
  an empty one, ``${opt:key,${null}}``, left out);
- ``matrix``: ``{variable: values}``; the stage runs one job per combination (in the order of the
  keys, the last varying fastest). Values are a list, or a mapping ``{value: [extra args]}`` that
  adds args to the jobs of that value. ``{variable}`` in ``name``, ``args``, ``run_dir`` and
  ``ckpt`` is the job's value (``{name}``: the job's name). ``${...}`` is OmegaConf's, resolved when
  the stage starts, so ``${best:<run dir>}`` names a checkpoint an earlier stage wrote;
- ``name``: the job name's template (default: the stage's name);
- ``run_dir``: a training run's directory: ``denoiser-train`` gets ``skip_done=true
  ckpt_path=auto hydra.run.dir=<run_dir>`` (a finished run is skipped, an interrupted one resumed);
- ``ckpt``: the checkpoint a job leaves (default for a training job: :func:`best` of its run,
  looked up when a later stage chooses it);
- ``checkpoints``: ``{stages: [...], where: {variable: value or [values]}}``: adds ``ckpt={name:
  path, ...}``, the checkpoints the jobs of those stages left (a job with such a variable only when
  its value is one of ``where``'s);
- ``jobs``: how many jobs run side by side (default 1); ``threads``: torch threads per job
  (``threads=N`` and ``OMP_NUM_THREADS``; ``auto``: the cores shared among ``jobs``; null: the
  command's own default);
- ``reuse``: ``{dir, pattern}``: when the stage wrote no such file under ``dir`` its command
  reused an earlier run's work (a training run it skipped, frames a render kept): its time row is
  that run's;
- ``produces``: a folder: the stage is skipped when it finished there before with the same command
  lines and no checkpoint they name is newer (``pipeline_inputs.txt``, written last);
- ``if_exists``: run the stage only when this path exists; ``otherwise_remove``: paths removed when
  it does not (no stale table of an earlier run in a report); ``unless_exists``: skip the stage
  when this path exists (make demo's teacher, whatever its steps, instead of a shorter one); ``when``: run the
  stage only when this is true (``${eq:${teacher},own}``); a stage skipped so still gives its jobs'
  ``ckpt`` to later stages' ``checkpoints`` (make demo's ``teacher=release``);
- ``on_collapse``: ``stop`` (default) or ``warn`` when a training job leaves ``COLLAPSED``;
- ``existing``: the jobs are training runs another pipeline made (``make demo``'s students, say):
  nothing runs, each ``run_dir`` must hold ``DONE`` (else one line: the path and this message), and
  their checkpoints are there for ``checkpoints``;
- ``jobs_from``: ``{_target_: <callable>, ...}`` called when the stage starts; it returns more
  jobs, ``[{name, args, variables, run_dir, ckpt}]`` (only ``name`` needed): jobs that an earlier
  stage's output decides (the Pareto front's variants with more seeds, the runs a sweep finished).
"""

from __future__ import annotations

import itertools
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

from denoiser.checkpoint import RUN_CHECKPOINTS
from denoiser.errors import ConfigError

#: the keys a stage may have (anything else is a typo, refused by name)
STAGE_KEYS = frozenset({
    "command", "module", "copy", "args", "matrix", "name", "run_dir", "ckpt", "checkpoints", "jobs",
    "threads", "reuse", "produces", "if_exists", "otherwise_remove", "on_collapse", "existing", "jobs_from",
    "unless_exists", "script", "python", "when",
})


def optional(key: str, value) -> str:
    """``key=value``, or an empty string (an argument left out) when ``value`` is null: the
    resolver ``${opt:trainer.max_steps,${steps}}`` passes a knob only when it is set."""
    return "" if value is None else f"{key}={value}"


def given(keys, overrides) -> list[str]:
    """The pipeline's own command-line overrides (``${hydra:overrides.task}``) of ``keys``, as given:
    a key ``data`` takes ``data=...``, a key ending in ``.`` (``data.``) every ``data.<key>=...``
    (``+``/``~`` prefixes kept). The resolver ``${given:[data,data.,layout],${hydra:overrides.task}}``
    passes a user's data on to every command of a pipeline; nothing given, nothing added, so the
    defaults' command lines stay as they were."""
    keys = [str(k) for k in keys]
    out = []
    for override in overrides or []:
        key = str(override).split("=", 1)[0].lstrip("+~")
        if any(key.startswith(k) if k.endswith(".") else key == k for k in keys):
            out.append(str(override))
    return out


def unless(condition, arg: str) -> str:
    """``arg``, or an empty string (left out) when ``condition`` is true: the resolver
    ``${unless:${oidn},~baselines.oidn_fast}`` keeps a baseline out unless it is asked for."""
    return "" if condition else str(arg)


def equal(a, b) -> bool:
    """Whether ``a`` and ``b`` are the same value (as strings): the resolver ``${eq:${teacher},own}``."""
    return str(a) == str(b)


def concat(*lists) -> list:
    """The lists one after another: the resolver ``${concat:[none,no_kd],${variants}}``."""
    return [item for items in lists for item in items]


def best(run_dir: str | Path) -> str:
    """The checkpoint a training run is evaluated with: ``checkpoints/best.ckpt`` (best validation
    PSNR), else ``checkpoints/last.ckpt`` (also when neither exists yet: the path it will have)."""
    for name in RUN_CHECKPOINTS:
        if (Path(run_dir) / name).is_file():
            return str(Path(run_dir) / name)
    return str(Path(run_dir) / RUN_CHECKPOINTS[-1])


def best_on_val(metrics_csv: str | Path, runs: str | Path, prefix: str, column: str = "psnr") -> str:
    """The checkpoint (:func:`best`) of the run under ``runs`` whose method, named ``<prefix>...`` in
    ``denoiser-eval``'s ``metrics.csv`` of a val split, has the highest mean ``column`` (its
    ``sequence == "mean"`` row): which seed ships (make release). ConfigError naming the file when it
    holds no such method."""
    import csv

    path = Path(metrics_csv)
    if not path.is_file():
        return best(Path(runs) / f"{prefix}<best on val: {path} not written yet>")  # dry runs and planning
    with open(path, newline="") as f:
        means = {r["method"]: float(r[column]) for r in csv.DictReader(f)
                 if r["method"].startswith(prefix) and r.get("sequence") == "mean" and r.get(column)}
    if not means:
        raise ConfigError(f"{path}: no method named {prefix}... with a mean {column} (the val stage's evaluation)")
    return best(Path(runs) / max(sorted(means), key=means.get))


@dataclass
class Job:
    """One command line of a stage. ``variables``: its matrix values (``name`` included)."""

    name: str
    variables: dict[str, str]
    args: list[str]
    run_dir: str | None = None
    ckpt: str | None = None
    extra: list[str] = field(default_factory=list)

    def checkpoint(self) -> str | None:
        """The checkpoint this job leaves, looked up now: ``ckpt`` as given, else :func:`best` of its
        run directory. A job is planned before its run trains; its ``best.ckpt`` exists only after."""
        return self.ckpt or (best(self.run_dir) if self.run_dir else None)


_FIELD = re.compile(r"\{(\w+)\}")


def fill(template: str, variables: Mapping[str, str]) -> str:
    """``template`` with ``{variable}`` replaced by its value; braces around anything else (a
    ``ckpt={a: b}`` mapping, ``${...}``) are left as they are."""
    return _FIELD.sub(lambda m: str(variables[m.group(1)]) if m.group(1) in variables else m.group(0), template)


def flat(args) -> list:
    """A stage's ``args`` with any list among them (``${axes}``: a list key) spread in place."""
    out = []
    for a in args or []:
        out.extend(a if isinstance(a, (list, tuple)) else [a])
    return out


def check_stage(name: str, stage: Mapping) -> None:
    """ConfigError naming the stage for an unknown key or a stage with nothing to run."""
    unknown = sorted(set(stage) - STAGE_KEYS)
    if unknown:
        raise ConfigError(f"stages.{name}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(STAGE_KEYS))})")
    if sum(bool(stage.get(k)) for k in ("command", "module", "script", "copy")) != 1:
        raise ConfigError(f"stages.{name}: give exactly one of command, module, script or copy")
    if stage.get("on_collapse", "stop") not in ("stop", "warn"):
        raise ConfigError(f"stages.{name}.on_collapse: {stage['on_collapse']!r} (stop or warn)")


def expand(name: str, stage: Mapping) -> list[Job]:
    """The jobs of a resolved stage (a plain mapping, see the module's docstring), in order."""
    matrix = stage.get("matrix") or {}
    keys = list(matrix)
    choices = []
    for key in keys:
        values = matrix[key]
        if isinstance(values, Mapping):
            choices.append([(str(v), list(extra or [])) for v, extra in values.items()])
        elif isinstance(values, (list, tuple)):
            choices.append([(str(v), []) for v in values])
        else:
            choices.append([(str(values), [])])
    args = [a for a in flat(stage.get("args")) if a not in (None, "")]
    jobs = []
    for combo in itertools.product(*choices):
        variables = {key: value for key, (value, _) in zip(keys, combo)}
        variables["name"] = fill(str(stage.get("name") or name), variables)
        extra = [fill(str(a), variables) for _, more in combo for a in more]
        jobs.append(_job(stage, variables, [fill(str(a), variables) for a in args] + extra))
    if stage.get("jobs_from"):
        jobs = [] if not stage.get("matrix") else jobs
        for more in _instantiate(stage["jobs_from"]):
            variables = {**{k: str(v) for k, v in (more.get("variables") or {}).items()}, "name": str(more["name"])}
            jobs.append(_job(stage, variables, [fill(str(a), variables) for a in args]
                             + [str(a) for a in more.get("args") or []], more.get("run_dir"), more.get("ckpt")))
    return jobs


def _job(stage: Mapping, variables: dict[str, str], args: list[str], run_dir=None, ckpt=None) -> Job:
    """A job of ``stage``: its run directory and checkpoint as given, else from the stage's
    templates (a training run's: none here, :meth:`Job.checkpoint` looks it up when it is chosen)."""
    if run_dir is None and stage.get("run_dir"):
        run_dir = fill(str(stage["run_dir"]), variables)
    if ckpt is None and stage.get("ckpt"):
        ckpt = fill(str(stage["ckpt"]), variables)
    return Job(variables["name"], variables, args, str(run_dir) if run_dir else None, str(ckpt) if ckpt else None)


def _instantiate(spec: Mapping):
    from hydra.utils import instantiate

    return list(instantiate(dict(spec)) or [])


def expand_needs(needs) -> list[tuple[str, str]]:
    """``[(path, what)]`` of a pipeline's ``needs``: a list of ``{path, what, matrix}`` (``{variable}``
    in ``path`` and ``what`` filled for every combination of ``matrix``, as a stage's)."""
    out = []
    for need in needs or []:
        for job in expand("need", {"matrix": need.get("matrix"), "args": [need["path"], need.get("what", "")]}):
            out.append((job.args[0], job.args[1]))
    return out


def choose_checkpoints(selection: Mapping, stages: Mapping[str, list[Job]]) -> dict[str, str]:
    """``{job name: checkpoint}`` of the jobs of ``selection['stages']`` (in that order) whose
    variables match ``selection.get('where')``; ``stages``: every stage's jobs, by stage name."""
    where = {k: [str(x) for x in v] if isinstance(v, (list, tuple)) else [str(v)]
             for k, v in (selection.get("where") or {}).items()}
    chosen: dict[str, str] = {}
    for stage_name in selection.get("stages") or []:
        if stage_name not in stages:
            raise ConfigError(f"checkpoints.stages: {stage_name!r} is not a stage of this pipeline "
                              f"(stages: {', '.join(stages)})")
        for job in stages[stage_name]:
            ckpt = job.checkpoint()
            if ckpt and all(k not in job.variables or job.variables[k] in v for k, v in where.items()):
                chosen[job.name] = ckpt
    return chosen


def ckpt_override(chosen: Mapping[str, str]) -> str:
    """``ckpt={name: path, ...}``, the checkpoint mapping every evaluating command takes."""
    return "ckpt={" + ", ".join(f"{name}: {path}" for name, path in chosen.items()) + "}"
