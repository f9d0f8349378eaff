"""Motion vectors: warping frame t-1's reference by frame t's motion reproduces frame t.

The warp here is written independently of the simulator: bilinear lookup of frame t-1 at
``p + motion(p)`` (pixel centres at +0.5). Pixels count as visible in both frames when the
lookup stays inside the image and its four source pixels lie on one surface in frame t-1
(depth within 5 % and albedo within 0.02 of each other), which excludes disocclusions and
silhouettes where a bilinear warp cannot be right. Buffers are read back from the EXR files.
"""

from __future__ import annotations

import numpy as np
import pytest

from denoiser.commands.tools.effect_cost import bench_scene
from denoiser.data.exr import read_frame
from denoiser.render.job import RenderSettings, frame_path, render_sequence
from denoiser.render.passes import NO_HIT_DEPTH
from denoiser.render.spec import build_scene

CHANNELS = {"reference": ("reference.R", "reference.G", "reference.B"), "albedo": ("albedo.R", "albedo.G", "albedo.B"),
            "depth": ("depth.Z",), "motion": ("motion.X", "motion.Y")}
SIZE = 40


def bilinear_warp(img: np.ndarray, motion: np.ndarray):
    """Sample ``img [H,W,C]`` at ``p + motion``; returns (warped, inside mask, the 4 source pixel indices)."""
    h, w = img.shape[:2]
    xs, ys = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    x = xs + motion[..., 0] - 0.5
    y = ys + motion[..., 1] - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    inside = (x0 >= 0) & (y0 >= 0) & (x0 + 1 < w) & (y0 + 1 < h)
    x0, y0 = np.clip(x0, 0, w - 2), np.clip(y0, 0, h - 2)
    out = (img[y0, x0] * (1 - fx) * (1 - fy) + img[y0, x0 + 1] * fx * (1 - fy)
           + img[y0 + 1, x0] * (1 - fx) * fy + img[y0 + 1, x0 + 1] * fx * fy)
    return out, inside, (y0, x0)


def same_surface(buf: np.ndarray, idx, tol, relative: bool) -> np.ndarray:
    y0, x0 = idx
    nb = np.stack([buf[y0, x0], buf[y0, x0 + 1], buf[y0 + 1, x0], buf[y0 + 1, x0 + 1]])
    spread = (nb.max(0) - nb.min(0)).max(-1)
    return spread < (tol * nb.min(0).min(-1) if relative else tol)


def psnr(a, b, mask) -> float:
    def tm(x):
        return np.maximum(x, 0) / (1 + np.maximum(x, 0))

    mse = float(np.mean(((tm(a) - tm(b)) ** 2)[mask]))
    return 10 * np.log10(1 / mse)


def render(tmp_path, effects, edit):
    from denoiser.render.variant import activate

    mi = activate("auto", quiet=True)
    cfg = bench_scene(effects)
    edit(cfg)
    render_sequence(mi, build_scene(cfg, 0), tmp_path, RenderSettings(2, 2, 128, SIZE, SIZE), seq_seed=3)
    return [read_frame(frame_path(tmp_path, t), CHANNELS)[0] for t in range(2)]


def check_warp(prev, cur):
    warped, inside, idx = bilinear_warp(prev["reference"], cur["motion"])
    mask = inside & (cur["depth"][..., 0] < NO_HIT_DEPTH)
    mask &= same_surface(prev["depth"], idx, 0.05, relative=True)
    mask &= same_surface(prev["albedo"], idx, 0.02, relative=False)
    assert mask.mean() > 0.3, "too few pixels visible in both frames to judge"
    flipped, _, _ = bilinear_warp(prev["reference"], -cur["motion"])
    return psnr(warped, cur["reference"], mask), psnr(prev["reference"], cur["reference"], mask), \
        psnr(flipped, cur["reference"], mask)


@pytest.mark.slow
def test_camera_motion_vectors_warp_previous_reference(tmp_path):
    frames = render(tmp_path, ["area_light", "textures", "camera_motion"],
                    lambda c: c["camera"].update(orbit=4.0, dolly=[0.0, 0.02, -0.05]))
    assert np.abs(frames[1]["motion"]).max() > 2  # the camera really moved several pixels
    warped, unwarped, flipped = check_warp(*frames)
    assert warped >= 30
    assert warped > unwarped + 3 and warped > flipped + 3


@pytest.mark.slow
def test_object_motion_vectors_warp_previous_reference(tmp_path):
    def edit(c):
        c["objects"][1].update(velocity=[0.12, 0.05, 0.0], spin={"axis": [0, 1, 0], "degrees": 20})
        c["objects"][2].update(velocity=[-0.08, 0.0, 0.1], material={
            "type": "diffuse", "color": {"texture": "stripes", "tiles": 4}})

    frames = render(tmp_path, ["area_light", "textures", "object_motion"], edit)
    moving = np.abs(frames[1]["motion"]).max(-1) > 0.5
    assert 0.02 < moving.mean() < 0.5  # only the objects move; the room is still
    warped, unwarped, flipped = check_warp(*frames)
    assert warped >= 30
    assert warped > unwarped + 3 and warped > flipped + 3
