"""Side-by-side tonemapped crops of several methods on one frame (PNG, via matplotlib).

One row of panels, in the given order (e.g. noisy | OIDN | teacher | student | reference),
each titled with the method's label and, when given, a number (e.g. the frame's PSNR).
Pixels are shown 1:1 (nearest neighbour), tonemapped with :func:`denoiser.metrics.tonemap`.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np
import torch

from denoiser.atomic import atomic_save_figure
from denoiser.metrics import tonemap


def crop_box(height: int, width: int, size: int, center: Sequence[int] | None = None) -> tuple[int, int, int, int]:
    """``(top, left, h, w)`` of a ``size`` x ``size`` crop (clipped to the frame) around ``center`` ``(y, x)``."""
    h, w = min(size, height), min(size, width)
    cy, cx = (height // 2, width // 2) if center is None else (int(center[0]), int(center[1]))
    top = int(np.clip(cy - h // 2, 0, height - h))
    left = int(np.clip(cx - w // 2, 0, width - w))
    return top, left, h, w


def to_display(image: torch.Tensor, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """``[1, 3, H, W]`` or ``[3, H, W]`` linear HDR -> tonemapped ``[h, w, 3]`` float array in [0, 1]."""
    if image.ndim == 4:
        image = image[0]
    if box is not None:
        top, left, h, w = box
        image = image[:, top:top + h, left:left + w]
    return tonemap(image.detach().float().cpu()).permute(1, 2, 0).numpy()


def save_crops(path: str | os.PathLike, panels: Mapping[str, np.ndarray], notes: Mapping[str, str] | None = None,
               title: str | None = None, scale: float = 2.0) -> Path:
    """Write a PNG with one titled panel per entry of ``panels`` (``label -> [h, w, 3]`` in [0, 1]).

    ``notes``: optional second title line per label; ``scale``: screen pixels per image pixel.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    labels = list(panels)
    h, w = next(iter(panels.values())).shape[:2]
    dpi = 100
    panel_w = max(w * scale / dpi, 1.2)
    panel_h = h * scale / dpi
    fig, axes = plt.subplots(1, len(labels), figsize=(panel_w * len(labels), panel_h + 0.6 + (0.3 if title else 0)),
                             dpi=dpi, squeeze=False)
    for ax, label in zip(axes[0], labels):
        ax.imshow(np.clip(panels[label], 0, 1), interpolation="nearest")
        text = label if not notes or label not in notes else f"{label}\n{notes[label]}"
        ax.set_title(text, fontsize=8)
        ax.set_xticks([])
        ax.set_yticks([])
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    return atomic_save_figure(fig, path)
