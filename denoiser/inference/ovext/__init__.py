"""The project's OpenVINO CPU extension: the kernel filters as single operations, one C++
header per operation (``kernel_apply.hpp``, ``pyramid_filter.hpp``, ``pyramid_filter_head.hpp``,
``embed_net.hpp``, ``log1p.hpp``, ``color_feature.hpp``, ``guide_features.hpp``, ``factored_head.hpp``,
``clamp_blend.hpp``, ``guide_gate.hpp``, ``warp_history.hpp``, with ``common.hpp``, ``logit_stats.hpp`` and
``simd.hpp``), registered
in ``extension.cpp``, the one file
compiled; their names, inputs and attributes are :data:`denoiser.nn.graph_ops.OPERATIONS`. ``denoiser::KernelApply`` is the per-pixel kernel filter
(:func:`denoiser.nn.kernels.apply_kernels_graph`), ``denoiser::PyramidFilter`` the whole
:class:`~denoiser.nn.pyramid.PyramidFilter` (partition, pooled parts, the levels' kernels,
upsampling, normalisation), ``denoiser::PyramidFilterHead`` the same with the level-0 head
computed row by row inside it from its factors (:class:`denoiser.nn.unet.FactoredHead`: the
graphs with matmul heads), ``denoiser::EmbedNet`` the EmbedNet's three 1x1 layers per pixel
(the same f32 graphs), ``denoiser::Log1p`` the input transforms' ``log1p`` (OpenVINO's ``Log``
is a reference implementation on the CPU), ``denoiser::ColorFeature`` the history's colour parts
of the U-Net input, written channels-last as its first convolution reads them (the f32 graphs),
``denoiser::GuideFeatures`` the auxiliary buffers' features (the f32 graphs),
``denoiser::FactoredHead`` the level-0 head's other channels from the same factors as
``PyramidFilterHead`` (:meth:`denoiser.nn.unet.FactoredHead.tensor`),
``denoiser::ClampBlend`` the history clamp and blend (:func:`denoiser.nn.temporal.clamp_blend`) and
``denoiser::GuideGate`` the disocclusion gate (:meth:`denoiser.nn.temporal.TemporalRecurrence.gate`).

The extension is C++ against the headers and libraries the ``openvino`` wheel ships. It is
compiled on first use, with the machine's C++ compiler (``$CXX``, else ``g++``/``c++``) and
``-march=native``, into a per-user cache keyed by the source, the OpenVINO version, the compiler,
its flags, the vector ISAs it targets with them (:func:`dispatch_targets`: the kernels' vector
code is written once and compiled for the widest, see ``common.hpp``), the machine type and the CPU's flags (``$DENOISER_CACHE/ovext``, where
``$DENOISER_CACHE`` is the root of the project's caches, else ``$XDG_CACHE_HOME/denoiser``, else
``~/.cache/denoiser``); later uses load the cached library. The cache trusts nothing it did not build:

* its folders are created with mode 0700, and the extension is refused (None, with the reason)
  when the cache root, ``ovext/`` or the key's folder is owned by another user, is writable by
  group or others, or (below the root) is a symbolic link;
* the library's SHA-256 is written beside it (``<library>.sha256``, atomically, after a
  successful build) and checked before the library is used (and again by :func:`load_into`): a
  missing or different hash means the file is not loaded and is rebuilt;
* the compiler runs for at most ``$DENOISER_OVEXT_TIMEOUT`` seconds (default
  :data:`BUILD_TIMEOUT_S`; its whole process group is killed then), and a timeout is a failed
  build;
* a failed build is remembered in the key's folder (``build-failed``, holding the reason), so
  later processes say that reason instead of compiling again; delete the file to retry;
* where ``/proc/cpuinfo`` has no ``flags`` line (or cannot be read) ``-march=native`` is left out:
  the CPU cannot be told apart from another, so only a portable library (the compiler's default
  target) is cached and reused;
* ``$DENOISER_OVEXT_MARCH`` (:data:`MARCH_ENV`, e.g. ``x86-64-v3`` or ``haswell``: AVX2 and FMA)
  builds for that target in place of ``-march=native``, under its own key: a library for the
  older CPUs of a cluster, or the AVX2 kernels tested on an AVX-512 machine. A target that
  enables an ISA ``-march=native`` does not (an ISA macro the compiler defines for it and not for
  this CPU) is refused with that reason, not run into an illegal instruction.

The build is atomic: a failed or interrupted build leaves no library behind.

:func:`kernel_extension` returns the library's path, or None when it cannot be built (no
``openvino``, no compiler, a compile error, an untrusted cache); :func:`unavailable_reason` says
why in one line. Graphs exported with ``fused_kernels=True`` (:func:`denoiser.inference.step_graph.export_onnx`)
need it; the OpenVINO backend exports them when it is available and the plain graph otherwise.
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import re
import shutil
import signal
import stat
import subprocess
import sys
from pathlib import Path
from typing import NamedTuple

from denoiser.atomic import atomic_path, atomic_write_text
from denoiser.errors import UserError

#: the file compiled (it includes the operations' headers), shipped with the package
SOURCE = Path(__file__).with_name("extension.cpp")
#: every source file of the extension, in the build's cache key (a changed header is a new build)
SOURCES = tuple(sorted([SOURCE, *Path(__file__).parent.glob("*.hpp")]))
#: compiler flags (part of the cache key); :data:`NATIVE` is added where the CPU's flags are known.
#: ``-fno-math-errno``: ``std::sqrt`` then vectorises (errno is never read; the values are the same)
# a target's ISA macros (__AVX2__, __AVX512F__): upper case, where the CPU names' (__znver4__) are lower
ISA_MACRO = re.compile(r"__[A-Z][A-Z0-9_]*__")
FLAGS = ("-O3", "-fno-math-errno", "-std=c++17", "-fPIC", "-shared", "-fvisibility=hidden")
NATIVE = "-march=native"
#: the CPU description whose ``flags`` line keys (and allows) a ``-march=native`` build
CPUINFO = Path("/proc/cpuinfo")
#: seconds the compiler may run (``$DENOISER_OVEXT_TIMEOUT`` overrides)
BUILD_TIMEOUT_S = 300.0
TIMEOUT_ENV = "DENOISER_OVEXT_TIMEOUT"
#: a ``-march=`` target in place of :data:`NATIVE` (empty or unset: native)
MARCH_ENV = "DENOISER_OVEXT_MARCH"
LIBRARY = "libdenoiser_openvino.so"
#: in a key's folder: the reason its build failed (later processes do not compile again)
FAILED = "build-failed"


#: the compiler's macros naming the vector ISAs it targets (``-dM -E``), as they appear in the
#: cache key and the build's message: the kernels' strip width follows them (``common.hpp``)
TARGET_MACROS = {"__AVX512F__": "avx512f", "__AVX512BW__": "avx512bw", "__AVX512VL__": "avx512vl",
                 "__AVX2__": "avx2", "__AVX__": "avx", "__FMA__": "fma", "__SSE2__": "sse2",
                 "__ARM_NEON": "neon", "__ARM_FEATURE_SVE": "sve", "__ARM_FEATURE_FMA": "fma"}


class _Unavailable(RuntimeError):
    """The extension cannot be used; the message is the reason, one line."""


class _BuildFailed(_Unavailable):
    """The compiler failed or ran out of time (remembered for the cache key)."""


class _Toolchain(NamedTuple):
    """What a build needs: the compiler, the ``openvino`` package's folder and version, and the
    libraries to link (the runtime, its ONNX front end, TBB)."""

    cxx: str
    openvino: Path
    version: str
    libs: list[Path]


def cache_root() -> Path:
    """The root of the project's caches (see the module docstring); the extension is under ``ovext/``."""
    if os.environ.get("DENOISER_CACHE"):
        return Path(os.environ["DENOISER_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "denoiser"


def compiler() -> str | None:
    """The C++ compiler's path: ``$CXX``, else ``g++``, else ``c++``; None when there is none."""
    for name in (os.environ.get("CXX"), "g++", "c++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _cpu_flags() -> str | None:
    """The ``flags`` line of :data:`CPUINFO`; None when there is none or it cannot be read."""
    try:
        with open(CPUINFO) as fh:
            return next((line.strip() for line in fh if line.startswith("flags")), None)
    except OSError:
        return None


def _defined_macros(cxx: str, flags: tuple[str, ...]) -> set[str] | None:
    """The macros ``cxx``'s preprocessor defines with ``flags``' target options (``-m``, ``-f``);
    None where the compiler cannot say (it does not run, fails, or runs past
    ``$DENOISER_OVEXT_TIMEOUT``)."""
    target = [f for f in flags if f.startswith(("-m", "-f"))]
    timeout = _timeout()
    try:  # in its own process group, all of it killed at the timeout (as _compile)
        proc = subprocess.Popen([cxx, *target, "-dM", "-E", "-x", "c++", os.devnull], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    except OSError:
        return None
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        return None
    if proc.returncode != 0:
        return None
    return {line.split()[1] for line in out.splitlines() if line.startswith("#define ") and len(line.split()) > 1}


def dispatch_targets(cxx: str, flags: tuple[str, ...]) -> str:
    """The vector ISAs ``cxx`` compiles for with ``flags`` (the :data:`TARGET_MACROS` its
    preprocessor defines, e.g. ``avx2 avx fma sse2``): what the kernels' vector code becomes, in
    the cache key. ``""`` where the compiler cannot say (it does not run, prints no macros, or runs
    past ``$DENOISER_OVEXT_TIMEOUT``)."""
    return _targets_of(_defined_macros(cxx, flags) or set())


def _targets_of(defined: set[str]) -> str:
    """The :data:`TARGET_MACROS` names among the macros ``defined`` (:func:`dispatch_targets`)."""
    return " ".join(dict.fromkeys(name for macro, name in TARGET_MACROS.items() if macro in defined))


def _openvino_libs(root: Path) -> list[Path]:
    """The OpenVINO runtime, its ONNX front end and TBB, as the wheel ships them (versioned names)."""
    libs = root / "libs"
    found = []
    for stem in ("libopenvino.so", "libopenvino_onnx_frontend.so", "libtbb.so"):
        candidates = sorted(libs.glob(stem + "*"))
        if not candidates:
            raise _Unavailable(f"{libs}: no {stem}* in the openvino package")
        found.append(candidates[0])
    return found


def _toolchain() -> _Toolchain:
    """What a build needs (see :class:`_Toolchain`); raises ``_Unavailable`` naming what is missing."""
    try:
        import openvino as ov
    except ImportError:
        raise _Unavailable("openvino is not installed") from None
    if platform.system() != "Linux":
        raise _Unavailable(f"the extension is built on Linux only, not {platform.system()}")
    cxx = compiler()
    if cxx is None:
        raise _Unavailable("no C++ compiler ($CXX, g++ or c++) to build the OpenVINO extension")
    root = Path(ov.__file__).parent
    return _Toolchain(cxx, root, ov.__version__, _openvino_libs(root))


def missing_requirement() -> str | None:
    """Why the extension cannot even be compiled here (no ``openvino``, not Linux, no compiler),
    in one line; None when it can (``.ci/run`` then requires its tests to run)."""
    try:
        _toolchain()
    except _Unavailable as exc:
        return str(exc)
    return None


def _trusted_folder(folder: Path, root: Path) -> Path:
    """Create ``folder`` (under ``root``) and the folders between them with mode 0700, then check
    every one from ``root`` down: owned by this user, not writable by group or others, and (below
    ``root``, which may be a link such as ``~/.cache``) not a symbolic link. Raises ``_Unavailable``."""
    chain = [root, *reversed([p for p in folder.parents if p != root and root in p.parents]), folder]
    for i, path in enumerate(chain):
        path.mkdir(parents=i == 0, mode=0o700, exist_ok=True)
        st = os.stat(path) if i == 0 else os.lstat(path)
        if not stat.S_ISDIR(st.st_mode):
            raise _Unavailable(f"{path}: not a folder (a link or a file); the OpenVINO extension is not built or "
                               "loaded there")
        if st.st_uid != os.getuid():
            raise _Unavailable(f"{path}: owned by user id {st.st_uid}, not by this user ({os.getuid()}); the OpenVINO "
                               "extension is not built or loaded there")
        if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
            raise _Unavailable(f"{path}: writable by group or others (mode {stat.S_IMODE(st.st_mode):04o}); the "
                               f"OpenVINO extension is not built or loaded there (chmod go-w {path})")
    return folder


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _hash_file(library: Path) -> Path:
    return library.with_name(library.name + ".sha256")


def _mismatch(library: Path) -> str | None:
    """Why ``library`` must not be loaded (no SHA-256 recorded beside it, or a different one);
    None when it is the library this cache built."""
    try:
        recorded = _hash_file(library).read_text().strip()
    except FileNotFoundError:
        return f"{library}: no SHA-256 recorded beside it"
    if _sha256(library) != recorded:
        return f"{library}: its SHA-256 is not the one recorded after its build"
    return None


def _timeout() -> float:
    value = os.environ.get(TIMEOUT_ENV)
    if not value:
        return BUILD_TIMEOUT_S
    try:
        seconds = float(value)
    except ValueError:
        seconds = 0.0
    if not seconds > 0:
        raise _Unavailable(f"${TIMEOUT_ENV}={value!r}: not a positive number of seconds")
    return seconds


def _compile(cmd: list[str], timeout: float) -> None:
    """Run the compiler ``cmd`` for at most ``timeout`` seconds (in its own process group, all of
    which is killed at the timeout: the compiler's children hold its output pipes). Raises
    ``_BuildFailed`` with one line: the first error line, or the timeout."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.communicate()
        raise _BuildFailed(f"building {SOURCE.name} took longer than {timeout:g} s (${TIMEOUT_ENV}) and was "
                           "stopped") from None
    if proc.returncode != 0:
        lines = (err or out).strip().splitlines()
        error = next((line for line in lines if "error" in line), lines[-1] if lines else "")
        error = error.strip()[:200] or f"{cmd[0]} exited with status {proc.returncode} and printed nothing"
        raise _BuildFailed(f"building {SOURCE.name} failed: {error}")


def _target_flags(cxx: str, cpu: str | None) -> tuple[tuple[str, ...], str]:
    """The build's flags and their :func:`dispatch_targets`: :data:`FLAGS` with ``-march=native``
    where the CPU's flags are known, or with ``$DENOISER_OVEXT_MARCH``'s target. That target is
    refused where it enables an instruction set ``-march=native`` does not (an ISA macro such as
    ``__AVX512F__`` or ``__AVX512FP16__`` that the compiler defines for it and not for this CPU)."""
    march = os.environ.get(MARCH_ENV, "").strip()
    if not march:
        flags = (*FLAGS, NATIVE) if cpu else FLAGS
        return flags, dispatch_targets(cxx, flags)
    if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._+-]*", march):
        raise _Unavailable(f"${MARCH_ENV}={march!r}: not a -march= target name (e.g. x86-64-v3, haswell)")
    flags = (*FLAGS, f"-march={march}")
    wanted = _defined_macros(cxx, flags)
    if wanted is None:
        raise _Unavailable(f"${MARCH_ENV}={march!r}: {cxx} does not know that target (-march={march})")
    native = _defined_macros(cxx, (*FLAGS, NATIVE))
    lacking = sorted(m.strip("_").lower() for m in wanted - (native or wanted) if ISA_MACRO.fullmatch(m))
    if lacking:
        raise _Unavailable(f"${MARCH_ENV}={march!r} enables {', '.join(lacking)}, which this CPU lacks "
                           f"(-march=native does not)")
    return flags, _targets_of(wanted)


#: each library this process built or found: what it was built for (:func:`built_for`)
_BUILT_FOR: dict[Path, str] = {}


def _build() -> Path:
    tools = _toolchain()
    cpu = _cpu_flags()
    flags, targets = _target_flags(tools.cxx, cpu)
    key = hashlib.sha256()
    sources = (p.name.encode() + b"\0" + p.read_bytes() for p in SOURCES)
    for part in (*sources, tools.version, tools.cxx, " ".join(flags), targets, platform.machine(), cpu or ""):
        key.update(part if isinstance(part, bytes) else part.encode())
        key.update(b"\0")
    root = cache_root()
    folder = _trusted_folder(root / "ovext" / key.hexdigest()[:16], root)
    target = folder / LIBRARY
    march = next((f for f in flags if f.startswith("-march=")), None)
    chosen_by = march or "no -march"
    if march and march != NATIVE:
        chosen_by += f" from ${MARCH_ENV}"
    _BUILT_FOR[target] = f"{targets or 'the default target'} ({chosen_by})"
    if target.exists():
        problem = _mismatch(target)
        if problem is None:
            return target
        print(f"{problem}; not loading it, building it again", file=sys.stderr, flush=True)
    failed = folder / FAILED
    if failed.exists():
        raise _Unavailable(f"{failed.read_text().strip()} (remembered from an earlier try: delete {failed} to "
                           "build again)")
    timeout = _timeout()
    if march is None:
        how = f", without {NATIVE}: {CPUINFO} names no CPU flags"
    else:
        how = "" if march == NATIVE else f", {march} from ${MARCH_ENV}"
    isa = f" for {targets}" if targets else ""
    print(f"building the OpenVINO extension {SOURCE.name}{isa} (once per machine{how}) ...", file=sys.stderr,
          flush=True)
    try:
        with atomic_path(target, ".so") as tmp:
            _compile([tools.cxx, *flags, f"-I{tools.openvino / 'include'}", str(SOURCE), "-o", str(tmp),
                      *map(str, tools.libs), f"-Wl,-rpath,{tools.openvino / 'libs'}"], timeout)
            digest = _sha256(tmp)
    except _BuildFailed as exc:
        atomic_write_text(failed, f"{exc}\n")
        raise
    atomic_write_text(_hash_file(target), digest + "\n")
    return target


def kernel_extension() -> Path | None:
    """The built extension library (built on the first call), or None (see :func:`unavailable_reason`)."""
    return _status()[0]


def built_for() -> str | None:
    """What the extension's kernels were compiled for, in one line: the vector ISAs
    (:func:`dispatch_targets`) and the ``-march`` that chose them, e.g. ``avx2 avx fma sse2
    (-march=x86-64-v3 from $DENOISER_OVEXT_MARCH)``; None where the extension is unavailable."""
    path = kernel_extension()
    return None if path is None else _BUILT_FOR.get(path)


def unavailable_reason() -> str | None:
    """Why :func:`kernel_extension` is None, in one line; None when it is available."""
    return _status()[1]


def load_into(core, source: str | os.PathLike = "graph") -> None:
    """Add the extension to an ``openvino.Core`` (before it reads a graph that uses it).

    Raises :class:`~denoiser.errors.UserError` naming ``source`` and the operations it uses when
    the extension is unavailable, or when the library no longer has the SHA-256 recorded at its build."""
    path = kernel_extension()
    if path is None:
        raise UserError(f"{source}: uses {_operations(source)}, and the OpenVINO extension is unavailable: "
                        f"{unavailable_reason()}")
    problem = _mismatch(path)
    if problem is not None:
        raise UserError(f"{source}: uses {_operations(source)}; the OpenVINO extension is not loaded: {problem}")
    core.add_extension(str(path))


def _operations(source: str | os.PathLike) -> str:
    """The extension's operations an ONNX file uses (``denoiser::PyramidFilter, ...``), for messages."""
    try:
        import onnx

        nodes = onnx.load(str(source), load_external_data=False).graph.node
    except (ImportError, OSError):  # no onnx, or no such file: name the extension only
        return "the extension's operations"
    names = sorted({f"denoiser::{n.op_type}" for n in nodes if n.domain == "denoiser"})
    return ", ".join(names) or "the extension's operations"


@functools.cache
def _status() -> tuple[Path | None, str | None]:
    try:
        return _build(), None
    except (_Unavailable, OSError) as exc:
        return None, str(exc)
