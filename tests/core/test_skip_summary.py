"""tests/conftest.py says what did not run: skips grouped by reason at the end of the session,
and, under ``DENOISER_REQUIRE_OVEXT=1`` (set by .ci/run where openvino and a compiler exist), a
skip for want of the OpenVINO extension (or of openvino, in the OpenVINO test modules) is a
failure, while other skips stay skips."""

import os
import shutil
import subprocess
import sys
from pathlib import Path

INNER = '''
import pytest
from helpers.ovext import skip_or_fail


@pytest.mark.parametrize("n", [1, 2, 3])
def test_needs_gpu(n):
    pytest.skip("no GPU here")


def test_needs_extension():
    skip_or_fail("the OpenVINO extension is unavailable: no C++ compiler")


def test_runs():
    assert True
'''

#: a module of tests/conftest.py's OPENVINO_MODULES whose import skips the whole module
OPENVINO_MODULE = '''
import pytest

pytest.importorskip("openvino_that_is_not_installed", reason="openvino is not installed")


def test_parity():
    pass
'''


def run_inner(tmp_path: Path, require: bool) -> subprocess.CompletedProcess:
    """pytest on a small module next to a copy of tests/conftest.py and tests/helpers/ (no pyproject: plain options)."""
    shutil.copy(Path(__file__).resolve().parents[1] / "conftest.py", tmp_path / "conftest.py")
    shutil.copytree(Path(__file__).resolve().parents[1] / "helpers", tmp_path / "helpers",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "test_inner.py").write_text(INNER)
    (tmp_path / "test_openvino.py").write_text(OPENVINO_MODULE)
    env = {k: v for k, v in os.environ.items() if k != "DENOISER_REQUIRE_OVEXT"}
    env["PYTEST_DISABLE_PLUGIN_AUTOLOAD"] = "1"  # a bare session starts faster
    if require:
        env["DENOISER_REQUIRE_OVEXT"] = "1"
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "--continue-on-collection-errors",
                           "test_inner.py", "test_openvino.py"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120, check=False)


def test_skips_are_listed_by_reason(tmp_path):
    proc = run_inner(tmp_path, require=False)
    assert proc.returncode == 0, proc.stdout[-2000:]
    section = proc.stdout.split("skipped, by reason", 1)[1].splitlines()
    assert section[1].split() == ["3", "no", "GPU", "here"]  # the most frequent reason first, counted once
    assert section[2].strip() == "test_inner.py: test_needs_gpu (3 cases)"
    assert section[3].split(None, 1) == ["1", "openvino is not installed"]  # then by reason
    assert section[4].strip() == "test_openvino.py: (module)"
    assert section[5].split(None, 1) == ["1", "the OpenVINO extension is unavailable: no C++ compiler"]
    assert section[6].strip() == "test_inner.py: test_needs_extension"
    assert "1 passed, 5 skipped" in proc.stdout


def test_required_extension_turns_its_skip_into_a_failure(tmp_path):
    proc = run_inner(tmp_path, require=True)
    assert proc.returncode == 1
    assert "1 failed, 1 passed, 3 skipped, 1 error" in proc.stdout
    assert "test_openvino.py: skipped (openvino is not installed), and DENOISER_REQUIRE_OVEXT=1" in proc.stdout
    assert "no C++ compiler (and DENOISER_REQUIRE_OVEXT=1: this test must run here)" in proc.stdout
    assert "   3  no GPU here" in proc.stdout
