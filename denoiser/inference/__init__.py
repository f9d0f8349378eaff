"""Inference: running a trained network outside training, as fast as the machine allows.

* :mod:`~denoiser.inference.backends`: how a network is prepared and stepped (PyTorch eager,
  channels-last, autocast, ``torch.compile``, ONNX Runtime, OpenVINO), each returning a
  :class:`~denoiser.recurrent.Stepper`;
* :mod:`~denoiser.inference.cuda_backend`: the CUDA backends (cast weights, CUDA graphs) and the
  GPU's measurements;
* :mod:`~denoiser.inference.triton_filter`: the pyramid filter as Triton kernels;
* :mod:`~denoiser.inference.step_graph`: one recurrent step as an ONNX graph (export, check,
  ONNX Runtime and OpenVINO steps);
* :mod:`~denoiser.inference.ovext`: the OpenVINO CPU extension (C++, built on first use).

Imports the root vocabulary and :mod:`denoiser.nn` only. Imported by :mod:`denoiser.methods`,
:mod:`denoiser.report` and the commands (never by ``nn``, ``lit`` or ``data``).
"""
