"""ONND: online neural denoising with cross-regression, an evaluation method (our reading).

Baseline "ONND" of the comparison, identified as Choi et al., *Online Neural Denoising with
Cross-Regression for Interactive Rendering*, ACM TOG 43(6), SIGGRAPH Asia 2024 (public code:
``CGLab-GIST/cross-denoiser``). This is an independent re-implementation from the paper's idea
and a reading of that code; nothing is copied. See ``docs/baselines_onnd.md``.

Per frame (``S`` samples per pixel, split into two independent half buffers A and B)::

    y_a, y_b  = log1p(mean of samples[:S//2]), log1p(mean of samples[S//2:])   [1, 3, H, W]
    v         = box3x3(mean_c (y_a - y_b)^2) / 2                               [1, 1, H, W]
    pilot_a   = cross_regression(y_a, guide=y_b)    (weights from B, values from A)
    pilot_b   = cross_regression(y_b, guide=y_a)
    logits, a = UNet([pilot_a, pilot_b, prev, albedo, normal])   [1, k*k, H, W], [1, 1, H, W]
    f_x       = apply_kernels(pilot_x, logits); out_x = a * f_x + (1 - a) * prev   (x = a, b)
    loss      = relmse(out_a, pilot_b) + relmse(out_b, pilot_a)      (no reference used)
    one Adam step on loss; output = expm1(a * apply_kernels((pilot_a + pilot_b)/2) + (1 - a) * prev)

``prev`` is the previous log output warped by the backward ``motion`` (zero weight where the
warp reads outside the image, at the first frame and at camera cuts).

**Cross-regression** (:func:`cross_regression`): for every pixel c, a weighted local linear
regression over the ``(2r+1)^2`` window of the values ``y`` onto the features
``x_j = [1, albedo_j - albedo_c, normal_j - normal_c]`` (P = 7) with ridge ``lambda`` on the
slopes; the weights come from the *other* half, ``w_cj = exp(-mean_c (g_c - g_j)^2 / (v_c + v_j
+ eps))``, so the noise of ``y`` does not choose its own weights. The estimate is the intercept
(the fit evaluated at c), clamped to the window's range of ``y``.

Data: ONND needs per-sample radiance ``frame["samples"] [1, S, 3, H, W]`` with ``S >= 2``. Render
it with ``denoiser-render save_samples=true`` (``conf/render.yaml``; the renderer then writes
``spp`` single-sample passes as ``sample.<k>.R/G/B``, :func:`denoiser.buffers.sample_channels`,
and ``color`` is their mean). Frames without them raise :class:`~denoiser.errors.ConfigError`.

State: the network and the Adam moments persist across frames and camera cuts (training goes
on through the sequence, as in the paper); :meth:`reset` (a new sequence) re-initialises them
from ``seed`` (the paper's script starts each scene from a fresh network), unless
``keep_weights=True``. The temporal history is dropped at :meth:`reset` and at ``reset=True``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from denoiser.errors import ConfigError
from denoiser.nn.kernels import apply_kernels
from denoiser.nn.unet import UNet
from denoiser.nn.warp import warp_all
from denoiser.nonfinite import replace_tensor

EPS = 1e-4
#: largest log1p radiance kept (expm1 stays finite in float32; log1p(65504) ~ 11.1)
LOG_MAX = 30.0


def half_buffers(samples: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``samples [1, S, 3, H, W]`` (S >= 2) -> the two half means ``A, B``, each ``[1, 3, H, W]``.

    A averages samples ``0 .. S//2 - 1``, B the rest (one more when S is odd).
    """
    if samples.dim() != 5 or samples.shape[1] < 2:
        raise ConfigError(f"ONND needs at least 2 per-sample radiances [1, S>=2, 3, H, W], got {tuple(samples.shape)}")
    s = samples.shape[1] // 2
    samples = replace_tensor(samples).clamp_min(0.0)
    return samples[:, :s].mean(dim=1), samples[:, s:].mean(dim=1)


