"""The OpenVINO extension in the tests: skipped where it is unavailable, except where it must run."""

import os
from pathlib import Path

import pytest

#: set by .ci/run where ``openvino`` imports and a C++ compiler exists: there the OpenVINO
#: extension's tests must run, and a skip for want of the extension (or of openvino) is a failure
REQUIRE_OVEXT = "DENOISER_REQUIRE_OVEXT"


def skip_or_fail(reason: str):
    """Skip the test for ``reason``, or fail it when ``$DENOISER_REQUIRE_OVEXT`` is 1."""
    if os.environ.get(REQUIRE_OVEXT) == "1":
        pytest.fail(f"{reason} (and {REQUIRE_OVEXT}=1: this test must run here)", pytrace=False)
    pytest.skip(reason)


def extension_or_skip() -> Path:
    """The OpenVINO extension's library (:func:`denoiser.inference.ovext.kernel_extension`, built on first
    use); skips the test naming why it is unavailable (fails it under ``$DENOISER_REQUIRE_OVEXT``)."""
    from denoiser.inference import ovext

    path = ovext.kernel_extension()
    if path is None:
        skip_or_fail(f"the OpenVINO extension is unavailable: {ovext.unavailable_reason()}")
    return path
