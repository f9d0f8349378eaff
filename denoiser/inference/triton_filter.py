"""The pyramid kernel filter in Triton, for the CUDA backends (:mod:`denoiser.inference.cuda_backend`).

Same numbers as :func:`denoiser.nn.pyramid.pyramid_filter` (whose module docstring is the
definition) within float32 rounding, in three kernels:

* :func:`partition_softmax`: ``softmax_L(norm(head0[:, :L]))`` -> ``[B, L, H, W]`` float32;
* :func:`kernel_apply` (:func:`denoiser.nn.kernels.apply_kernels`): per pixel, the k*k logits are
  read once per pass straight from the U-Net head (any float dtype and strides, so an fp16
  channels-last head is read in place), non-finite values replaced (NaN -> 0, +-Inf -> +-1e4),
  scale-normalised with a two-pass variance over all k*k taps, and the softmax over the
  in-image taps (the centre tap always is) computed in float32 together with the weighted sum
  of the shifted input pixels: no ``[B, k*k, H, W]`` weights are written. With the scale the
  softmax is shifted by the logits' mean (every centred, scaled logit lies within
  ``scale * sqrt(k*k)`` of it, so ``exp`` stays normal for ``scale * sqrt(k*k) <= 80``; the
  OpenVINO extension's rule, ``denoiser/inference/ovext/kernel_apply.cpp``), otherwise by their maximum;
* :func:`add_upsampled`: ``bilinear_up(coarse) + fine`` (``F.interpolate``, ``align_corners=False``),
  and at level 0 the division by the filtered constant channel with the input-pixel fallback
  (:func:`denoiser.nn.pyramid.normalize`).

The average pooling of the partitions stays in torch (small, coarse levels). Inference only (no
autograd). The kernels also run on CPU tensors under Triton's interpreter (``TRITON_INTERPRET=1``,
set before triton is imported), which is how ``tests/inference/test_triton_filter.py`` checks them
without a GPU. Triton is an optional dependency (``pip install .[gpu]``); :func:`unavailable_reason`
says why the kernels cannot run here.
"""

from __future__ import annotations

import os
from collections.abc import Sequence

import torch
import torch.nn.functional as F

from denoiser.nn.pyramid import NORM_EPS, PyramidFilter, normalize, with_ones

try:
    import triton
    import triton.language as tl
except ImportError:  # optional: the CUDA backends fall back to the torch filter
    triton = tl = None

#: logits replaced for +-Inf (denoiser.nn.kernels.scale_logits)
LOGIT_INF = 1e4
#: largest float32: a value above it is +Inf
FLOAT32_MAX = 3.4028234663852886e38
#: pixels per Triton program
BLOCK = 256


def unavailable_reason(device: torch.device | str) -> str | None:
    """None when the Triton filter can run on ``device``, else why not (no triton; a CPU device
    without ``TRITON_INTERPRET=1``)."""
    if triton is None:
        return "triton is not installed (pip install .[gpu])"
    if torch.device(device).type == "cuda":
        return None if torch.cuda.is_available() else "no CUDA device"
    if os.environ.get("TRITON_INTERPRET") == "1":
        return None
    return f"{device}: Triton runs on CUDA (or on the CPU under TRITON_INTERPRET=1)"


