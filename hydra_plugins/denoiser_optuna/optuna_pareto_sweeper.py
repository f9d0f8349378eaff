"""A Hydra sweeper around Optuna's own multi-objective search (``hydra/sweeper=optuna_pareto``).

Why not ``hydra-optuna-sweeper``: its releases (1.2.0, 1.3.0) pin ``optuna<3``, whose storage
does not work with SQLAlchemy 2 (what the current Optuna and this stack install). This plugin
is a thin loop around the current Optuna API; the search itself is Optuna's sampler (NSGA-II
by default, or TPE): ``study.ask()`` -> overrides -> the Hydra launcher runs the jobs ->
``study.tell(trial, values)``, where ``values`` is what the task function returns (for
denoiser-train with ``objectives.time`` set: ``[val/psnr, ms per frame]``).

The study lives in ``<sweep dir>/optuna.db`` (SQLite). A rerun of the same command loads it:
trials still RUNNING (the sweep was killed during them) are marked FAIL, completed ones are
kept, and trials are asked until ``n_trials`` are complete. Job directories are named by trial
number (``hydra.job.num``), so a resumed sweep never reuses one.

Search space (``params``, and sweep overrides on the command line, which win): Hydra's sweep
syntax, ``choice(a,b)`` / ``a,b`` (categorical; any values, lists included),
``range(1,4)`` (integers), ``interval(0.1,1)`` (float; ``tag(log, interval(...))`` for a log scale).
"""

from __future__ import annotations

import logging
import math
import sys
from pathlib import Path
from typing import Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.plugins.sweeper import Sweeper

log = logging.getLogger(__name__)


def _distribution(override):
    """``(kind, payload)`` of one sweep override: ``("cat", [value strings])``, ``("int", (lo, hi,
    step))`` or ``("float", (lo, hi, log))``."""
    from hydra.core.override_parser.types import Override

    if override.is_choice_sweep():
        return "cat", [Override._get_value_element_as_str(v) for v in override.value().list]
    if override.is_range_sweep():
        r = override.value()
        values = list(override.sweep_iterator())
        if all(isinstance(v, int) for v in values):
            return "int", (int(r.start), int(values[-1]), int(r.step))
        return "cat", [Override._get_value_element_as_str(v) for v in values]
    if override.is_interval_sweep():
        iv = override.value()
        log_scale = "log" in (iv.tags or set())
        if isinstance(iv.start, int) and isinstance(iv.end, int):
            return "int", (iv.start, iv.end, 1)
        return "float", (float(iv.start), float(iv.end), log_scale)
    raise ValueError(f"{override.input_line}: not a sweep")


def _suggest(trial, name: str, dist) -> str:
    kind, payload = dist
    if kind == "cat":
        return payload[trial.suggest_categorical(name, list(range(len(payload))))] if len(payload) > 1 else payload[0]
    if kind == "int":
        lo, hi, step = payload
        return str(trial.suggest_int(name, lo, hi, step=step))
    lo, hi, log_scale = payload
    return repr(trial.suggest_float(name, lo, hi, log=log_scale))


