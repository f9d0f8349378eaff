"""Real-time Monte Carlo denoising with render-aware knowledge distillation.

Layout: the package root holds the shared vocabulary (at most thirteen modules, one job each,
each imported from anywhere, importing only each other and :mod:`denoiser.conf`):
:mod:`~denoiser.buffers`, :mod:`~denoiser.nonfinite`, :mod:`~denoiser.errors`,
:mod:`~denoiser.atomic`, :mod:`~denoiser.configs`, :mod:`~denoiser.checkpoint`,
:mod:`~denoiser.release`, :mod:`~denoiser.recurrent`, :mod:`~denoiser.frames`,
:mod:`~denoiser.metrics`, :mod:`~denoiser.measure`, :mod:`~denoiser.machine`,
:mod:`~denoiser.tables`. Everything else
lives in a wing, and a wing imports only the wings named after it (docs/architecture.md;
checked by tests/core/test_house.py):

* ``nn/``         the networks in plain PyTorch                   -> root
* ``data/``       EXR I/O, layouts, datasets, the data module       -> root
* ``render/``     the Mitsuba scene simulator                       -> root, data
* ``inference/``  backends, ONNX step graph, CUDA/Triton, OpenVINO  -> root, nn
* ``methods/``    the compared methods (OIDN, networks, ONND)       -> root, nn, inference
* ``report/``     evaluation, summaries, statistics, plots          -> root, nn, inference, methods, data
* ``lit/``        Lightning training modules, losses, transfer      -> root, nn, data
* ``commands/``   one module per console script                     -> everything; nothing imports it
* ``conf/``       the Hydra configs (YAML), shipped in the package

In a source checkout the configs (``conf/``, beside the package) import as ``denoiser.conf``:
:mod:`denoiser._conf_mount`, called below. A checkpoint of an earlier layout that names a class by
an old module path loads through :data:`denoiser.checkpoint.OLD_TARGETS`.

Conventions (stated once, used everywhere):

* Tensors are float32 ``[B, T, C, H, W]`` (per-sample radiance ``[B, T, S, 3, H, W]``),
  pixel coordinates are ``(x, y)`` with x to the right and y downward.
* Radiance is linear HDR and never clamped on load; NaN/Inf are replaced at the reader.
* Motion is *backward* motion in pixels: the surface seen at pixel centre ``p`` in frame
  ``t`` was at ``p + motion`` in frame ``t-1``.
* Normals are camera space, unit length: x right, y up, z into the scene; no hit = 0.
* Depth is planar depth along the viewing axis; no hit = +inf or a very large value.
"""

__version__ = "0.1.0"

from denoiser import _conf_mount

_conf_mount.mount()
