"""Real-time Monte Carlo denoising with render-aware knowledge distillation.

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

from denoiser import _aliases

_aliases.install()