def half_variance(y_a: torch.Tensor, y_b: torch.Tensor) -> torch.Tensor:
    """Per-pixel variance of one half ``[1, 1, H, W]`` from ``y_a, y_b [1, 3, H, W]``:
    the 3x3 box mean of ``mean_c (y_a - y_b)^2 / 2`` (the halves are independent)."""
    d = ((y_a - y_b) ** 2).mean(dim=1, keepdim=True) / 2
    return F.avg_pool2d(F.pad(d, (1, 1, 1, 1), mode="replicate"), 3, stride=1)


def _cross_regression_rows(y: torch.Tensor, guide: torch.Tensor, var: torch.Tensor, feats: torch.Tensor,
                           radius: int, ridge: float, rows: slice, h: int) -> torch.Tensor:
    """Cross-regression of output rows ``rows`` (inputs ``[1, C, H, W]``); ``[1, 3, len(rows), W]``."""
    k = 2 * radius + 1
    lo, hi = max(rows.start - radius, 0), min(rows.stop + radius, h)
    top = rows.start - lo  # halo rows above the block in the slice

    def taps(x: torch.Tensor) -> torch.Tensor:  # [1, C, h', W] -> [C, K, N] of the block's pixels
        c, w = x.shape[1], x.shape[-1]
        u = F.unfold(x[:, :, lo:hi], k, padding=radius).view(c, k * k, hi - lo, w)
        return u[:, :, top: top + rows.stop - rows.start].reshape(c, k * k, -1)

    valid = taps(torch.ones_like(var))[0]  # [K, N]: 1 where the tap is inside the image
    yt, gt, vt, ft = taps(y), taps(guide), taps(var)[0], taps(feats)
    centre = (k * k) // 2
    dist = ((gt - gt[:, centre: centre + 1]) ** 2).mean(dim=0) / (vt + vt[centre: centre + 1] + EPS)
    wts = torch.exp(-dist) * valid  # [K, N]
    x = torch.cat([valid[None], (ft - ft[:, centre: centre + 1]) * valid[None]], dim=0)  # [P, K, N]
    xw = x * wts[None]
    # sums over the taps as elementwise products (a batched matmul of tiny P x K blocks is slow on CPU)
    n_p = x.shape[0]
    gram = x.new_empty(n_p, n_p, x.shape[-1])
    for p in range(n_p):
        for q in range(p, n_p):  # symmetric: P (P + 1) / 2 sums
            gram[p, q] = gram[q, p] = (xw[p] * x[q]).sum(dim=0)
    gram = gram.permute(2, 0, 1)  # [N, P, P]
    rhs = torch.stack([(xw[p:p + 1] * yt).sum(dim=1) for p in range(n_p)]).permute(2, 0, 1)  # [N, P, 3]
    reg = torch.full((x.shape[0],), float(ridge), dtype=y.dtype, device=y.device)
    reg[0] = 0.0
    beta = torch.linalg.solve(gram + torch.diag(reg), rhs)  # the centre tap keeps gram[0,0] >= 1
    est = beta[:, 0, :].T  # [3, N]
    big = torch.finfo(y.dtype).max
    ymin = torch.where(valid[None] > 0, yt, big).amin(dim=1)
    ymax = torch.where(valid[None] > 0, yt, -big).amax(dim=1)
    est = torch.where(torch.isfinite(est), est, yt[:, centre])
    est = torch.minimum(torch.maximum(est, ymin), ymax)
    return est.reshape(1, 3, rows.stop - rows.start, -1)


