"""The Triton pyramid filter (denoiser/inference/triton_filter.py) against the torch module and a plain
loop over pixels in float64, at odd sizes, k = 3 and 5, with hard values (large logits, NaN and
Inf logits, zero input, fp16 and channels-last heads). Without a GPU the kernels run under
Triton's interpreter (``TRITON_INTERPRET=1``) on CPU tensors; without triton the tests skip."""

from __future__ import annotations

import importlib
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest
import torch
import torch.nn.functional as F

DEVICE = "cuda" if torch.cuda.is_available() else "cpu"
#: relative tolerance: the interpreter's exp is NumPy's (correctly rounded); on a GPU tl.exp is
#: ex2.approx of x * log2(e), whose error grows with |x| (up to about 45 here: ~3e-6)
TOL = 2e-6 if DEVICE == "cpu" else 2e-5
if DEVICE == "cpu" and "triton" not in sys.modules:
    os.environ["TRITON_INTERPRET"] = "1"  # read when triton decorates its own functions, at import

pytest.importorskip("triton", reason="triton is not installed (pip install .[gpu])")

import triton.language.standard
from triton.runtime.interpreter import InterpretedFunction

from denoiser.nn.kernels import apply_kernels
from denoiser.nn.pyramid import normalize, pyramid_filter

#: whether the kernels can run in this process: on a GPU, or interpreted (triton imported after
#: TRITON_INTERPRET=1 was set; in a whole-suite run an earlier import, e.g. Lightning's, came
#: first: then test_in_a_fresh_interpreter runs this file in a child process instead)
IN_PROCESS = DEVICE == "cuda" or isinstance(triton.language.standard.zeros, InterpretedFunction)
pytestmark = pytest.mark.slow  # the interpreter runs a kernel in about a second


def test_in_a_fresh_interpreter():
    """This file's tests under TRITON_INTERPRET=1 in a child process, when they cannot run here."""
    if IN_PROCESS:
        pytest.skip("the kernels run in this process (the other tests of this file)")
    env = {**os.environ, "TRITON_INTERPRET": "1", "OMP_NUM_THREADS": "1"}
    child = subprocess.run([sys.executable, "-m", "pytest", __file__, "-q", "-p", "no:cacheprovider", "-x"],
                           check=False, env=env, capture_output=True, text=True, timeout=1200)
    assert child.returncode == 0, child.stdout[-4000:] + child.stderr[-2000:]
    passed = re.search(r"(\d+) passed", child.stdout)
    assert passed and int(passed.group(1)) >= 29, child.stdout[-2000:]


@pytest.fixture(scope="module")
def tf():
    """denoiser.inference.triton_filter with its kernels built for this machine (interpreted on the CPU;
    a module imported before the environment variable was set is reloaded)."""
    if not IN_PROCESS:
        pytest.skip("triton was imported uninterpreted: test_in_a_fresh_interpreter runs this in a child process")
    import denoiser.inference.triton_filter as module

    if (DEVICE == "cpu") != isinstance(module._kernel_apply, InterpretedFunction):
        module = importlib.reload(module)
    assert module.unavailable_reason(DEVICE) is None
    with np.errstate(all="ignore"):  # the interpreter computes masked-off lanes too (0/0, exp overflow)
        yield module


def loop_reference(x: torch.Tensor, logits: torch.Tensor, scale: float | None) -> torch.Tensor:
    """Plain loops over pixels and taps in float64: non-finite logits replaced, normalised by
    ``scale / sqrt(var over all k*k taps + 1)``, softmax over the in-image taps only."""
    b, c, h, w = x.shape
    k = math.isqrt(logits.shape[1])
    r = k // 2
    xd = x.double().cpu()
    z = logits.double().cpu().nan_to_num(nan=0.0, posinf=1e4, neginf=-1e4)
    if scale is not None:
        z = z * (scale / torch.sqrt(z.var(dim=1, unbiased=False, keepdim=True) + 1.0))
    out = torch.zeros(b, c, h, w, dtype=torch.float64)
    for y in range(h):
        for xx in range(w):
            taps = [(i, j) for i in range(k) for j in range(k) if 0 <= y + i - r < h and 0 <= xx + j - r < w]
            weights = torch.softmax(torch.stack([z[:, i * k + j, y, xx] for i, j in taps], 1), dim=1)
            for t, (i, j) in enumerate(taps):
                out[:, :, y, xx] += weights[:, t, None] * xd[:, :, y + i - r, xx + j - r]
    return out


def rel_err(a: torch.Tensor, b: torch.Tensor) -> float:
    a, b = a.double().cpu(), b.double().cpu()
    return ((a - b).abs().max() / b.abs().max().clamp_min(1e-30)).item()


