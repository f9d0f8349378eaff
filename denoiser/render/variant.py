"""Choose and activate the Mitsuba 3 variant once per process.

``llvm_ad_rgb`` (vectorized, JIT-compiled with LLVM) is used when libLLVM can be loaded and a
tiny test render succeeds; otherwise ``scalar_rgb`` (one ray at a time, several times slower)
with a one-line notice on stderr. Mitsuba's kernels need LLVM >= 16: the older LLVM 14/15
shipped by Debian fail to compile them, so ``DRJIT_LIBLLVM_PATH`` is pointed at libLLVM-19
(``scripts/setup_llvm.sh`` installs it) before mitsuba is imported, unless the user set it.
"""

from __future__ import annotations

import glob
import os
import sys

from denoiser.errors import ConfigError

LLVM = "llvm_ad_rgb"
SCALAR = "scalar_rgb"
#: Where Debian/Ubuntu put libLLVM; newest first.
LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)

_active: str | None = None


def find_libllvm() -> str | None:
    """Path of a libLLVM >= 19 (``DRJIT_LIBLLVM_PATH`` wins), or None."""
    env = os.environ.get("DRJIT_LIBLLVM_PATH")
    if env:
        return env if os.path.exists(env) else None
    for cand in LLVM_CANDIDATES + tuple(sorted(glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*"), reverse=True)):
        if os.path.exists(cand) and ("-19" in cand or ".19" in cand or "-2" in cand):
            return cand
    return None


def _smoke_test(mi) -> None:
    """Render a 4x4 image of a diffuse sphere; raises when the variant cannot run."""
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 40,
                   "film": {"type": "hdrfilm", "width": 4, "height": 4, "rfilter": {"type": "box"}}},
        "shape": {"type": "sphere", "center": [0, 0, 4]},
        "light": {"type": "constant"},
    })
    img = mi.render(scene, spp=1)
    import numpy as np

    if not np.isfinite(np.asarray(img)).all():
        raise RuntimeError("non-finite test render")


def activate(requested: str = "auto", quiet: bool = False):
    """Set the Mitsuba variant (``auto``, ``llvm_ad_rgb`` or ``scalar_rgb``) and return ``mitsuba``.

    ``auto`` tries LLVM and falls back to scalar with a one-line notice. A variant can be set
    only once per process; later calls return the active one (a different explicit request is
    a :class:`ConfigError`).
    """
    global _active
    if requested not in ("auto", LLVM, SCALAR):
        raise ConfigError(f"render variant: unknown {requested!r}; use auto, {LLVM} or {SCALAR}")
    lib = find_libllvm()
    if lib and "DRJIT_LIBLLVM_PATH" not in os.environ:
        os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import mitsuba as mi

    if _active is not None:
        if requested not in ("auto", _active):
            raise ConfigError(f"render variant: {_active} already active in this process, cannot switch to "
                              f"{requested}")
        return mi
    order = [LLVM, SCALAR] if requested == "auto" else [requested]
    last_error = None
    for variant in order:
        try:
            mi.set_variant(variant)
            _smoke_test(mi)
        except Exception as exc:  # noqa: BLE001 - any failure means: variant unusable here
            last_error = exc
            if not quiet and variant == LLVM and len(order) > 1:
                reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                print(f"notice: Mitsuba variant {LLVM} unavailable ({reason[:120]}); falling back to {SCALAR}",
                      file=sys.stderr)
            continue
        _active = variant
        if not quiet:
            print(f"mitsuba {mi.__version__}: variant {variant}", file=sys.stderr)
        return mi
    raise ConfigError(f"render variant: {requested} cannot run here ({last_error})")


def active_variant() -> str | None:
    """The variant set by :func:`activate`, or None before the first call."""
    return _active
