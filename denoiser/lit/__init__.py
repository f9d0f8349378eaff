"""Training: the Lightning modules and what only training uses.

* :mod:`~denoiser.lit.supervised`: supervised training of one denoiser (teacher or student);
* :mod:`~denoiser.lit.distill`: distillation, a frozen teacher teaching the student;
* :mod:`~denoiser.lit.common`: what the two modules share (network inputs, validation metrics);
* :mod:`~denoiser.lit.losses`: the training losses (SMAPE, gradient, temporal, feature,
  adversarial);
* :mod:`~denoiser.lit.transfer`: teacher -> student parameter transfer;
* :mod:`~denoiser.lit.adapters`, :mod:`~denoiser.lit.schedule`, :mod:`~denoiser.lit.callbacks`,
  :mod:`~denoiser.lit.checkpoint_io`: feature adapters, the learning-rate schedule, callbacks,
  atomic checkpoint writes.

Imports the root vocabulary, :mod:`denoiser.nn` and :mod:`denoiser.data` only (never
``inference``, ``methods`` or ``report``). Imported by the commands (``denoiser-train``) and by
Hydra through the ``_target_`` of ``conf/model``, ``conf/base`` and ``conf/callbacks``.
"""
