"""The scene simulator on Mitsuba 3: scene configs -> multi-frame EXR sequences (docs/simulator.md).

Importing this package does not import Mitsuba; :func:`denoiser.render.variant.activate` does.
"""
