"""LearnedUpsamplingPyramid: the NPPD baseline's pyramid, with predicted upsampling weights.

Baseline after Balint et al., "Neural Partitioning Pyramids for Denoising Monte Carlo
Renderings" (SIGGRAPH 2023; public code github.com/balintio/nppd, read, not copied). The
partitioning and the per-level kernels are those of :class:`~denoiser.nn.pyramid.PyramidFilter`;
what differs is the coarse-to-fine recombination. Our paper's pyramid upsamples bilinearly; NPPD
lets the network predict, at every coarse pixel, how that pixel is *splatted* onto the finer
level: 16 weights over the 4 x 4 fine pixels centred on its 2 x 2 block (fine offsets -1..2 in
y and x from the block's top-left pixel), a softmax times 4 (a coarse pixel is the average of
4 fine ones, so the splat keeps the total energy). Bilinear 2x upsampling (``align_corners=False``)
is the special case of the separable weights ``[1, 3, 3, 1] / 4`` per axis
(:func:`bilinear_splat_logits`).

For linear radiance ``x`` ``[B, 3, H, W]`` and L levels, with ``x1 = [x, 1]``:

    w       = softmax_L(norm(partition logits))                  [B, L, H, W]
    y_i     = apply_kernels(avg_pool_{2^i}(w_i * x1), norm(kernel logits of level i))
    u_i     = 4 * softmax_16(norm(upsampling logits of level i) + prior)   [B, 16, H/2^i, W/2^i], i >= 1
    acc     = y_{L-1};  acc = splat_up(acc, u_{i+1}) + y_i  for i = L-2 .. 0
    output  = acc[:, :3] / acc[:, 3:]   (x where acc[:, 3:] <= NORM_EPS)

**Ours, not NPPD's:** (1) the convexity guarantee of PyramidFilter is kept: the splat is a
non-negative linear operator applied identically to every channel of ``[x, 1]``, so the
division by the constant channel makes each output pixel a convex combination of input pixels
(weights lost past the image border are lost from the normaliser too); NPPD preserves only the
total energy. (2) Logits pass :func:`~denoiser.nn.kernels.scale_logits` (``logit_scale``) like
every softmax here. (3) ``bilinear_prior=True`` adds ``log`` of the bilinear splat weights to the
upsampling logits, so an untrained head (logits near 0) starts at our bilinear pyramid and learns
a correction; NPPD's own scheme is ``bilinear_prior=False`` (uniform 4 x 4 splat at zero logits).
(4) NPPD's extra 5 x 5 kernel on the warped previous output is not built; temporal blending is
:class:`~denoiser.nn.temporal.TemporalRecurrence`'s.

Head layout (``head_channels``): level 0 ``L + k_0^2`` (partition logits first, as in
PyramidFilter); level i >= 1 ``k_i^2 + 16`` (kernel logits, then the upsampling logits that
splat level i onto level i-1).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from denoiser.nn.kernels import apply_kernels, scale_logits
from denoiser.nn.pyramid import check_kernel_sizes, normalize, partition_levels

#: splat footprint per axis: a coarse pixel covers fine offsets -1, 0, 1, 2 from its block's first pixel
FOOTPRINT = 4
#: splat weights per coarse pixel
SPLAT_TAPS = FOOTPRINT * FOOTPRINT
#: per fine-pixel parity (0 = even row/column, 1 = odd): the two contributing taps ``a`` of the
#: footprint and the offset of their coarse pixel in the 1-padded coarse grid (coarse Y' + offset - 1)
PARITY_TAPS = (((1, 1), (3, 0)), ((2, 1), (0, 2)))


def bilinear_splat_logits() -> np.ndarray:
    """``[16]`` log of the splat weights (divided by 4) that equal bilinear 2x upsampling:
    the outer product of ``[1, 3, 3, 1] / 4`` per axis, divided by 4 so they sum to one."""
    axis = np.array([1.0, 3.0, 3.0, 1.0]) / 4.0
    return np.log(np.outer(axis, axis).reshape(-1) / 4.0).astype(np.float32)


def splat_upsample(coarse: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Splat every coarse pixel onto the 4 x 4 fine pixels around its 2 x 2 block.

    coarse: ``[B, C, h, w]``; weights: ``[B, 16, h, w]`` non-negative, tap ``a*4 + b`` goes to
    fine pixel ``(2Y - 1 + a, 2X - 1 + b)`` from coarse ``(Y, X)`` (taps past the border are
    dropped). Returns ``[B, C, 2h, 2w]`` (float32 in, float32 out)::

        out[b, c, y, x] = sum_{Y, X, a, b: 2Y-1+a = y, 2X-1+b = x} weights[b, a*4+b, Y, X] * coarse[b, c, Y, X]

    Written as a gather: a fine pixel of row parity ``py`` receives from two coarse rows
    (:data:`PARITY_TAPS`), so each of the 4 parities sums 4 shifted products, and a pixel
    shuffle interleaves them (traceable; 16 products at the coarse size).
    """
    b, c, h, w = coarse.shape
    products = F.pad(coarse.unsqueeze(1) * weights.unsqueeze(2), (1, 1, 1, 1))  # [B, 16, C, h+2, w+2]
    parities = []
    for py in range(2):
        for px in range(2):
            total = None
            for a, oy in PARITY_TAPS[py]:
                for t, ox in PARITY_TAPS[px]:
                    view = products[:, a * FOOTPRINT + t, :, oy: oy + h, ox: ox + w]
                    total = view if total is None else total + view
            parities.append(total)
    stacked = torch.stack(parities, dim=2).reshape(b, c * 4, h, w)  # channel c*4 + py*2 + px
    return F.pixel_shuffle(stacked, 2)