CASES = {  # name: (logits, x) makers on a [2, *, 13, 17] frame
    "plain": (lambda g, n: torch.randn(2, n, 13, 17, generator=g) * 3, lambda g: torch.rand(2, 4, 13, 17, generator=g)),
    "large": (lambda g, n: torch.randn(2, n, 13, 17, generator=g) * 1e3,
              lambda g: torch.rand(2, 4, 13, 17, generator=g) * 1e4),
    "nonfinite": (lambda g, n: torch.randn(2, n, 13, 17, generator=g).index_fill_(1, torch.tensor([0]), float("nan"))
                  .index_fill_(1, torch.tensor([n - 1]), float("inf")).index_fill_(1, torch.tensor([1]), -float("inf")),
                  lambda g: torch.rand(2, 4, 13, 17, generator=g)),
    "zero_input": (lambda g, n: torch.randn(2, n, 13, 17, generator=g) * 3, lambda g: torch.zeros(2, 4, 13, 17)),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("scale", [None, 2.5, 30.0])
@pytest.mark.parametrize("k", [3, 5])
def test_kernel_apply_matches_loop_and_module(tf, k, scale, case):
    g = torch.Generator().manual_seed(k * 100 + len(case))
    make_logits, make_x = CASES[case]
    logits, x = make_logits(g, k * k), make_x(g)
    ref = loop_reference(x, logits, scale)
    out = tf.kernel_apply(x.to(DEVICE), logits.to(DEVICE), scale)
    assert out.dtype == torch.float32 and out.shape == x.shape
    assert rel_err(out, ref) <= TOL, rel_err(out, ref)  # 30 * 5 > 80: the max-shift path too
    assert rel_err(out, apply_kernels(x, logits, scale)) <= TOL
    if case == "zero_input":
        assert torch.equal(out.cpu(), torch.zeros_like(x))


def test_kernel_apply_reads_fp16_channels_last_views(tf):
    """The level-0 logits are a channel slice of an fp16 channels-last head: read in place."""
    g = torch.Generator().manual_seed(7)
    head = (torch.randn(1, 3 + 25, 13, 17, generator=g) * 4).half().to(memory_format=torch.channels_last)
    x = torch.rand(1, 4, 13, 17, generator=g)
    logits = head[:, 3:]
    assert not logits.is_contiguous()
    out = tf.kernel_apply(x.to(DEVICE), logits.to(DEVICE), 2.5)
    assert rel_err(out, loop_reference(x, logits.float(), 2.5)) <= TOL


def test_partition_and_upsampling_match_torch(tf):
    g = torch.Generator().manual_seed(3)
    head0 = torch.randn(2, 3 + 9, 13, 17, generator=g) * 5
    head0[0, 1, 2, 3] = float("nan")
    expected = torch.softmax(head0[:, :3].nan_to_num() * (2.5 / torch.sqrt(
        head0[:, :3].nan_to_num().var(dim=1, unbiased=False, keepdim=True) + 1.0)), dim=1)
    assert rel_err(tf.partition_softmax(head0.to(DEVICE), 3, 2.5), expected) <= TOL
    coarse, fine = torch.rand(2, 4, 7, 9, generator=g), torch.rand(2, 4, 13, 17, generator=g)
    fine[:, 3, :2] = 0.0
    coarse[:, 3, :1] = 0.0  # a normaliser of exactly zero in the first rows: the input passes through
    x = torch.rand(2, 3, 13, 17, generator=g) + 5.0
    acc = F.interpolate(coarse, size=(13, 17), mode="bilinear", align_corners=False) + fine
    assert rel_err(tf.add_upsampled(coarse.to(DEVICE), fine.to(DEVICE)), acc) <= TOL
    final = tf.add_upsampled(coarse.to(DEVICE), fine.to(DEVICE), x.to(DEVICE)).cpu()
    assert rel_err(final, normalize(acc, x)) <= TOL
    assert torch.equal(final[:, :, 0], x[:, :, 0])


@pytest.mark.parametrize("sizes,scale", [([5, 5, 5], 2.5), ([3, 5], None)])
def test_pyramid_filter_matches_module(tf, sizes, scale):
    g = torch.Generator().manual_seed(len(sizes))
    h, w = 12, 20  # multiples of 2^(L-1), as the Denoiser pads; 3x5 at the coarsest level
    x = torch.rand(1, 3, h, w, generator=g) * 4
    heads = [torch.randn(1, len(sizes) + sizes[0] ** 2, h, w, generator=g) * 3] + [
        torch.randn(1, k * k, h >> i, w >> i, generator=g) * 3 for i, k in enumerate(sizes) if i > 0]
    out, extras = tf.pyramid_filter_triton(x.to(DEVICE), [hd.to(DEVICE) for hd in heads], sizes, scale)
    ref, ref_extras = pyramid_filter(x, heads, sizes, scale)
    assert rel_err(out, ref) <= TOL
    assert rel_err(extras["partition"], ref_extras["partition"]) <= TOL


def test_denoiser_with_the_triton_filter_matches(tf):
    """Wired in by the CUDA backend (triton_filter=true): a recurrent sequence with a cut."""
    from denoiser.configs import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.inference.cuda_backend import CudaBackend
    from denoiser.recurrent import RecurrentRunner

    torch.manual_seed(0)
    net = build_net(compose_net_config("tiny", "student")).eval()
    frames = [(random_frame(1, 13, 17, seed=s, kind="hard"), s in (0, 2)) for s in range(3)]
    with torch.inference_mode():
        reference = list(RecurrentRunner(net.step).run(frames))
    backend = CudaBackend(precision="fp32", device=DEVICE, channels_last=False, triton_filter=True)
    assert backend.available() is None and backend.uses_triton()
    prepared = backend.prepare_net(net)
    assert isinstance(prepared.filter, tf.TritonPyramidFilter)
    with torch.backends.cudnn.flags(enabled=True, allow_tf32=False):  # fp32 convolutions on a GPU too
        outputs = list(RecurrentRunner(backend.prepare(net, None, 1).step).run(frames))
    for out, ref in zip(outputs, reference):
        assert rel_err(out, ref) <= 1e-5
