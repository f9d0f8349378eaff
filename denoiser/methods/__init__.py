"""Methods: what evaluation and the benchmark compare, behind one per-frame interface.

* :mod:`~denoiser.methods.baselines`: the method interface and the baselines (noisy input,
  Intel Open Image Denoise, a trained network stepped through the runner), built from
  ``conf/baselines``;
* :mod:`~denoiser.methods.onnd`: ONND, online neural denoising with cross-regression (trained
  on the fly, per sequence).

Imports the root vocabulary, :mod:`denoiser.nn` and :mod:`denoiser.inference` only. Imported
by :mod:`denoiser.report` and the commands (never by ``nn``, ``inference``, ``lit`` or ``data``).
"""