class LearnedUpsamplingPyramid(nn.Module):
    """Partitioning pyramid whose coarse-to-fine upsampling weights are predicted (NPPD).

    Args:
        kernel_sizes: kernel size per level, finest first (``${kernel.sizes}``).
        logit_scale: softmax sharpness over scale-normalised logits, as in
            :class:`~denoiser.nn.pyramid.PyramidFilter` (None = raw logits, NPPD's own).
        bilinear_prior: add the log bilinear weights to the upsampling logits (zero logits =
            bilinear); False = NPPD's plain softmax.

    ``head_channels``: level 0 ``L + k_0^2``; level i >= 1 ``k_i^2 + 16``.
    """

    def __init__(self, kernel_sizes: Sequence[int], logit_scale: float | None = None,
                 bilinear_prior: bool = False):
        super().__init__()
        self.kernel_sizes = check_kernel_sizes(kernel_sizes)
        self.logit_scale = None if logit_scale is None else float(logit_scale)
        self.bilinear_prior = bool(bilinear_prior)
        self.levels = len(self.kernel_sizes)
        self.head_channels = [self.levels + self.kernel_sizes[0] ** 2] + [
            k * k + SPLAT_TAPS for k in self.kernel_sizes[1:]]
        self.multiple = 2 ** (self.levels - 1)

    def upsampling_weights(self, logits: torch.Tensor) -> torch.Tensor:
        """``[B, 16, h, w]`` upsampling logits -> splat weights ``[B, 16, h, w]`` float32, >= 0, summing to 4."""
        z = scale_logits(logits, self.logit_scale)
        if self.bilinear_prior:
            prior = torch.from_numpy(bilinear_splat_logits()).to(z.device).view(1, SPLAT_TAPS, 1, 1)
            z = z + prior
        return 4.0 * torch.softmax(z, dim=1)

    def forward(self, x: torch.Tensor, heads: Sequence[torch.Tensor], scale: torch.Tensor
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: ``[B, 3, H, W]`` linear radiance (H, W multiples of 2^(L-1));
        heads[i]: ``[B, head_channels[i], H/2^i, W/2^i]``; scale: ``[B, 1, 1, 1]`` (unused).

        Returns ``(output [B, 3, H, W] float32, {"partition": [B, L, H, W]})``.
        """
        with torch.autocast(device_type=x.device.type, enabled=False):
            head0 = heads[0].float()
            x1, partition, parts = partition_levels(x, head0, self.levels, self.logit_scale)
            filtered, upsampling = [], [None]
            for i, part in enumerate(parts):
                head = head0[:, self.levels:] if i == 0 else heads[i].float()
                k2 = self.kernel_sizes[i] ** 2
                filtered.append(apply_kernels(part, head[:, :k2], self.logit_scale))
                if i > 0:
                    upsampling.append(self.upsampling_weights(head[:, k2:]))
            acc = filtered[-1]
            for i in range(self.levels - 2, -1, -1):
                acc = splat_upsample(acc, upsampling[i + 1]) + filtered[i]
            return normalize(acc, x1[:, :-1]), {"partition": partition}

