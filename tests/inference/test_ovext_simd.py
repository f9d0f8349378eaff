"""The OpenVINO extension's portable SIMD layer (``denoiser/inference/ovext/simd.hpp``) on each ISA
a compiler here can target: ``ovext_simd_check.cpp`` (the transposes and relayouts, floor, 2^u,
partial loads, the variable shuffle against plain loops) built and run for the compiler's default
target (SSE2 on x86: 4 lanes), for ``-march=native`` (the extension's build: 8 lanes with AVX2,
16 with AVX-512), for AVX-512 where the CPU has it (else only compiled), and for aarch64 NEON
under QEMU where Debian's ``g++-aarch64-linux-gnu`` and ``qemu-user`` are installed."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from denoiser.inference import ovext

CHECK = Path(__file__).with_name("ovext_simd_check.cpp")
HEADERS = ovext.SOURCE.parent


def lanes(targets: str) -> int:
    """The strip width simd.hpp picks for these dispatch targets."""
    names = targets.split()
    return 16 if "avx512f" in names else 8 if "avx" in names else 4


def build(cxx: str, flags: list[str], out: Path) -> Path:
    proc = subprocess.run([cxx, "-O3", "-std=c++17", *flags, f"-I{HEADERS}", str(CHECK), "-o", str(out)],
                          capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out


def run_check(cmd: list[str]) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return proc.stdout.strip()


@pytest.fixture(scope="module")
def cxx():
    found = ovext.compiler()
    if found is None:
        pytest.skip("no C++ compiler ($CXX, g++ or c++)")
    return found


def cpu_flags() -> set[str]:
    line = ovext._cpu_flags()
    return set(line.split(":", 1)[1].split()) if line else set()


@pytest.mark.parametrize("target", ["default", "native"])
def test_simd_layer_matches_plain_loops(tmp_path, cxx, target):
    flags = [] if target == "default" else [ovext.NATIVE]
    if target == "native" and not cpu_flags():
        pytest.skip("no CPU flags in /proc/cpuinfo: the extension is not built with -march=native here")
    width = lanes(ovext.dispatch_targets(cxx, tuple(flags)))
    assert run_check([str(build(cxx, flags, tmp_path / "check"))]) == f"ok S={width}"


def test_simd_layer_on_avx512(tmp_path, cxx):
    """AVX-512 (x86-64-v4): 16 lanes; run where the CPU has it, else compiled only."""
    if "avx512f" not in ovext.dispatch_targets(cxx, ("-march=x86-64-v4",)).split():
        pytest.skip(f"{cxx} does not target AVX-512 with -march=x86-64-v4")
    binary = build(cxx, ["-march=x86-64-v4"], tmp_path / "check512")
    if "avx512f" not in cpu_flags():
        pytest.skip("built for AVX-512; this CPU cannot run it")
    assert run_check([str(binary)]) == "ok S=16"


def test_simd_layer_on_neon_under_qemu(tmp_path):
    """aarch64 NEON: 4 lanes, under QEMU. Skips where the tools are absent; under
    ``$DENOISER_REQUIRE_NEON=1`` (``.ci/run``, where ``make neon-tools`` installed them) that fails."""
    cross, qemu = shutil.which("aarch64-linux-gnu-g++"), shutil.which("qemu-aarch64")
    if cross is None or qemu is None:
        reason = "no aarch64 cross compiler and QEMU (make neon-tools, or apt-get install g++-aarch64-linux-gnu qemu-user)"
        if os.environ.get("DENOISER_REQUIRE_NEON") == "1":
            pytest.fail(f"{reason} (and DENOISER_REQUIRE_NEON=1: this test must run here)", pytrace=False)
        pytest.skip(reason)
    assert "neon" in ovext.dispatch_targets(cross, ()).split()
    binary = build(cross, ["-static"], tmp_path / "check_arm")
    assert run_check([qemu, str(binary)]) == "ok S=4"


@pytest.mark.slow
def test_the_operations_on_an_avx2_build(cxx, monkeypatch):
    """Where the CPU has AVX-512, the extension's own tests (tests/inference/test_ovext.py: every
    operation against its plain reference) run again on an AVX2 build of it (8 lanes:
    ``$DENOISER_OVEXT_MARCH=x86-64-v3``), so one machine checks both ISAs' kernels. On an AVX2-only
    CPU the native build is that build, and the AVX-512 one cannot run."""
    if "avx512f" not in cpu_flags():
        pytest.skip("this CPU has no AVX-512: its native build is the AVX2 one, tested by test_ovext.py")
    targets = ovext.dispatch_targets(cxx, (*ovext.FLAGS, "-march=x86-64-v3")).split()
    if "avx2" not in targets or "avx512f" in targets:
        pytest.skip(f"{cxx} does not target AVX2 alone with -march=x86-64-v3 ({' '.join(targets)})")
    monkeypatch.delenv(ovext.MARCH_ENV, raising=False)
    ovext._status.cache_clear()
    native = ovext.kernel_extension()
    native_for = ovext.built_for()
    ovext._status.cache_clear()
    if native is None:
        pytest.skip(f"the OpenVINO extension is unavailable: {ovext.unavailable_reason()}")
    env = {**os.environ, ovext.MARCH_ENV: "x86-64-v3", "PYTEST_ADDOPTS": ""}
    for name in ("PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT"):
        env.pop(name, None)
    root = Path(__file__).parents[2]
    which = subprocess.run([sys.executable, "-c", ("from denoiser.inference import ovext; "
                                                   "print(ovext.built_for()); print(ovext.kernel_extension(), ovext.unavailable_reason())")],
                           capture_output=True, text=True, timeout=600, env=env, cwd=root, check=False)
    assert which.returncode == 0, which.stderr[-2000:]
    library, reason = which.stdout.split()[-2:]
    assert reason == "None" and Path(library).parent != native.parent, which.stdout + which.stderr
    # what each build was made for, as the bench's report names it
    built_for = which.stdout.strip().splitlines()[-2]
    assert built_for == f"{' '.join(targets)} (-march=x86-64-v3 from ${ovext.MARCH_ENV})", which.stdout
    assert native_for.endswith("(-march=native)") and "avx512f" in native_for.split(), native_for
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-W", "ignore",
                           str(Path(__file__).with_name("test_ovext.py"))],
                          capture_output=True, text=True, timeout=1200, env=env, cwd=root, check=False)
    tail = proc.stdout[-3000:] + proc.stderr[-2000:]
    assert proc.returncode == 0 and " passed" in proc.stdout and " failed" not in proc.stdout, tail


AVX2_CHECK = Path(__file__).parents[2] / "scripts" / "avx2_check.sh"


def test_the_avx2_check_variants_undo_one_choice_each(tmp_path):
    """scripts/avx2_check.sh's stage 4 pairs the shipped kernels against copies with one AVX2
    choice undone: each copy differs from the source in exactly one line, and the script stops in
    one line where that line moved (so the AVX2 CPU's run does not pair two equal builds)."""
    proc = subprocess.run(["bash", str(AVX2_CHECK), "--variants", str(tmp_path / "v")], capture_output=True, text=True,
                          timeout=60, check=False)
    assert proc.returncode == 0, proc.stderr
    for variant, header, line in (("q4", "embed_net.hpp", "constexpr int Q = NOUT % 4 == 0 && S < 16 ? 4 : 1;"),
                                  ("g16", "pyramid_filter_head.hpp", "constexpr int64_t G = NC;")):
        old = (HEADERS / header).read_text().splitlines()
        new = (tmp_path / "v" / variant / header).read_text().splitlines()
        changed = [(a.strip(), b.strip()) for a, b in zip(old, new, strict=True) if a != b]
        assert len(changed) == 1 and changed[0][1] == line, changed
        others = sorted(p.name for p in (tmp_path / "v" / variant).iterdir())
        assert others == sorted(p.name for p in HEADERS.iterdir() if p.suffix in (".hpp", ".cpp")), others
    moved = tmp_path / "moved"
    (moved / "denoiser" / "inference" / "ovext").mkdir(parents=True)
    (moved / "scripts").mkdir()
    shutil.copy(AVX2_CHECK, moved / "scripts")
    for p in HEADERS.iterdir():
        if p.suffix in (".hpp", ".cpp"):
            text = p.read_text().replace("? 8 : NC;", "? 8 : NC ;")  # the head-0 product's line, moved
            (moved / "denoiser" / "inference" / "ovext" / p.name).write_text(text)
    proc = subprocess.run(["bash", str(moved / "scripts" / "avx2_check.sh"), "--variants", str(tmp_path / "w")],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0 and "update variants()" in proc.stderr, proc.stderr


def test_the_avx2_check_refuses_a_cpu_with_avx512(tmp_path):
    if "avx512f" not in cpu_flags():
        pytest.skip("this CPU has no AVX-512: the check would run")
    proc = subprocess.run(["bash", str(AVX2_CHECK), str(tmp_path / "out")], capture_output=True, text=True, timeout=60,
                          check=False)
    assert proc.returncode == 2 and "this CPU has AVX-512" in proc.stderr and not (tmp_path / "out").exists(), proc.stderr
