"""1x1 adapters for feature distillation: student feature maps -> teacher feature widths.

Student and teacher return ``extras["features"]`` (one U-Net map per level, finest first).
Level ``i`` of the student (``[B, c_s, h, w]``) is mapped by a 1x1 convolution to the
teacher's width ``c_t`` of the same level; levels whose spatial sizes differ are not paired.
"""

from __future__ import annotations

import torch
from torch import nn

from denoiser.frames import random_frame


@torch.no_grad()
def feature_shapes(net: nn.Module, size: int = 32) -> list[tuple[int, int, int]]:
    """``(channels, height, width)`` of each map in ``net.step(...)[2]["features"]`` on a probe frame."""
    was_training = net.training
    net.eval()
    _, _, extras = net.step(random_frame(1, size, size, kind="probe"), None)
    net.train(was_training)
    return [tuple(int(v) for v in f.shape[1:]) for f in extras["features"]]


class FeatureAdapters(nn.Module):
    """One 1x1 conv per paired level. ``pairs``: list of ``(level, c_student, c_teacher)``.

    ``forward(student_features) -> list`` of adapted maps ``[B, c_teacher, h, w]`` for the
    paired levels, in the order of ``pairs``.
    """

    def __init__(self, pairs: list[tuple[int, int, int]]):
        super().__init__()
        self.levels = [p[0] for p in pairs]
        self.convs = nn.ModuleList([nn.Conv2d(cs, ct, 1) for _, cs, ct in pairs])

    @classmethod
    def between(cls, student: nn.Module, teacher: nn.Module, size: int = 32) -> FeatureAdapters:
        """Adapters for every level where the student's and teacher's maps have the same spatial size."""
        s_shapes, t_shapes = feature_shapes(student, size), feature_shapes(teacher, size)
        pairs = [(i, s[0], t[0]) for i, (s, t) in enumerate(zip(s_shapes, t_shapes)) if s[1:] == t[1:]]
        return cls(pairs)

    def forward(self, student_features: list[torch.Tensor]) -> list[torch.Tensor]:
        return [conv(student_features[i]) for i, conv in zip(self.levels, self.convs)]
