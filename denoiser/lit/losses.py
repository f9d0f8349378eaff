"""Training losses (docs/design.md §3.3), shared by supervised training and distillation.

Every loss is computed in float32 on *linear HDR* radiance unless stated otherwise, and
returns a per-item value ``[B]`` (mean over frames, channels and pixels) so callers can mask
items (e.g. unlabeled sequences have no reference) before averaging.

Formulas (``x`` = prediction, ``y`` = target, both ``[B, T, 3, H, W]``, ``EPS = 0.01``):

* SMAPE: ``|x - y| / (|x| + |y| + EPS)``, averaged over pixels, channels and frames.
* gradient: finite differences ``dx(z) = z[..., :, 1:] - z[..., :, :-1]`` and
  ``dy(z) = z[..., 1:, :] - z[..., :-1, :]`` of the log-compressed radiance
  ``g(z) = log1p(max(z, 0))``; the term is ``mean |dx(g(x)) - dx(g(y))| + mean |dy(g(x)) - dy(g(y))|``.
  The compression keeps the term scale-robust on HDR (edges of bright lights do not dominate).
* temporal: with ``W_t(z)`` = frame ``t-1`` of ``z`` warped to frame ``t`` by the backward
  motion of frame ``t`` (bilinear, zeros outside the image, see :func:`warp_previous`), the
  temporal differences are ``dx_t = x_t - W_t(x)`` and ``dy_t = y_t - W_t(y)``; the term is
  ``|dx_t - dy_t| / (|x_t| + |y_t| + EPS)`` averaged over pixels whose warp source lies inside
  the image, over frames ``t >= 1`` that are not a reset (first frame or camera cut).
  Normalizing by the frame magnitude (not by the differences) measures flicker relative to the
  image, the way a viewer sees it.

* hdr (off unless ``hdr_weight > 0``): L1 between tonemapped images after a per-image exposure,
  ``mean |T(x / e) - T(y / e)|`` with ``T(z) = max(z, 0) / (1 + max(z, 0))`` (Reinhard) and
  ``e = mean_{c,h,w}(max(y, 0)) + HDR_EPS`` per item and frame (``HDR_EPS = 1e-3``, from the
  target, no gradient). Each pixel contributes at most 1 and the gradient is at most ``1 / e``,
  so a 1e6 firefly neither dominates the loss nor blows up the gradient, while dark regions
  are weighed as a viewer sees them after exposure.

Adversarial terms (image level, used by distillation), ``D`` = critic, ``r`` = real, ``f`` = fake:

* WGAN-GP: critic ``mean D(f) - mean D(r) + lambda * mean (||grad D(m)||_2 - 1)^2`` on random
  interpolates ``m = a r + (1 - a) f`` (``a ~ U[0, 1]`` per item); generator ``-mean D(f)``.
* hinge: critic ``mean relu(1 - D(r)) + mean relu(1 + D(f))``; generator ``-mean D(f)``.

Feature distillation: ``mean |A(s) - t| / (mean |t| + 0.001)`` per paired level (``A`` a 1x1
adapter from student to teacher width), see :func:`feature_loss`.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.nn.warp import warp_all

#: Epsilon of the SMAPE denominator (docs/design.md §3.3).
SMAPE_EPS = 0.01
#: Floor of the per-image exposure of the hdr term.
HDR_EPS = 1e-3


def _per_item(x: torch.Tensor) -> torch.Tensor:
    """Mean over every dimension but the first: ``[B, ...] -> [B]``."""
    return x.reshape(x.shape[0], -1).mean(dim=1)


def smape(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """SMAPE per item: ``pred, target: [B, ...]`` linear HDR -> ``[B]``.

    ``|x - y| / (|x| + |y| + 0.01)`` computed in float32.
    """
    x, y = pred.float(), target.float()
    return _per_item((x - y).abs() / (x.abs() + y.abs() + SMAPE_EPS))


def log_compress(x: torch.Tensor) -> torch.Tensor:
    """``log1p(max(x, 0))`` in float32; any shape."""
    return torch.log1p(x.float().clamp_min(0.0))


def gradient_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L1 between spatial gradients of log-compressed images: ``[B, ..., H, W] -> [B]``.

    ``mean |dx(g(x)) - dx(g(y))| + mean |dy(g(x)) - dy(g(y))|`` with ``g = log1p(max(., 0))``.
    """
    gx, gy = log_compress(pred), log_compress(target)
    ddx = (gx[..., :, 1:] - gx[..., :, :-1]) - (gy[..., :, 1:] - gy[..., :, :-1])
    ddy = (gx[..., 1:, :] - gx[..., :-1, :]) - (gy[..., 1:, :] - gy[..., :-1, :])
    return _per_item(ddx.abs()) + _per_item(ddy.abs())


