"""The pipelines as code: ``denoiser-pipeline pipeline=<name>`` runs ``conf/pipeline/<name>.yaml``.

- :mod:`denoiser.pipeline.stages`: a stage as data (its jobs, their command lines, checkpoints);
- :mod:`denoiser.pipeline.runner`: the stages in order, jobs side by side, skip and resume;
- :mod:`denoiser.pipeline.timings`: the stage-time table (reused work keeps its run's seconds).

Importing the package registers the OmegaConf resolvers of the pipeline configs: ``${best:<run
dir>}`` (the checkpoint a training run is evaluated with), ``${best_on_val:<metrics.csv>,<runs>,<prefix>}``
(that of the run whose method is best on a val evaluation), ``${opt:key,${value}}`` (``key=value``,
or no argument when the value is null), ``${concat:[a],${list}}``, ``${given:[keys],${hydra:overrides.task}}``
(the pipeline's own overrides of those keys, passed on), ``${eq:a,b}`` and ``${unless:${flag},arg}``
(:mod:`denoiser.pipeline.stages`).
"""

from __future__ import annotations

from omegaconf import OmegaConf

from denoiser.pipeline.stages import best, best_on_val, concat, equal, given, optional, unless

OmegaConf.register_new_resolver("best", best, replace=True)
OmegaConf.register_new_resolver("best_on_val", best_on_val, replace=True)
OmegaConf.register_new_resolver("opt", optional, replace=True)
OmegaConf.register_new_resolver("concat", concat, replace=True)
OmegaConf.register_new_resolver("given", given, replace=True)
OmegaConf.register_new_resolver("unless", unless, replace=True)
OmegaConf.register_new_resolver("eq", equal, replace=True)
