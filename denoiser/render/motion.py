"""Backward motion vectors from geometry (not optical flow).

docs/design.md §3.1: the surface seen at pixel centre ``p`` in frame ``t`` was at ``p + motion`` in
frame ``t-1``; x right, y down, in pixels. For a pixel that sees point ``P`` of object ``k``
at time ``t``, its position at ``t-1`` is ``M_k(t-1) M_k(t)^-1 P`` (static objects: ``P``),
projected with the camera of ``t-1``. Pixels that see nothing (environment at infinity) move
with the camera rotation only. Points behind the previous camera get motion 0.
A static scene (no camera or object motion) gets exact zeros without any computation.
"""

from __future__ import annotations

import numpy as np

from denoiser.render import transforms as tf
from denoiser.render.passes import AuxBuffers
from denoiser.render.spec import SceneSpec


def backward_motion(spec: SceneSpec, aux: AuxBuffers, t: int, width: int, height: int) -> np.ndarray:
    """Motion ``[H, W, 2]`` float32 of frame ``t`` relative to frame ``t - 1``."""
    if spec.is_static:
        return np.zeros((height, width, 2), np.float32)
    prev_pos = aux.position.copy()
    for k in spec.moving_objects:
        mask = aux.object == k
        if mask.any():
            obj = spec.objects[k]
            m = obj.to_world(t - 1.0) @ np.linalg.inv(obj.to_world(float(t)))
            prev_pos[mask] = tf.apply(m, aux.position[mask])
    cam_prev = spec.camera.to_world(t - 1.0)
    fov = spec.camera.fov
    uv, z = tf.project(cam_prev, fov, width, height, prev_pos)
    if spec.camera.moves:
        dirs = tf.pixel_rays(spec.camera.to_world(float(t)), fov, width, height)
        uv_inf, z_inf = tf.project(cam_prev, fov, width, height, dirs, directions=True)
        uv = np.where(aux.hit[..., None], uv, uv_inf)
        z = np.where(aux.hit, z, z_inf)
    else:
        centres = _centres(width, height)
        uv = np.where(aux.hit[..., None], uv, centres)
        z = np.where(aux.hit, z, 1.0)
    motion = uv - _centres(width, height)
    motion = np.where((z > 1e-6)[..., None] & np.isfinite(motion), motion, 0.0)
    return motion.astype(np.float32)


def _centres(width: int, height: int) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([xs, ys], axis=-1)
