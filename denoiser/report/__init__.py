"""Report: measuring methods on labeled sequences and writing what the measurements say.

* :mod:`~denoiser.report.evaluation`: every method over the same frames, metrics per sequence;
* :mod:`~denoiser.report.seed_groups`, :mod:`~denoiser.report.stats`: seed groups, mean ± std over
  training seeds, paired bootstrap intervals and the claims they support;
* :mod:`~denoiser.report.provenance`: what a report names as its code and data (the commit, the
  split's hash);
* :mod:`~denoiser.report.figure_tables`: the declared figure tables of a summary;
* :mod:`~denoiser.report.pareto`: Pareto fronts of trained variants, and timing one network;
* :mod:`~denoiser.report.plot_crops`, :mod:`~denoiser.report.plot_tradeoff`: the figures
  (tonemapped crops, accuracy against time);
* :mod:`~denoiser.report.history_diagnosis`: where a recurrent denoiser's history goes wrong.

Imports the root vocabulary, :mod:`denoiser.nn`, :mod:`denoiser.inference`,
:mod:`denoiser.methods` and :mod:`denoiser.data`. Imported by the commands, scripts and the
Hydra plugins only (never by a library wing).
"""