def hdr_loss(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L1 of Reinhard-tonemapped images after per-image exposure: ``[B, T, 3, H, W]`` (or
    ``[B, 3, H, W]``) -> ``[B]`` in [0, 1].

    ``mean |T(x / e) - T(y / e)|``, ``T(z) = max(z, 0) / (1 + max(z, 0))``,
    ``e = mean(max(y, 0)) + HDR_EPS`` over channels and pixels of each frame of the target (detached).
    """
    x, y = pred.float(), target.float()
    e = y.detach().clamp_min(0.0).mean(dim=(-3, -2, -1), keepdim=True) + HDR_EPS
    tx, ty = (x / e).clamp_min(0.0), (y / e).clamp_min(0.0)
    return _per_item((tx / (1.0 + tx) - ty / (1.0 + ty)).abs())


def warp_previous(prev: torch.Tensor, motion: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Warp frame ``t-1`` to frame ``t`` with the backward motion of frame ``t``.

    ``prev: [N, C, H, W]``, ``motion: [N, 2, H, W]`` in pixels (x right, y down): the surface
    seen at pixel centre ``p`` in frame ``t`` was at ``p + motion`` in frame ``t-1``, so
    ``out(p) = prev(p + motion(p))``, bilinear, zeros outside (the network's own
    :func:`denoiser.nn.warp.warp_to_current`). Returns ``(warped [N, C, H, W], valid [N, 1, H, W])``
    with ``valid`` 1.0 where the bilinear footprint lies entirely inside the image (a warped
    constant image of ones, :func:`~denoiser.nn.warp.coverage`, is >= 0.999 there), else 0.0.
    """
    (warped,), coverage = warp_all([prev], motion)
    return warped, (coverage >= 0.999).float()


def temporal_loss(
    pred: torch.Tensor, target: torch.Tensor, motion: torch.Tensor, reset: torch.Tensor | None = None
) -> torch.Tensor:
    """Relative error of warped temporal differences, per item.

    ``pred, target: [B, T, 3, H, W]`` linear HDR, ``motion: [B, T, 2, H, W]`` backward motion,
    ``reset: bool [B, T]`` (frames with ``reset`` have no valid predecessor).
    ``|(x_t - W_t(x)) - (y_t - W_t(y))| / (|x_t| + |y_t| + 0.01)`` over valid pixels of frames
    ``t >= 1``; returns ``[B]`` (0 for items with fewer than two consecutive frames).
    """
    b, t = pred.shape[:2]
    if t < 2:
        return pred.new_zeros(b, dtype=torch.float32)
    x, y = pred.float(), target.float()
    cur_x, cur_y = x[:, 1:].flatten(0, 1), y[:, 1:].flatten(0, 1)
    mot = motion[:, 1:].flatten(0, 1)
    wx, valid = warp_previous(x[:, :-1].flatten(0, 1), mot)
    wy, _ = warp_previous(y[:, :-1].flatten(0, 1), mot)
    err = ((cur_x - wx) - (cur_y - wy)).abs() / (cur_x.abs() + cur_y.abs() + SMAPE_EPS)
    mask = valid.expand_as(err)
    if reset is not None:
        keep = (~reset[:, 1:].bool()).flatten(0, 1).float().view(-1, 1, 1, 1)
        mask = mask * keep
    err = (err * mask).reshape(b, t - 1, -1).sum(dim=(1, 2))
    count = mask.reshape(b, t - 1, -1).sum(dim=(1, 2))
    return err / count.clamp_min(1.0)


class DenoiseLoss(nn.Module):
    """Weighted sum of SMAPE, gradient, temporal and hdr terms (weights from config).

    ``forward(pred, target, motion, reset) -> dict[name, [B]]`` with the *weighted* per-item
    terms whose weight is non-zero (``smape``, ``gradient``, ``temporal``, ``hdr``); a term with
    weight 0 is not computed and absent from the dict. ``pred, target: [B, T, 3, H, W]``.
    ``hdr_weight`` defaults to 0 (configs from before the term existed).
    """

    def __init__(self, smape_weight: float = 1.0, gradient_weight: float = 0.5, temporal_weight: float = 0.25,
                 hdr_weight: float = 0.0):
        super().__init__()
        self.weights = {"smape": float(smape_weight), "gradient": float(gradient_weight),
                        "temporal": float(temporal_weight), "hdr": float(hdr_weight)}

    def forward(self, pred: torch.Tensor, target: torch.Tensor, motion: torch.Tensor,
                reset: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        terms: dict[str, torch.Tensor] = {}
        if self.weights["smape"]:
            terms["smape"] = self.weights["smape"] * smape(pred, target)
        if self.weights["gradient"]:
            terms["gradient"] = self.weights["gradient"] * gradient_loss(pred, target)
        if self.weights["temporal"]:
            terms["temporal"] = self.weights["temporal"] * temporal_loss(pred, target, motion, reset)
        if self.weights["hdr"]:
            terms["hdr"] = self.weights["hdr"] * hdr_loss(pred, target)
        return terms


def masked_mean(per_item: torch.Tensor, mask: torch.Tensor | None) -> torch.Tensor:
    """Mean of ``per_item [B]`` over items where ``mask [B]`` is True (0 if none)."""
    if mask is None:
        return per_item.mean()
    m = mask.to(per_item.dtype)
    return (per_item * m).sum() / m.sum().clamp_min(1.0)


# ----------------------------------------------------------------------------- adversarial


class HingeAdversarial:
    """Hinge objective. Critic: ``mean relu(1 - D(r)) + mean relu(1 + D(f))``; generator: ``-mean D(f)``.

    ``real, fake: [N, C, H, W]``; ``D`` returns patch scores of any shape.
    """

    def critic_loss(self, critic: nn.Module, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
        return F.relu(1.0 - critic(real.detach()).float()).mean() + F.relu(1.0 + critic(fake.detach()).float()).mean()

    def generator_loss(self, critic: nn.Module, fake: torch.Tensor) -> torch.Tensor:
        return -critic(fake).float().mean()


class WassersteinGP:
    """WGAN-GP objective (Gulrajani et al. 2017).

    Critic: ``mean D(f) - mean D(r) + gp_weight * mean (||grad_m D(m)||_2 - 1)^2`` on random
    interpolates ``m = a r + (1 - a) f``, ``a ~ U[0, 1]`` per item; generator: ``-mean D(f)``.
    ``real, fake: [N, C, H, W]``.
    """

    def __init__(self, gp_weight: float = 10.0):
        self.gp_weight = float(gp_weight)

    def critic_loss(self, critic: nn.Module, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
        real, fake = real.detach(), fake.detach()
        loss = critic(fake).float().mean() - critic(real).float().mean()
        if self.gp_weight:
            loss = loss + self.gp_weight * gradient_penalty(critic, real, fake)
        return loss

    def generator_loss(self, critic: nn.Module, fake: torch.Tensor) -> torch.Tensor:
        return -critic(fake).float().mean()


def gradient_penalty(critic: nn.Module, real: torch.Tensor, fake: torch.Tensor) -> torch.Tensor:
    """WGAN-GP penalty ``mean (||grad_m D(m)||_2 - 1)^2`` on interpolates (scalar).

    ``real, fake: [N, C, H, W]``; ``m = a real + (1 - a) fake`` with ``a ~ U[0, 1]`` per item.
    """
    a = torch.rand(real.shape[0], 1, 1, 1, device=real.device, dtype=real.dtype)
    mix = (a * real.detach() + (1 - a) * fake.detach()).requires_grad_(True)
    scores = critic(mix)
    (grad,) = torch.autograd.grad(scores.float().sum(), mix, create_graph=True)
    return ((grad.flatten(1).norm(dim=1) - 1.0) ** 2).mean()


def feature_loss(student: torch.Tensor, teacher: torch.Tensor) -> torch.Tensor:
    """Normalized L1 between adapted student and teacher features (scalar).

    ``student, teacher: [N, C, h, w]`` (student already mapped by its 1x1 adapter):
    ``mean |s - t| / (mean |t| + 1e-3)`` in float32, so layers of any scale weigh alike.
    """
    s, t = student.float(), teacher.float()
    return (s - t).abs().mean() / (t.abs().mean() + 1e-3)
