"""Layouts: how logical buffers map to files and EXR channels (``conf/layout/*.yaml``)."""

from denoiser.data.layouts.base import BufferSpec, Layout, SequenceSource, image_size
from denoiser.data.layouts.blender import BlenderLayout, vector_to_motion
from denoiser.data.layouts.native import NativeLayout
from denoiser.data.layouts.oidn import OidnLayout

__all__ = [
           "BlenderLayout",
           "BufferSpec",
           "Layout",
           "NativeLayout",
           "OidnLayout",
           "SequenceSource",
           "image_size",
           "vector_to_motion",
]
