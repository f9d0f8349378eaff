"""The buffer vocabulary: every per-frame buffer's name, channel count and native EXR channels.

This is the one place that names them; the reader, the data module, the networks, the
exporter, evaluation, the benchmark, denoising and the tests all import from here. It imports
nothing, so every layer (``nn``, ``data``, ``render``, the commands) may use it.

Shapes: one frame is a dict ``{buffer: [B, C, H, W]}`` float32 tensors; a training window is
``{buffer: [B, T, C, H, W]}``; per-sample radiance ``samples`` is ``[B, S, 3, H, W]`` per
frame (``[B, T, S, 3, H, W]`` per window). Pixel coordinates are (x, y) with y down.

=============  ===  ====================  ====================================================
buffer         C    native EXR channels   meaning
=============  ===  ====================  ====================================================
``color``      3    ``color.R/G/B``       noisy radiance (mean over the frame's samples), linear HDR
``samples``    3    ``sample.<k>.R/G/B``  per-sample radiance, ``k = 0 .. S-1`` (optional)
``albedo``     3    ``albedo.R/G/B``      first-hit albedo, nominally [0, 1] (>1 accepted)
``normal``     3    ``normal.X/Y/Z``      first-hit shading normal, camera space (x right, y up,
                                          z into the scene); no hit = 0
``depth``      1    ``depth.Z``           planar depth along the viewing axis; no hit = +inf or
                                          a very large value (Blender writes 1e10)
``motion``     2    ``motion.X/Y``        backward motion in pixels: the surface at pixel p in
                                          frame t was at p + motion in frame t-1 (y down)
``reference``  3    ``reference.R/G/B``   converged radiance (absent in unlabeled sequences)
=============  ===  ====================  ====================================================

``denoised`` (3, ``denoised.R/G/B``) is what evaluation and ``denoiser-denoise`` write.
"""

from __future__ import annotations

#: Buffers every network reads per frame, in this order (the exported graph's input order).
#: ``motion`` is zero when absent (a static camera and scene).
FRAME_INPUTS = ("color", "albedo", "normal", "depth", "motion")
#: Network inputs: :data:`FRAME_INPUTS` plus the optional per-sample radiance.
NETWORK_INPUTS = (*FRAME_INPUTS, "samples")
#: Every buffer a sequence may hold on disk (``sequence.json`` ``buffers``).
SEQUENCE_BUFFERS = ("color", "samples", "albedo", "normal", "depth", "motion", "reference")
#: Buffers every sequence must have.
REQUIRED_BUFFERS = ("color",)
#: Buffers that hold radiance (scaled together by an exposure change).
RADIANCE_BUFFERS = ("color", "samples", "reference")

#: Channel count C of each buffer (``samples``: channels per sample).
CHANNELS = {"color": 3, "samples": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2, "reference": 3,
            "denoised": 3}

_RGB = ("R", "G", "B")
#: Channel suffixes of each buffer in the native layout: buffer ``normal`` is ``normal.X/Y/Z``.
NATIVE_SUFFIXES: dict[str, tuple[str, ...]] = {
    "color": _RGB, "albedo": _RGB, "reference": _RGB, "denoised": _RGB,
    "normal": ("X", "Y", "Z"), "depth": ("Z",), "motion": ("X", "Y"),
}
#: Buffers whose channels are R, G, B (a colour permutation applies to all of them).
RGB_BUFFERS = tuple(b for b in SEQUENCE_BUFFERS if b == "samples" or NATIVE_SUFFIXES.get(b) == _RGB)


def native_channels(name: str, num_channels: int | None = None) -> tuple[str, ...]:
    """Native EXR channel names of buffer ``name``: ``("normal.X", "normal.Y", "normal.Z")``.

    ``num_channels`` defaults to the buffer's own count; a buffer that is not in the vocabulary
    (or has another count) gets ``.R/.G/.B`` for 3 channels, else ``.0, .1, ...``.
    """
    suffixes = NATIVE_SUFFIXES.get(name)
    num_channels = len(suffixes) if num_channels is None and suffixes else num_channels
    if suffixes is None or len(suffixes) != num_channels:
        suffixes = _RGB if num_channels == 3 else tuple(str(i) for i in range(num_channels or 0))
    return tuple(f"{name}.{s}" for s in suffixes)


def sample_channels(k: int) -> tuple[str, str, str]:
    """Channel names of the ``k``-th per-sample radiance: ``sample.k.R/G/B``."""
    return tuple(f"sample.{k}.{c}" for c in _RGB)  # type: ignore[return-value]
