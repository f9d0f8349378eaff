"""Denoiser networks in plain PyTorch (no Lightning, no Hydra).

Parts, each in its own module:

* :mod:`.inputs`   - input sanitising and the half-precision-safe feature transforms;
* :mod:`.embed`    - :class:`EmbedNet`, per-sample / per-pixel 1x1 feature extractor;
* :mod:`.unet`     - :class:`UNet` with one output head per pyramid level;
* :mod:`.parts`    - :func:`conv_of_parts`, a convolution of a concatenation run part by part (export);
* :mod:`.kernels`  - :func:`apply_kernels`, per-pixel softmax-normalised k x k kernels;
* :mod:`.pyramid`  - :class:`PyramidFilter` (partitioning pyramid);
* :mod:`.filters`  - ablation filters :class:`SingleKernelFilter` and :class:`DirectColor`;
* :mod:`.nppd`     - baseline :class:`LearnedUpsamplingPyramid` (NPPD's predicted upsampling);
* :mod:`.ws`       - baseline :class:`WeightSharingFilter` (WS's weight-sharing kernels);
* :mod:`.warp`     - :func:`warp_to_current` (backward motion, bilinear, zeros outside);
* :mod:`.temporal` - :class:`TemporalRecurrence` (history state, blend weights, resets);
* :mod:`.denoiser` - :class:`Denoiser` with the one ``step`` used everywhere;
* :mod:`.critic`   - :class:`PatchCritic` for adversarial distillation.
* :mod:`.graph_mode` - whether a graph is being recorded, and the switches of its form;
* :mod:`.graph_ops`  - the OpenVINO extension's operation schema (each export stub beside its code).

Imports only the root vocabulary (:mod:`denoiser.nonfinite`, :mod:`denoiser.errors`,
:mod:`denoiser.buffers`, :mod:`denoiser.recurrent`, ...) and itself; every other part may import
it (``inference``, ``methods``, ``report``, ``lit``, the commands), ``data`` and ``render`` do not.

See ``docs/architecture.md`` for how the parts fit together.
"""
