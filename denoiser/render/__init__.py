"""The scene simulator on Mitsuba 3: scene configs -> multi-frame EXR sequences (docs/simulator.md).

Importing this package does not import Mitsuba; :func:`denoiser.render.variant.activate` does.

Imports the root vocabulary and :mod:`denoiser.data` (the EXR writer, ``sequence.json``) only.
Imported by ``denoiser-render`` and the render benchmark (:mod:`denoiser.commands`) only.
"""
