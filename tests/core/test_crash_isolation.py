"""``make test`` never loses its summary to a test that kills its process (issue 44): the suite runs
in a pytest-xdist worker (the Makefile's ``PYTEST_ISOLATION``), so a segfault is that test's failure."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

CRASHING = '''
import ctypes


def test_before():
    assert 1 + 1 == 2


def test_null_read():
    ctypes.string_at(0)  # reads address 0: SIGSEGV


def test_after():
    assert "after".upper() == "AFTER"
'''


@pytest.mark.slow
def test_make_test_reports_a_crashing_test_and_prints_the_summary(tmp_path):
    venv = Path(sys.executable).parents[1]
    if shutil.which("make") is None or not (venv / ".installed").is_file():
        pytest.skip("needs make and the venv that make setup installed (its .installed stamp)")
    (tmp_path / "test_crashing.py").write_text(CRASHING)
    proc = subprocess.run(["make", "-s", "-C", str(REPO), "test", f"VENV={venv}",
                           f"PYTEST_ARGS={tmp_path / 'test_crashing.py'} -p no:cacheprovider --rootdir={tmp_path}"],
                          capture_output=True, text=True, timeout=300, check=False)
    out = proc.stdout + proc.stderr
    assert proc.returncode != 0, out
    assert "FAILED" in out and "test_crashing.py::test_null_read" in out and "crashed" in out, out[-3000:]
    assert "1 failed, 2 passed" in out, out[-3000:]  # the summary, with the tests after the crash run
