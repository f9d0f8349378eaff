"""Fuzzing of the EXR reader (``tests/data/fuzz_exr.py``, atheris): the regression inputs, and a bounded session.

The session runs in a subprocess, so a crash inside the OpenEXR C++ library is a finding
reported by this test (libFuzzer saves the input), not a dead test run. docs/fuzzing.md
describes longer runs and how a finding becomes a regression input in ``tests/fixtures/exr_fuzz/``.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from fuzz_exr import check, write_seeds

HERE = Path(__file__).parent
REGRESSIONS = sorted((HERE.parent / "fixtures" / "exr_fuzz").glob("*.exr"))
#: seconds of the bounded session
SESSION_SECONDS = 20
#: bytes of address space of the fuzzing process (libFuzzer's -rss_limit_mb=2048 reports less as a finding)
ADDRESS_SPACE = 6 << 30


@pytest.mark.parametrize("path", REGRESSIONS, ids=[p.stem for p in REGRESSIONS])
def test_regression_inputs(path, tmp_path):
    """Inputs the fuzzer once found: each reads or raises ExrError, and prints nothing."""
    check(path.read_bytes(), tmp_path / "input.exr")


def test_seeds_are_real_exr_files(tmp_path):
    """The seeds are valid files the reader reads (the deep one is refused), so the session starts from real EXRs."""
    from denoiser.data import exr
    from denoiser.errors import ExrError

    seeds = write_seeds(tmp_path)
    assert len(seeds) >= 20
    for seed in seeds:
        if "deep" in seed.name:
            with pytest.raises(ExrError, match="deep EXR images are not supported"):
                exr.read_channels(seed)
        else:
            assert exr.read_channels(seed), seed
        check(seed.read_bytes(), tmp_path / "input.exr")


def fuzz_stats(output: str) -> dict[str, int]:
    """libFuzzer's ``-print_final_stats=1`` numbers and the final corpus size."""
    stats = {k: int(v) for k, v in re.findall(r"stat::(\w+):\s+(\d+)", output)}
    corpus = re.findall(r"corp: (\d+)/", output)
    if corpus:
        stats["corpus_size"] = int(corpus[-1])
    return stats


def limit_memory() -> None:
    """Address-space cap of the fuzzing process: a runaway allocation fails there, not on the machine."""
    import resource

    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE, ADDRESS_SPACE))


@pytest.mark.slow
def test_bounded_fuzz_session(tmp_path):
    pytest.importorskip("atheris")
    corpus, findings = tmp_path / "corpus", tmp_path / "findings"
    write_seeds(corpus)
    for path in REGRESSIONS:
        (corpus / path.name).write_bytes(path.read_bytes())
    findings.mkdir()
    env = {**os.environ, "PYTHONPATH": str(HERE.parents[1])}
    proc = subprocess.run([sys.executable, str(HERE / "fuzz_exr.py"), str(corpus), f"-max_total_time={SESSION_SECONDS}",
                           "-timeout=10", "-rss_limit_mb=2048", "-print_final_stats=1",
                           f"-artifact_prefix={findings}/"], cwd=tmp_path, env=env, capture_output=True, text=True,
                          timeout=SESSION_SECONDS + 120, check=False, preexec_fn=limit_memory)
    output = proc.stdout + proc.stderr
    saved = sorted(findings.iterdir())
    summary = [line for line in output.splitlines() if "ERROR: libFuzzer" in line or "Uncaught Python exception" in line
               or line.startswith(("SUMMARY", "AssertionError", "Traceback"))]
    assert proc.returncode == 0 and not saved, (
        f"fuzzing found a problem (exit {proc.returncode}): {' | '.join(summary[:4])}; input(s) saved: "
        f"{', '.join(map(str, saved)) or 'none'}; replay with: python tests/data/fuzz_exr.py --replay <input>\n"
        + output[-4000:])
    stats = fuzz_stats(output)
    print(f"\nfuzz session: {stats}")
    assert stats["number_of_executed_units"] > 1000, stats  # it really ran
