"""The calling thread's alternate signal stack, kept as it was across OpenVINO calls (issue 44).

OpenVINO's CPU plugin gives the thread that creates a plugin or a compiled model a signal stack of
its own (``ov::intel_cpu::SigAltStackSetup``: ``mmap`` + ``sigaltstack``, saving the previous one)
and, when that object is destroyed, sets the saved one back and unmaps its own. Destroyed in an
order other than the reverse of creation (two compiled models, f32 then bf16, freed first-first),
the thread is left with a signal stack that points at unmapped memory. Python installs its signal
handlers with ``SA_ONSTACK``, so the next signal that Python handles on that thread (``SIGCHLD``
when a DataLoader worker exits: torch installs that handler; ``SIGINT`` on Ctrl-C) cannot be
delivered: the kernel kills the process with ``SIGSEGV`` (``si_code`` ``SI_KERNEL``, no fault
address, no Python traceback). :func:`kept` wraps every OpenVINO call that can create or destroy
such objects, so the thread leaves it with the signal stack it entered with.

Linux only; elsewhere (or when libc has no ``sigaltstack``) :func:`kept` does nothing.
"""

from __future__ import annotations

import ctypes
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import NamedTuple

#: ``ss_flags`` of a disabled signal stack (Linux)
SS_DISABLE = 2


class _StackT(ctypes.Structure):
    _fields_ = [("ss_sp", ctypes.c_void_p), ("ss_flags", ctypes.c_int), ("ss_size", ctypes.c_size_t)]


class SignalStack(NamedTuple):
    """One thread's alternate signal stack: ``address`` (0 when none), ``flags``, ``size`` in bytes."""

    address: int
    flags: int
    size: int

    @property
    def enabled(self) -> bool:
        return not self.flags & SS_DISABLE


def _libc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.sigaltstack.argtypes = [ctypes.POINTER(_StackT), ctypes.POINTER(_StackT)]
        return libc
    except (OSError, AttributeError):
        return None


_LIBC = _libc()


def current() -> SignalStack | None:
    """The calling thread's alternate signal stack (None where it cannot be read)."""
    if _LIBC is None:
        return None
    out = _StackT()
    if _LIBC.sigaltstack(None, ctypes.byref(out)) != 0:
        return None
    return SignalStack(out.ss_sp or 0, out.ss_flags, out.ss_size)


def install(stack: SignalStack) -> None:
    """Make ``stack`` the calling thread's alternate signal stack (OSError if the kernel refuses)."""
    if _LIBC is None:
        return
    new = _StackT(stack.address or None, stack.flags & SS_DISABLE, stack.size)
    if _LIBC.sigaltstack(ctypes.byref(new), None) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"sigaltstack: cannot set {stack}")


@contextmanager
def kept() -> Iterator[None]:
    """Run the block, then give the calling thread back the signal stack it had before, if the block
    changed it (see the module docstring). Nested blocks are fine; no-op where unsupported."""
    before = current()
    try:
        yield
    finally:
        if before is not None and current() != before:
            install(before)