@torch.no_grad()
def cross_regression(y: torch.Tensor, guide: torch.Tensor, var: torch.Tensor, feats: torch.Tensor,
                     radius: int = 3, ridge: float = 1e-2, max_pixels: int = 32768) -> torch.Tensor:
    """Weighted local linear regression of ``y`` onto ``feats``, weighted by ``guide`` (see module doc).

    y, guide: ``[1, 3, H, W]`` (log radiance of two independent halves); var: ``[1, 1, H, W]``
    per-pixel variance of one half; feats: ``[1, F, H, W]`` (albedo, normal). Returns ``[1, 3, H, W]``:
    at pixel c the intercept of the fit over the in-image taps of the ``(2r+1)^2`` window,
    clamped to the window's range of ``y``. Computed in row blocks of at most ``max_pixels`` pixels
    (memory ``O(max_pixels * (2r+1)^2 * (F+1))``).
    """
    h, w = y.shape[-2:]
    step = max(1, max_pixels // max(w, 1))
    y, guide, var, feats = (t.float() for t in (y, guide, var, feats))
    return torch.cat([_cross_regression_rows(y, guide, var, feats, radius, ridge, slice(r0, min(r0 + step, h)), h)
                      for r0 in range(0, h, step)], dim=2)


def relmse(x: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Relative MSE, mean over ``[1, 3, H, W]``: ``(x - t)^2 / (t^2 + 1e-2)`` (target detached)."""
    target = target.detach()
    return ((x - target) ** 2 / (target ** 2 + 1e-2)).mean()


class OnlineCrossRegression:
    """ONND (Choi et al. 2024) as a per-frame evaluation method; see the module docstring.

    Args:
        label: display name.
        regression_radius: cross-regression window radius r (window ``(2r+1)^2``; the paper's code 17x17).
        ridge: ridge on the regression slopes.
        kernel_size: k of the per-pixel k x k filter the network predicts (odd).
        widths: U-Net encoder widths (finest first); the bottleneck is twice the last.
        lr: Adam learning rate (one step per frame).
        centre_logit: initial logit of the kernel's centre tap (the others start at 0): 0 starts
            from a k x k box filter of the pilot estimates, a large value from the pilot itself
            (the identity filter), which the online steps then widen where the loss asks for it.
        seed: initialisation seed of the network.
        keep_weights: keep the trained network across :meth:`reset` (new sequences).
        threads: torch intra-op threads during a call (None: torch's current setting).
        device: where it runs; frames are moved there.

    ``__call__(frame, reset)``: ``frame`` holds ``[1, C, H, W]`` buffers plus ``samples
    [1, S, 3, H, W]``; returns ``[1, 3, H, W]`` float32 linear HDR, finite and >= 0.
    """

    recurrent = True
    backend = "PyTorch eager + online step"  # denoiser-bench's backend column
    uses_samples = True  # evaluation passes frame["samples"] only to methods that say so

    def __init__(self, label: str = "ONND", regression_radius: int = 3, ridge: float = 1e-2,
                 kernel_size: int = 5, widths=(8, 16), lr: float = 1e-3, centre_logit: float = 8.0,
                 seed: int = 0, keep_weights: bool = False, threads: int | None = None, device: str = "cpu"):
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ConfigError(f"ONND kernel_size must be odd and >= 1, got {kernel_size}")
        if regression_radius < 0:
            raise ConfigError(f"ONND regression_radius must be >= 0, got {regression_radius}")
        self.label = label
        self.radius, self.ridge, self.k = int(regression_radius), float(ridge), int(kernel_size)
        self.widths = [int(w) for w in widths]
        self.lr, self.seed, self.keep_weights = float(lr), int(seed), bool(keep_weights)
        self.centre_logit = float(centre_logit)
        self.threads = int(threads) if threads else None
        self.device = torch.device(device)
        self.last_loss: float | None = None
        self._init_network()
        self._prev: torch.Tensor | None = None

    def _init_network(self) -> None:
        """A fresh U-Net (``[1, 15, H, W]`` -> ``[1, k*k + 1, H, W]``) and Adam, seeded by ``seed``."""
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(self.seed)
            w = self.widths
            self.net = UNet(15, w, 2 * w[-1], list(reversed(w[:-1])), [self.k * self.k + 1]).to(self.device)
            head = self.net.heads[0]
            torch.nn.init.zeros_(head.weight)  # start from one fixed filter everywhere and alpha = 0.5
            torch.nn.init.zeros_(head.bias)
            with torch.no_grad():
                head.bias[(self.k * self.k) // 2] = self.centre_logit  # 0: a box filter
        self.net.train()
        self.optimizer = torch.optim.Adam(self.net.parameters(), lr=self.lr)

    @property
    def num_parameters(self) -> int:
        return sum(p.numel() for p in self.net.parameters())

    def reset(self) -> None:
        """A new sequence: drop the history; re-initialise the network unless ``keep_weights``."""
        self._prev = None
        if not self.keep_weights:
            self._init_network()

    def __call__(self, frame: dict, reset: bool = False) -> torch.Tensor:
        """One frame (``[1, C, H, W]`` buffers + ``samples [1, S, 3, H, W]``) -> ``[1, 3, H, W]``."""
        if frame.get("samples") is None:
            raise ConfigError("ONND needs per-sample radiance (frame['samples'], channels sample.<k>.R/G/B of "
                              "denoiser.buffers.sample_channels): render the data with save_samples=true")
        threads = self.threads
        old = torch.get_num_threads()
        if threads and threads != old:
            torch.set_num_threads(threads)
        try:
            with torch.inference_mode(False):  # the online step needs autograd, even inside a caller's inference mode
                return self._denoise(frame, reset).to(frame["color"].device)
        finally:
            if threads and threads != old:
                torch.set_num_threads(old)

    def _denoise(self, frame: dict, reset: bool) -> torch.Tensor:
        dev = self.device
        a, b = half_buffers(frame["samples"].to(dev))
        h, w = a.shape[-2:]
        y_a = torch.log1p(a).clamp_max(LOG_MAX)
        y_b = torch.log1p(b).clamp_max(LOG_MAX)
        albedo = replace_tensor(frame["albedo"].to(dev)).clamp(0.0, 1.0)
        normal = replace_tensor(frame["normal"].to(dev)).clamp(-1.0, 1.0)
        feats = torch.cat([albedo, normal], dim=1)
        var = half_variance(y_a, y_b)
        pilot_a = cross_regression(y_a, y_b, var, feats, self.radius, self.ridge)
        pilot_b = cross_regression(y_b, y_a, var, feats, self.radius, self.ridge)

        if reset or self._prev is None or self._prev.shape[-2:] != (h, w):
            prev = torch.zeros_like(y_a)
            ok = torch.zeros_like(var)
        else:
            # warp_all sanitises and clamps the motion itself (denoiser.nn.warp.sample_positions)
            (prev,), cover = warp_all([self._prev], frame["motion"].to(dev))
            ok = (cover > 0.999).float()

        x = torch.cat([pilot_a, pilot_b, prev, albedo, normal], dim=1)
        m = self.net.multiple
        ph, pw = (-h) % m, (-w) % m
        x = F.pad(x, (0, pw, 0, ph), mode="replicate") if ph or pw else x
        self.optimizer.zero_grad(set_to_none=True)
        with torch.enable_grad():
            head = self.net(x)[0][0][:, :, :h, :w]
            logits, alpha = head[:, :-1], torch.sigmoid(head[:, -1:].float())
            alpha = ok * alpha + (1 - ok)  # no usable history: spatial only
            out_a = alpha * apply_kernels(pilot_a, logits) + (1 - alpha) * prev
            out_b = alpha * apply_kernels(pilot_b, logits) + (1 - alpha) * prev
            loss = 0.5 * (relmse(out_a, pilot_b) + relmse(out_b, pilot_a))
            if torch.isfinite(loss):
                loss.backward()
                torch.nn.utils.clip_grad_norm_(self.net.parameters(), 1.0)
                self.optimizer.step()  # the online training step of this frame
        with torch.no_grad():
            out_log = alpha * apply_kernels(0.5 * (pilot_a + pilot_b), logits.detach()) + (1 - alpha) * prev
            out_log = torch.nan_to_num(out_log.detach(), nan=0.0).clamp(0.0, LOG_MAX)
        self.last_loss = float(loss.detach())
        self._prev = out_log
        return torch.expm1(out_log).clamp_min(0.0).float()
