"""The project's OpenVINO CPU extension (``kernel_apply.cpp``): the kernel filters as single
operations. ``denoiser::KernelApply`` is the per-pixel kernel filter
(:func:`denoiser.nn.kernels.apply_kernels_graph`), ``denoiser::PyramidFilter`` the whole
:class:`~denoiser.nn.pyramid.PyramidFilter` (partition, pooled parts, the levels' kernels,
upsampling, normalisation), ``denoiser::Log1p`` the input transforms' ``log1p`` (OpenVINO's ``Log``
is a reference implementation on the CPU), ``denoiser::AddUpsampled`` the level-0 head's sum
with its upsampled half-resolution part (:meth:`denoiser.nn.unet.UNet.head0_before_upsampling`).

The extension is C++ against the headers and libraries the ``openvino`` wheel ships. It is
compiled on first use, with the machine's C++ compiler (``$CXX``, else ``g++``/``c++``) and
``-march=native``, into a per-user cache keyed by the source, the OpenVINO version, the compiler
and the CPU's flags (``$DENOISER_CACHE``, the root of the project's caches as for the frame cache, else ``$XDG_CACHE_HOME/denoiser``, else
``~/.cache/denoiser``); later uses load the cached library. The build is atomic: a failed or
interrupted build leaves no library behind.

:func:`kernel_extension` returns the library's path, or None when it cannot be built (no
``openvino``, no compiler, a compile error); :func:`unavailable_reason` says why in one line.
Graphs exported with ``fused_kernels=True`` (:func:`denoiser.step_graph.export_onnx`) need it;
the OpenVINO backend exports them when it is available and the plain graph otherwise.
"""

from __future__ import annotations

import functools
import hashlib
import os
import platform
import shutil
import subprocess
import sys
from pathlib import Path

from denoiser.atomic import atomic_path
from denoiser.errors import UserError

#: the extension's source, shipped with the package
SOURCE = Path(__file__).with_name("kernel_apply.cpp")
#: compiler flags (part of the cache key)
FLAGS = ("-O3", "-march=native", "-std=c++17", "-fPIC", "-shared", "-fvisibility=hidden")


def cache_root() -> Path:
    """Where built libraries are kept (see the module docstring)."""
    if os.environ.get("DENOISER_CACHE"):
        return Path(os.environ["DENOISER_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "denoiser"


def _compiler() -> str | None:
    for name in (os.environ.get("CXX"), "g++", "c++"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


def _cpu_flags() -> str:
    try:
        with open("/proc/cpuinfo") as fh:
            return next((line for line in fh if line.startswith("flags")), "")
    except OSError:
        return platform.processor()


def _openvino_libs(root: Path) -> list[Path]:
    """The OpenVINO runtime, its ONNX front end and TBB, as the wheel ships them (versioned names)."""
    libs = root / "libs"
    found = []
    for stem in ("libopenvino.so", "libopenvino_onnx_frontend.so", "libtbb.so"):
        candidates = sorted(libs.glob(stem + "*"))
        if not candidates:
            raise FileNotFoundError(f"{libs}: no {stem}* in the openvino package")
        found.append(candidates[0])
    return found


def _build() -> tuple[Path | None, str | None]:
    try:
        import openvino as ov
    except ImportError:
        return None, "openvino is not installed"
    if platform.system() != "Linux":
        return None, f"the extension is built on Linux only, not {platform.system()}"
    cxx = _compiler()
    if cxx is None:
        return None, "no C++ compiler ($CXX, g++ or c++) to build the OpenVINO extension"
    root = Path(ov.__file__).parent
    try:
        libs = _openvino_libs(root)
    except FileNotFoundError as exc:
        return None, str(exc)
    key = hashlib.sha256()
    for part in (SOURCE.read_bytes(), ov.__version__.encode(), cxx.encode(), " ".join(FLAGS).encode(),
                 _cpu_flags().encode()):
        key.update(part)
    target = cache_root() / "ovext" / key.hexdigest()[:16] / "libdenoiser_openvino.so"
    if target.exists():
        return target, None
    print(f"building the OpenVINO extension {SOURCE.name} (once per machine) ...", file=sys.stderr, flush=True)
    with atomic_path(target, ".so") as tmp:
        cmd = [cxx, *FLAGS, f"-I{root / 'include'}", str(SOURCE), "-o", str(tmp), *map(str, libs),
               f"-Wl,-rpath,{root / 'libs'}"]
        done = subprocess.run(cmd, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            lines = (done.stderr or done.stdout).strip().splitlines()
            error = next((line for line in lines if "error" in line), lines[-1] if lines else "")
            raise _BuildFailed(f"building {SOURCE.name} failed: {error.strip()[:200]}")
    return target, None


class _BuildFailed(RuntimeError):
    pass


def kernel_extension() -> Path | None:
    """The built extension library (built on the first call), or None (see :func:`unavailable_reason`)."""
    return _status()[0]


def unavailable_reason() -> str | None:
    """Why :func:`kernel_extension` is None, in one line; None when it is available."""
    return _status()[1]


def load_into(core, source: str | os.PathLike = "graph") -> None:
    """Add the extension to an ``openvino.Core`` (before it reads a graph that uses it).

    Raises :class:`~denoiser.errors.UserError` naming ``source`` and the operations it uses when
    the extension is unavailable."""
    path = kernel_extension()
    if path is None:
        raise UserError(f"{source}: uses {_operations(source)}, and the OpenVINO extension is unavailable: "
                        f"{unavailable_reason()}")
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
        return _build()
    except (_BuildFailed, OSError) as exc:
        return None, str(exc)
