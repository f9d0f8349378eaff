"""Test-session set-up shared by every test module."""

import sys


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