if triton is not None:
    _LOGIT_INF = tl.constexpr(LOGIT_INF)
    _FLOAT32_MAX = tl.constexpr(FLOAT32_MAX)
    _NORM_EPS = tl.constexpr(NORM_EPS)

    @triton.jit
    def _finite_logit(v):
        """nan_to_num(v, nan=0, posinf=1e4, neginf=-1e4) in float32."""
        v = v.to(tl.float32)
        v = tl.where(v != v, 0.0, v)  # noqa: PLR0124 - NaN
        v = tl.where(v > _FLOAT32_MAX, _LOGIT_INF, v)
        return tl.where(v < -_FLOAT32_MAX, -_LOGIT_INF, v)

    @triton.jit
    def _kernel_apply(x_ptr, z_ptr, out_ptr, H, W, scale,
                      xsb, xsc, xsh, xsw, zsb, zsc, zsh, zsw,
                      C: tl.constexpr, CP: tl.constexpr, KS: tl.constexpr, HAS_SCALE: tl.constexpr,
                      MEAN_SHIFT: tl.constexpr, BLOCK: tl.constexpr):
        """out[b, :, p] = sum_t softmax_t(norm(z[b, :, p]) + border)[t] * x[b, :, p + offset_t];
        one program: BLOCK pixels of item b (flattened y * W + x), all C channels."""
        NT: tl.constexpr = KS * KS
        R: tl.constexpr = KS // 2
        b = tl.program_id(1)
        offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = offs < H * W
        py = offs // W
        px = offs % W
        zrow = z_ptr + b * zsb + py * zsh + px * zsw
        mean = tl.zeros([BLOCK], dtype=tl.float32)
        s = tl.full([BLOCK], 1.0, dtype=tl.float32)
        if HAS_SCALE:
            for t in tl.static_range(NT):
                mean += _finite_logit(tl.load(zrow + t * zsc, mask=valid, other=0.0))
            mean = mean / NT
            var = tl.zeros([BLOCK], dtype=tl.float32)
            for t in tl.static_range(NT):
                d = _finite_logit(tl.load(zrow + t * zsc, mask=valid, other=0.0)) - mean
                var += d * d
            s = scale / tl.sqrt(var / NT + 1.0)
        if MEAN_SHIFT:
            shift = tl.zeros([BLOCK], dtype=tl.float32)
        else:  # the largest in-image scaled logit
            shift = tl.full([BLOCK], float("-inf"), dtype=tl.float32)
            for t in tl.static_range(NT):
                yy = py + (t // KS - R)
                xx = px + (t % KS - R)
                inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W)
                v = _finite_logit(tl.load(zrow + t * zsc, mask=valid, other=0.0))
                shift = tl.where(inside, tl.maximum(shift, (v - mean) * s), shift)
        chan = tl.arange(0, CP)
        cmask = chan < C
        total = tl.zeros([BLOCK], dtype=tl.float32)
        acc = tl.zeros([BLOCK, CP], dtype=tl.float32)
        for t in tl.static_range(NT):
            yy = py + (t // KS - R)
            xx = px + (t % KS - R)
            inside = (yy >= 0) & (yy < H) & (xx >= 0) & (xx < W) & valid
            v = _finite_logit(tl.load(zrow + t * zsc, mask=valid, other=0.0))
            e = tl.where(inside, tl.exp((v - mean) * s - shift), 0.0)
            total += e
            ptr = x_ptr + b * xsb + chan[None, :] * xsc + yy[:, None] * xsh + xx[:, None] * xsw
            xv = tl.load(ptr, mask=inside[:, None] & cmask[None, :], other=0.0).to(tl.float32)
            acc += e[:, None] * xv
        out = acc / total[:, None]
        optr = out_ptr + b * C * H * W + chan[None, :] * (H * W) + offs[:, None]
        tl.store(optr, out, mask=valid[:, None] & cmask[None, :])

    @triton.jit
    def _partition_softmax(z_ptr, out_ptr, H, W, scale, zsb, zsc, zsh, zsw,
                           L: tl.constexpr, LP: tl.constexpr, HAS_SCALE: tl.constexpr, BLOCK: tl.constexpr):
        """out[b, :, p] = softmax_L(norm(z[b, :L, p])) (torch's order: z * s, then max shift)."""
        b = tl.program_id(1)
        offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = offs < H * W
        py = offs // W
        px = offs % W
        lev = tl.arange(0, LP)
        lmask = lev < L
        m2 = valid[:, None] & lmask[None, :]
        ptr = z_ptr + b * zsb + lev[None, :] * zsc + py[:, None] * zsh + px[:, None] * zsw
        v = _finite_logit(tl.load(ptr, mask=m2, other=0.0))
        if HAS_SCALE:
            mean = tl.sum(tl.where(m2, v, 0.0), axis=1) / L
            d = tl.where(m2, v - mean[:, None], 0.0)
            v = v * (scale / tl.sqrt(tl.sum(d * d, axis=1) / L + 1.0))[:, None]
        v = tl.where(lmask[None, :], v, float("-inf"))
        e = tl.exp(v - tl.max(v, axis=1)[:, None])
        e = tl.where(lmask[None, :], e, 0.0)
        out = e / tl.sum(e, axis=1)[:, None]
        tl.store(out_ptr + b * L * H * W + lev[None, :] * (H * W) + offs[:, None], out, mask=m2)

    @triton.jit
    def _add_upsampled(c_ptr, f_ptr, x_ptr, out_ptr, h, w, H, W, ry, rx,
                       xsb, xsc, xsh, xsw,
                       C1: tl.constexpr, CP: tl.constexpr, FINAL: tl.constexpr, BLOCK: tl.constexpr):
        """acc = bilinear_up(coarse [B, C1, h, w]) + fine [B, C1, H, W] (contiguous); FINAL: out
        [B, C1 - 1, H, W] = acc[:C1-1] / acc[C1-1], x where that is <= NORM_EPS; else out = acc."""
        b = tl.program_id(1)
        offs = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
        valid = offs < H * W
        py = offs // W
        px = offs % W
        sy = tl.maximum(ry * (py.to(tl.float32) + 0.5) - 0.5, 0.0)
        sx = tl.maximum(rx * (px.to(tl.float32) + 0.5) - 0.5, 0.0)
        y0 = tl.minimum(sy.to(tl.int32), h - 1)
        x0 = tl.minimum(sx.to(tl.int32), w - 1)
        y1 = y0 + (y0 < h - 1).to(tl.int32)
        x1 = x0 + (x0 < w - 1).to(tl.int32)
        ly1 = sy - y0.to(tl.float32)
        lx1 = sx - x0.to(tl.float32)
        ly0 = 1.0 - ly1
        lx0 = 1.0 - lx1
        chan = tl.arange(0, CP)
        m2 = valid[:, None] & (chan < C1)[None, :]
        cb = c_ptr + b * C1 * h * w + chan[None, :] * (h * w)
        v00 = tl.load(cb + (y0 * w + x0)[:, None], mask=m2, other=0.0)
        v01 = tl.load(cb + (y0 * w + x1)[:, None], mask=m2, other=0.0)
        v10 = tl.load(cb + (y1 * w + x0)[:, None], mask=m2, other=0.0)
        v11 = tl.load(cb + (y1 * w + x1)[:, None], mask=m2, other=0.0)
        up = ly0[:, None] * (lx0[:, None] * v00 + lx1[:, None] * v01) + \
            ly1[:, None] * (lx0[:, None] * v10 + lx1[:, None] * v11)
        acc = up + tl.load(f_ptr + b * C1 * H * W + chan[None, :] * (H * W) + offs[:, None], mask=m2, other=0.0)
        if FINAL:
            den = tl.sum(tl.where(chan[None, :] == C1 - 1, acc, 0.0), axis=1)
            m3 = valid[:, None] & (chan < C1 - 1)[None, :]
            xv = tl.load(x_ptr + b * xsb + chan[None, :] * xsc + py[:, None] * xsh + px[:, None] * xsw,
                         mask=m3, other=0.0).to(tl.float32)
            ok = den > _NORM_EPS
            out = tl.where(ok[:, None], acc / tl.maximum(den, _NORM_EPS)[:, None], xv)
            tl.store(out_ptr + b * (C1 - 1) * H * W + chan[None, :] * (H * W) + offs[:, None], out, mask=m3)
        else:
            tl.store(out_ptr + b * C1 * H * W + chan[None, :] * (H * W) + offs[:, None], acc, mask=m2)


def _pow2(n: int) -> int:
    return 1 << max(int(n) - 1, 0).bit_length()


def _grid(b: int, h: int, w: int) -> tuple[int, int]:
    return (triton.cdiv(h * w, BLOCK), b)


def kernel_apply(x: torch.Tensor, logits: torch.Tensor, scale: float | None = None) -> torch.Tensor:
    """:func:`denoiser.nn.kernels.apply_kernels` in one Triton kernel (no autograd).

    x: ``[B, C, H, W]`` any float dtype and strides; logits: ``[B, k*k, H, W]`` (k odd) any float
    dtype and strides; scale: logit normalisation (None: raw logits). Returns ``[B, C, H, W]`` float32.
    """
    from denoiser.nn.kernels import kernel_size_of

    k = kernel_size_of(logits)
    b, c, h, w = x.shape
    out = torch.empty(b, c, h, w, device=x.device, dtype=torch.float32)
    has_scale = scale is not None
    mean_shift = has_scale and float(scale) * k <= 80.0  # scale * sqrt(k*k)
    _kernel_apply[_grid(b, h, w)](x, logits, out, h, w, float(scale or 1.0), *x.stride(), *logits.stride(),
                                  C=c, CP=_pow2(c), KS=k, HAS_SCALE=has_scale, MEAN_SHIFT=mean_shift, BLOCK=BLOCK)
    return out


def partition_softmax(head0: torch.Tensor, levels: int, scale: float | None = None) -> torch.Tensor:
    """``softmax_L(scale_logits(head0[:, :levels]))``: head0 ``[B, >= L, H, W]`` any float dtype
    and strides -> ``[B, L, H, W]`` float32 (:func:`denoiser.nn.pyramid.partition_levels`)."""
    b, _, h, w = head0.shape
    out = torch.empty(b, levels, h, w, device=head0.device, dtype=torch.float32)
    _partition_softmax[_grid(b, h, w)](head0, out, h, w, float(scale or 1.0), *head0.stride(),
                                       L=levels, LP=_pow2(levels), HAS_SCALE=scale is not None, BLOCK=BLOCK)
    return out


def add_upsampled(coarse: torch.Tensor, fine: torch.Tensor, x: torch.Tensor | None = None) -> torch.Tensor:
    """``F.interpolate(coarse, fine's size, bilinear, align_corners=False) + fine``.

    coarse: ``[B, C1, h, w]``, fine: ``[B, C1, H, W]`` float32. With ``x`` ``[B, C1 - 1, H, W]``
    (any float dtype and strides) the sum is normalised as :func:`denoiser.nn.pyramid.normalize`
    (``acc[:, :-1] / acc[:, -1]``, x where that is <= NORM_EPS) -> ``[B, C1 - 1, H, W]``; without,
    -> ``[B, C1, H, W]``. All float32.
    """
    coarse, fine = coarse.float().contiguous(), fine.float().contiguous()
    b, c1, hh, ww = fine.shape
    h, w = coarse.shape[-2:]
    final = x is not None
    out = torch.empty(b, c1 - 1 if final else c1, hh, ww, device=fine.device, dtype=torch.float32)
    xs = x.stride() if final else (0, 0, 0, 0)
    _add_upsampled[_grid(b, hh, ww)](coarse, fine, x if final else fine, out, h, w, hh, ww,
                                     float(h) / float(hh), float(w) / float(ww), *xs,
                                     C1=c1, CP=_pow2(c1), FINAL=final, BLOCK=BLOCK)
    return out


def pyramid_filter_triton(x: torch.Tensor, heads: Sequence[torch.Tensor], kernel_sizes: Sequence[int],
                          logit_scale: float | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:func:`denoiser.nn.pyramid.pyramid_filter` with the Triton kernels (same arguments and
    result: x ``[B, 3, H, W]``, heads[i] ``[B, head_channels[i], H/2^i, W/2^i]`` ->
    ``(output [B, 3, H, W] float32, {"partition": [B, L, H, W]})``)."""
    levels = len(kernel_sizes)
    with torch.autocast(device_type=x.device.type, enabled=False):
        x = x.float()
        partition = partition_softmax(heads[0], levels, logit_scale)
        x1 = with_ones(x)
        logits = [heads[0][:, levels:]] + list(heads[1:levels])
        filtered = []
        for i in range(levels):
            part = partition[:, i: i + 1] * x1
            filtered.append(kernel_apply(F.avg_pool2d(part, 2 ** i) if i > 0 else part, logits[i], logit_scale))
        if levels == 1:
            return normalize(filtered[0], x), {"partition": partition}
        acc = filtered[-1]
        for i in range(levels - 2, -1, -1):
            acc = add_upsampled(acc, filtered[i], x if i == 0 else None)
        return acc, {"partition": partition}


class TritonPyramidFilter(PyramidFilter):
    """A :class:`~denoiser.nn.pyramid.PyramidFilter` whose forward runs the Triton kernels
    (:func:`pyramid_filter_triton`); same configuration, same numbers within float32 rounding."""

    @classmethod
    def of(cls, module: PyramidFilter) -> TritonPyramidFilter:
        """The Triton version of ``module`` (kernel sizes and logit scale copied)."""
        return cls(module.kernel_sizes, module.logit_scale)

    def forward(self, x: torch.Tensor, heads: Sequence[torch.Tensor], scale: torch.Tensor
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: ``[B, 3, H, W]``; heads[i]: ``[B, head_channels[i], H/2^i, W/2^i]``; scale ``[B, 1, 1, 1]``
        (unused). Returns ``(output [B, 3, H, W] float32, {"partition": [B, L, H, W]})``."""
        return pyramid_filter_triton(x, heads, self.kernel_sizes, self.logit_scale)


def use_triton_filter(net: torch.nn.Module) -> int:
    """Replace, in place, every :class:`~denoiser.nn.pyramid.PyramidFilter` child of ``net`` (not
    one already Triton) by its :class:`TritonPyramidFilter`; returns how many were replaced."""
    replaced = 0
    for parent in list(net.modules()):
        for name, child in list(parent.named_children()):
            if type(child) is PyramidFilter:
                setattr(parent, name, TritonPyramidFilter.of(child))
                replaced += 1
    return replaced