class OptunaParetoSweeper(Sweeper):
    def __init__(self, directions=("maximize", "minimize"), n_trials: int = 20, n_jobs: int = 1,
                 sampler: str = "nsga2", population_size: int = 8, seed: int = 0, study_name: str = "pareto",
                 storage=None, max_failures: int = 10, params=None):
        self.directions = [str(d) for d in directions]
        self.n_trials, self.n_jobs = int(n_trials), max(1, int(n_jobs))
        self.sampler_name, self.population_size, self.seed = str(sampler), int(population_size), int(seed)
        self.study_name, self.storage, self.max_failures = str(study_name), storage, int(max_failures)
        self.params = {str(k): str(v) for k, v in (params or {}).items()}

    def setup(self, *, hydra_context, task_function, config) -> None:
        from hydra.core.plugins import Plugins

        self.config = config
        self.hydra_context = hydra_context
        self.launcher = Plugins.instance().instantiate_launcher(hydra_context=hydra_context,
                                                                task_function=task_function, config=config)
        self.sweep_dir = Path(config.hydra.sweep.dir)

    def _sampler(self):
        import optuna

        if self.sampler_name == "nsga2":
            return optuna.samplers.NSGAIISampler(population_size=self.population_size, seed=self.seed)
        if self.sampler_name == "tpe":
            return optuna.samplers.TPESampler(seed=self.seed)
        if self.sampler_name == "random":
            return optuna.samplers.RandomSampler(seed=self.seed)
        raise ValueError(f"hydra.sweeper.sampler: {self.sampler_name!r} is not nsga2, tpe or random")

    def study(self):
        """Create the study or load it (a resumed sweep); trials left RUNNING by a killed sweep become FAIL."""
        import optuna
        from optuna.trial import TrialState

        self.sweep_dir.mkdir(parents=True, exist_ok=True)
        storage = self.storage or f"sqlite:///{(self.sweep_dir / 'optuna.db').resolve()}"
        study = optuna.create_study(study_name=self.study_name, storage=storage, directions=self.directions,
                                    sampler=self._sampler(), load_if_exists=True)
        for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
            print(f"optuna_pareto: trial {t.number} was interrupted (left RUNNING by a killed sweep): marked FAIL",
                  file=sys.stderr)
            study._storage.set_trial_state_values(t._trial_id, state=TrialState.FAIL)
        return study

    def sweep(self, arguments: list[str]) -> list:
        from optuna.trial import TrialState

        parser = OverridesParser.create()
        space: dict[str, Any] = {}
        fixed: list[str] = []
        for line in [f"{k}={v}" for k, v in self.params.items()] + list(arguments):  # command line wins
            override = parser.parse_overrides([line])[0]
            key = override.get_key_element()
            space.pop(key, None)
            fixed = [f for f in fixed if parser.parse_overrides([f])[0].get_key_element() != key]
            if override.is_sweep_override():
                space[key] = _distribution(override)
            else:
                fixed.append(line)
        study = self.study()
        done = lambda: len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))
        failures, returns = 0, []
        log.info("optuna_pareto: study %s in %s, %d/%d trials complete", self.study_name, self.sweep_dir, done(),
                 self.n_trials)
        while done() < self.n_trials:
            trials = [study.ask() for _ in range(min(self.n_jobs, self.n_trials - done()))]
            batch = [tuple(fixed + [f"{k}={_suggest(t, k, d)}" for k, d in space.items()]) for t in trials]
            results = self.launcher.launch(batch, initial_job_idx=trials[0].number)
            for trial, overrides, result in zip(trials, batch, results):
                try:
                    values = result.return_value  # raises the job's exception when it failed
                    values = [float(v) for v in (values if isinstance(values, (list, tuple)) else [values])]
                    if len(values) != len(self.directions) or any(math.isnan(v) for v in values):
                        raise ValueError(f"the task returned {values}, not {len(self.directions)} numbers")
                    trial.set_user_attr("overrides", list(overrides))
                    study.tell(trial, values)
                except Exception as exc:  # noqa: BLE001 - a failed trial is recorded, the sweep goes on
                    log.warning("trial %d failed: %s", trial.number, exc)
                    study.tell(trial, state=TrialState.FAIL)
                    failures += 1
            returns.append(results)
            if failures >= self.max_failures:
                log.error("optuna_pareto: %d failed trials, stopping", failures)
                break
        self._write_results(study)
        return returns

    def _write_results(self, study) -> None:
        from omegaconf import OmegaConf

        front = [{"number": t.number, "values": list(t.values), "overrides": t.user_attrs.get("overrides", [])}
                 for t in study.best_trials]
        OmegaConf.save(OmegaConf.create({"directions": self.directions, "n_complete": len(
            [t for t in study.trials if t.state.name == "COMPLETE"]), "pareto_front": front}),
            self.sweep_dir / "optimization_results.yaml")
