"""Test-session set-up shared by every test module."""

import os
import sys
import tempfile

# built artefacts (the OpenVINO extension, denoiser.ovext) go to a per-session folder, not ~/.cache
os.environ.setdefault("DENOISER_CACHE", tempfile.mkdtemp(prefix="denoiser-test-cache-"))


def _absl_handler_on_the_real_stderr() -> None:
    """``import openvino`` imports ``absl.logging`` (through ``openvino.tools.ovc``), whose handler
    keeps the ``sys.stderr`` of that moment: inside pytest, the capture's file. Its ``close()``
    closes any stream that is not the current ``sys.stderr``/``stdout``, so the next
    ``logging.config.dictConfig`` (Hydra's, e.g. in tests/test_help.py) closed pytest's capture
    file and the session died with "I/O operation on closed file". Point it at the real stderr."""
    try:
        import absl.logging
    except ImportError:
        return
    absl.logging.get_absl_handler().python_handler.stream = sys.__stderr__


_absl_handler_on_the_real_stderr()


def tiny_checkpoint(path, seed: int = 0, **extra):
    """A checkpoint of ``net=tiny kernel=student`` with the weights of ``torch.manual_seed(seed)``,
    written by :func:`denoiser.checkpoint.save_checkpoint` (``extra`` keys go to its top level)."""
    import torch

    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config

    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(seed)
    return save_checkpoint(path, build_net(cfg), cfg, **extra)


def compose_command(name: str, overrides, threads: int | None = None):
    """The entry config ``conf/<name>.yaml`` composed with ``overrides`` (plus ``threads=N`` when given)."""
    from denoiser.configs import compose_config

    return compose_config([*overrides, *([f"threads={threads}"] if threads else [])], name)
