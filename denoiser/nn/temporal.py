"""Temporal recurrence: the history state, its warping, and the predicted blend weights.

State (all ``[B, C, H, W]`` float32 at the frame's size, linear where radiance):

* ``"output"``   ``[B, 3, H, W]`` previous denoised output (linear HDR);
* ``"color"``    ``[B, 3, H, W]`` accumulated input color (the blended filter input, linear);
* ``"features"`` ``[B, F, H, W]`` accumulated learned features (tanh of a head, in [-1, 1]);
* ``"guide"``    ``[B, 7, H, W]`` previous guide features (albedo, normal, depth feature), so
  the network can compare warped and current geometry and reject stale history.

Per step: the state is warped to the current frame (:func:`warp_to_current`, together with a
constant-1 channel giving the coverage ``c`` in [0, 1]: the fraction of the bilinear footprint
inside the image). Warped values are divided by ``c`` (where ``c > COVER_MIN``, else 0) so they
are convex combinations of previous pixels, and ``valid = c`` (0 where the history was reset).
The network sees, next to the current frame, ``log1p(history output / s)``,
``log1p(history color / s)`` (``s`` the current color scale), the warped guide and features and
``valid``. Its level-0 head predicts two logits and the next features:

    a = sigmoid(h_in)  * valid;  filter input = color    + a * (history color  - color)
    b = sigmoid(h_out) * valid;  output       = filtered + b * (history output - filtered)

Both blends are convex, so the output stays within [min, max] of the input and warped history.
A reset (first frame, camera cut) sets ``valid = 0`` and replaces history by zeros, so the
result cannot depend on the previous sequence.
"""

from __future__ import annotations

import torch
from torch import nn

from denoiser.nn.inputs import GUIDE_CHANNELS, color_feature
from denoiser.nn.warp import warp_to_current

#: minimum bilinear coverage for a warped history value to count
COVER_MIN = 1e-4

STATE_KEYS = ("output", "color", "features", "guide")


class TemporalRecurrence(nn.Module):
    """History handling for :class:`~denoiser.nn.denoiser.Denoiser` (no parameters of its own).

    Args:
        state_features: channels F of the learned recurrent features.
    """

    def __init__(self, state_features: int = 8):
        super().__init__()
        self.state_features = int(state_features)
        #: channels added to the U-Net input, in order: ``(part, channels)`` (see :meth:`inputs`)
        self.input_layout = (("output", 3), ("color", 3), ("guide", GUIDE_CHANNELS),
                             ("features", self.state_features), ("valid", 1))
        self.input_channels = sum(n for _, n in self.input_layout)
        #: channels the level-0 head must predict, in order: ``(part, channels)``; the blend
        #: logits h_in, h_out, then the next state features
        self.head_layout = (("history_in", 1), ("history_out", 1), ("features", self.state_features))
        self.head_channels = sum(n for _, n in self.head_layout)
        starts = [sum(n for _, n in self.head_layout[:i]) for i in range(len(self.head_layout))]
        self._head = {part: slice(s, s + n) for (part, n), s in zip(self.head_layout, starts)}

    def state_channels(self) -> dict[str, int]:
        return {"output": 3, "color": 3, "features": self.state_features, "guide": GUIDE_CHANNELS}

    def zero_state(self, like: torch.Tensor) -> dict[str, torch.Tensor]:
        """All-zero state shaped like ``like`` ``[B, *, H, W]``."""
        b, _, h, w = like.shape
        return {k: like.new_zeros(b, c, h, w, dtype=torch.float32)
                for k, c in self.state_channels().items()}

    def warp(self, state: dict | None, motion: torch.Tensor, reset: torch.Tensor | None,
             like: torch.Tensor) -> dict[str, torch.Tensor]:
        """Warp the state to the current frame.

        state: dict of ``STATE_KEYS`` tensors ``[B, C, H, W]`` or None/empty (= reset all);
        motion: ``[B, 2, H, W]``; reset: bool ``[B]`` or None; like: ``[B, 3, H, W]`` current color.
        Returns the warped, coverage-normalised history (same keys) plus ``"valid" [B, 1, H, W]``.
        """
        b = like.shape[0]
        if not state:
            state = self.zero_state(like)
            keep = torch.zeros(b, dtype=torch.bool, device=like.device)
        elif reset is None:
            keep = torch.ones(b, dtype=torch.bool, device=like.device)
        else:
            keep = ~reset.to(device=like.device, dtype=torch.bool).reshape(b)
        keep = keep.view(b, 1, 1, 1)
        stacked = torch.cat([state[k].float() for k in STATE_KEYS] + [torch.ones_like(like[:, :1])], 1)
        # discarded history must not leak, not even as NaN through 0 * x
        stacked = torch.where(keep, stacked, 0.0)
        warped = warp_to_current(stacked, motion)
        cover = warped[:, -1:]
        ok = cover > COVER_MIN
        values = torch.where(ok, warped[:, :-1] / cover.clamp_min(COVER_MIN), 0.0)
        history = dict(zip(STATE_KEYS, torch.split(values, list(self.state_channels().values()), dim=1)))
        history["valid"] = torch.where(ok, cover, 0.0)
        return history

    def inputs(self, history: dict[str, torch.Tensor], scale: torch.Tensor) -> torch.Tensor:
        """Network inputs from the warped history: ``[B, input_channels, H, W]`` float32.

        scale: ``[B, 1, 1, 1]`` current color scale.
        """
        parts = {"output": color_feature(history["output"], scale), "color": color_feature(history["color"], scale),
                 "guide": history["guide"], "features": history["features"], "valid": history["valid"]}
        return torch.cat([parts[part] for part, _ in self.input_layout], dim=1)

    def blend_in(self, color: torch.Tensor, history: dict[str, torch.Tensor], head: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor]:
        """Blend history color into the input: color ``[B, 3, H, W]``, head ``[B, head_channels, H, W]``.

        Returns ``(filter input [B, 3, H, W], weight a [B, 1, H, W])``.
        """
        a = torch.sigmoid(head[:, self._head["history_in"]].float()) * history["valid"]
        return color + a * (history["color"] - color), a

    def blend_out(self, filtered: torch.Tensor, history: dict[str, torch.Tensor], head: torch.Tensor
                  ) -> tuple[torch.Tensor, torch.Tensor]:
        """Blend the history output into the filtered frame; returns ``(output, weight b)``."""
        b = torch.sigmoid(head[:, self._head["history_out"]].float()) * history["valid"]
        return filtered + b * (history["output"] - filtered), b

    def next_state(self, output: torch.Tensor, color: torch.Tensor, head: torch.Tensor,
                   guide: torch.Tensor) -> dict[str, torch.Tensor]:
        """State for the next step (tensors ``[B, C, H, W]``, see module docstring)."""
        features = torch.tanh(head[:, self._head["features"]].float())
        return {"output": output, "color": color, "features": features, "guide": guide}
