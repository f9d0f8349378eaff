"""The one rule for non-finite values (docs/design.md §3.2): NaN -> 0, -Inf -> 0, +Inf -> ``POSINF`` = 65504.

65504 is the largest finite float16: "very bright" stays very bright and everything downstream
fits half precision; -Inf becomes 0, never negative energy that a filter kernel would spread
over its footprint. Finite values, however large, are kept (HDR is never clamped).

Applied by the EXR reader to every buffer it returns (:func:`replace_array`, in place, counted
so the caller can report it) and by the network to its inputs (:func:`replace_tensor`, so a
frame given to ``Denoiser.step`` or to its ONNX export directly gets the same treatment as one
read from a file).

Defined here, at the top of the package beside :mod:`denoiser.errors`, because both sides use
it and neither may import the other: ``denoiser.data`` must not import from ``denoiser.nn``,
and ``denoiser.nn`` stays plain torch (it imports no data, Lightning or I/O code). This module
imports only numpy; the torch version uses the tensor's own methods, so the EXR reader does not
import torch through it. Traced or exported (``denoiser-export``, ONNX Runtime, OpenVINO), the
replacement is recorded as two comparisons and two selects (:func:`nan_to_num`), which inference
engines fuse with their neighbours, instead of ``nan_to_num``'s IsNaN/IsInf/Where chain.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import torch

#: What +Inf becomes: the largest finite float16.
POSINF = 65504.0
#: What NaN and -Inf become.
NAN = NEGINF = 0.0


def replace_array(array: np.ndarray) -> int:
    """Apply the rule to a float array in place (any shape and float dtype); return how many values changed."""
    count = int(np.count_nonzero(~np.isfinite(array)))
    if count:
        np.nan_to_num(array, copy=False, nan=NAN, posinf=POSINF, neginf=NEGINF)
    return count


def nan_to_num(x: torch.Tensor, nan: float, posinf: float, neginf: float) -> torch.Tensor:
    """``x.nan_to_num(nan, posinf, neginf)`` (any shape; finite values kept, however large).

    Traced or exported, the same values through an explicit NaN test and selects: ``x < inf`` is
    false exactly for NaN and +Inf, ``x > -inf`` exactly for NaN and -Inf. NaN is always told by
    ``IsNaN``, never by a comparison alone: OpenVINO's CPU plugin took ``x > -inf`` as true for NaN
    (NaN became ``posinf``).
    """
    import torch

    if not (torch.jit.is_tracing() or torch.onnx.is_in_onnx_export()):
        return x.nan_to_num(nan=nan, posinf=posinf, neginf=neginf)
    inf = float("inf")
    return torch.where(torch.isnan(x), nan, torch.where(x < inf, torch.where(x > -inf, x, neginf), posinf))


def replace_tensor(x: torch.Tensor) -> torch.Tensor:
    """The rule on a tensor (any shape): a float32 copy with NaN/-Inf -> 0 and +Inf -> 65504."""
    return nan_to_num(x.float(), nan=NAN, posinf=POSINF, neginf=NEGINF)
