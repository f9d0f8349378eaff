"""Data: the rendered sequences on disk and what reads them.

* :mod:`~denoiser.data.exr`: EXR reading and writing; :mod:`~denoiser.data.sequence`:
  ``sequence.json``; :mod:`~denoiser.data.layouts`: how logical buffers map to files (native,
  Blender);
* :mod:`~denoiser.data.reader`, :mod:`~denoiser.data.cache`: frame reading with an optional
  decoded-frame cache;
* :mod:`~denoiser.data.dataset`, :mod:`~denoiser.data.augment`, :mod:`~denoiser.data.sampler`,
  :mod:`~denoiser.data.collate`, :mod:`~denoiser.data.datamodule`: training windows and the
  Lightning data module; :mod:`~denoiser.data.evalset`: the labeled sequences evaluation reads
  frame by frame; :mod:`~denoiser.data.synthetic`: sequences with exactly known motion.

Imports the root vocabulary only (it knows no model). Imported by :mod:`denoiser.render`,
:mod:`denoiser.lit`, :mod:`denoiser.report` and the commands.
"""
