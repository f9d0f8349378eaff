"""Parameter transfer: initialize a narrow student from a wide teacher of the same architecture.

Rule (ours; the paper only names "parameter transfer from teacher to student"):

1. **Importance** of an output channel ``o`` of a teacher convolution with weight ``W [C_out, C_in, k, k]``
   is the L1 norm of its filter, ``sum_{i, y, x} |W[o, i, y, x]|``.
2. Each convolution keeps the ``k_out`` most important output channels, where ``k_out`` is the
   student's width of that layer; the kept indices are sorted in ascending order so the
   relative channel order is preserved.
3. Its **input** channels are the ones that carry the kept channels of the layers feeding it:
   the data flow is followed through every operation of one real ``Denoiser.step`` call
   (two steps, so the recurrent state has a provenance too). Channelwise operations
   (activations, pooling, resampling, elementwise arithmetic) pass the selection through;
   ``torch.cat`` along channels concatenates the selections of its parts with the teacher's
   offsets. Channels of unknown provenance (e.g. a reshape) keep the identity when teacher and
   student widths agree, else their first ``k`` indices.
4. The student's weight is ``W[out_idx][:, in_idx]`` and its bias ``b[out_idx]``; a convolution
   whose spatial kernel size differs is left at its initialization, and every other parameter
   is copied when the shapes agree and left at its initialization otherwise.

Consequence (tested): if the teacher's discarded channels are dead (zero filters), the student
computes exactly the teacher's function.

The traces of teacher and student are aligned operation by operation (longest matching blocks;
a convolution is identified by its parameter name), so kernel-size variants (k3, k7, the
teacher's 5/7/9 against the student's 5/5/5) transfer too; every student convolution must find
the teacher convolution of the same name, otherwise a ConfigError (another architecture).
"""

from __future__ import annotations

import difflib
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.overrides import TorchFunctionMode

from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.runner import RecurrentRunner


@dataclass
class _Call:
    """One recorded torch operation: its function, arguments and tensor result."""

    func: Callable
    args: tuple
    kwargs: dict
    result: torch.Tensor


class _Recorder(TorchFunctionMode):
    """Records every top-level torch operation that returns a tensor (inner calls are not seen)."""

    def __init__(self):
        super().__init__()
        self.calls: list[_Call] = []

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        result = func(*args, **kwargs)
        if isinstance(result, torch.Tensor):
            self.calls.append(_Call(func, args, kwargs, result))
        return result


@torch.no_grad()
def trace_steps(net: nn.Module, frame: dict[str, torch.Tensor], steps: int = 2) -> list[list[_Call]]:
    """Record the operations of ``steps`` recurrent ``net.step`` calls on ``frame`` (one list per step)."""
    traces, runner = [], RecurrentRunner(net.step)
    for _ in range(steps):
        with _Recorder() as rec:
            runner(frame)
        traces.append(rec.calls)
    return traces


def _is_conv(func: Callable) -> bool:
    return func in (torch.conv2d, F.conv2d)


def _is_cat(func: Callable) -> bool:
    return func in (torch.cat, torch.concat, torch.concatenate)


def _channel_count(t: Any) -> int | None:
    return int(t.shape[1]) if isinstance(t, torch.Tensor) and t.dim() == 4 else None


def _first_tensor(args: tuple) -> torch.Tensor | None:
    for a in args:
        if isinstance(a, torch.Tensor):
            return a
    return None


@dataclass
class TransferPlan:
    """Selected teacher indices per student parameter name: ``{name: (out_idx [k_out], in_idx [k_in])}``."""

    convs: dict[str, tuple[torch.Tensor, torch.Tensor]] = field(default_factory=dict)


def _op_key(call: _Call, names: dict[int, str]) -> str:
    """Alignment key of a recorded operation: the parameter name for a convolution, else the function name."""
    if _is_conv(call.func) and len(call.args) > 1:
        return "conv:" + names.get(id(call.args[1]), "?")
    return getattr(call.func, "__name__", repr(call.func))


def aligned_calls(calls_t: list[_Call], calls_s: list[_Call], names_t: dict[int, str],
                  names_s: dict[int, str]) -> list[tuple[_Call, _Call]]:
    """Pairs of corresponding teacher/student operations (longest matching blocks of the two traces).

    Identical architectures give identical traces; kernel-size variants differ only in the number
    of filter taps applied after the U-Net, which stay unpaired.
    """
    keys_t = [_op_key(c, names_t) for c in calls_t]
    keys_s = [_op_key(c, names_s) for c in calls_s]
    matcher = difflib.SequenceMatcher(None, keys_t, keys_s, autojunk=False)
    return [(calls_t[b.a + i], calls_s[b.b + i]) for b in matcher.get_matching_blocks() for i in range(b.size)]


def plan_transfer(teacher: nn.Module, student: nn.Module, frame: dict[str, torch.Tensor] | None = None) -> TransferPlan:
    """Follow the data flow of teacher and student side by side and choose channels (rules 1-3).

    Raises ConfigError when a student convolution has no counterpart of the same name in the
    teacher's data flow (the two are not the same architecture).
    """
    frame = frame if frame is not None else random_frame(1, 32, 32, kind="probe")
    names_t = {id(p): n for n, p in teacher.named_parameters()}
    names_s = {id(p): n for n, p in student.named_parameters()}
    params_s = dict(student.named_parameters())
    traces_t, traces_s = trace_steps(teacher, frame), trace_steps(student, frame)
    plan = TransferPlan()
    # selections by tensor id, across steps (the recorded calls keep every tensor alive, so ids stay unique)
    selection: dict[int, torch.Tensor] = {}

    def sel_of(t_tensor, s_tensor) -> torch.Tensor:
        n_s = _channel_count(s_tensor)
        known = selection.get(id(t_tensor))
        if known is not None and len(known) == n_s:
            return known
        return torch.arange(n_s if n_s is not None else 0)  # identity / first-k fallback (rule 3)

    for calls_t, calls_s in zip(traces_t, traces_s):
        for ct, cs in aligned_calls(calls_t, calls_s, names_t, names_s):
            out = None
            if _is_conv(ct.func):
                x_t, w_t = ct.args[0], ct.args[1]
                x_s, w_s = cs.args[0], cs.args[1]
                name = names_t.get(id(w_t))
                in_idx = sel_of(x_t, x_s)
                k_out = int(w_s.shape[0])
                importance = w_t.detach().abs().flatten(1).sum(dim=1)
                out = torch.sort(torch.topk(importance, k_out).indices).values if k_out < w_t.shape[0] \
                    else torch.arange(k_out)
                if name is not None and name == names_s.get(id(w_s)) and name in params_s:
                    plan.convs[name] = (out, in_idx)
            elif _is_cat(ct.func):
                dim = ct.kwargs.get("dim", ct.args[1] if len(ct.args) > 1 else 0)
                parts_t, parts_s = ct.args[0], cs.args[0]
                if ct.result.dim() == 4 and dim in (1, -3) and len(parts_t) == len(parts_s):
                    offset, pieces = 0, []
                    for pt, ps in zip(parts_t, parts_s):
                        pieces.append(sel_of(pt, ps) + offset)
                        offset += int(pt.shape[1])
                    out = torch.cat(pieces)
            else:
                x_t, x_s = _first_tensor(ct.args), _first_tensor(cs.args)
                n_res = _channel_count(ct.result)
                if (x_t is not None and n_res is not None and _channel_count(x_t) == n_res
                        and id(x_t) in selection and _channel_count(cs.result) == _channel_count(x_s)):
                    out = selection[id(x_t)]
            if out is not None and _channel_count(cs.result) == len(out):
                selection[id(ct.result)] = out
    missing = [n for n, p in params_s.items() if p.dim() == 4 and n not in plan.convs]
    if missing:
        raise ConfigError(f"model.param_transfer: teacher and student are not the same architecture (student "
                          f"layer {missing[0]} has no counterpart in the teacher); set model.param_transfer=null")
    return plan


@torch.no_grad()
def transfer_parameters(teacher: nn.Module, student: nn.Module,
                        frame: dict[str, torch.Tensor] | None = None) -> dict[str, str]:
    """Initialize ``student`` in place from ``teacher`` (rule 4). Returns ``{param name: action}``
    with action ``selected`` (sliced by the plan), ``copied`` (same shape) or ``kept`` (own init)."""
    was_training = (teacher.training, student.training)
    teacher.eval()
    student.eval()
    plan = plan_transfer(teacher, student, frame)
    params_t = dict(teacher.named_parameters())
    report: dict[str, str] = {}
    for name, p_s in student.named_parameters():
        p_t = params_t.get(name)
        action = "kept"
        if name in plan.convs and p_t is not None and p_t.shape[2:] == p_s.shape[2:]:
            out_idx, in_idx = plan.convs[name]
            w = p_t[out_idx][:, in_idx] if len(in_idx) == p_s.shape[1] else None
            if w is not None and w.shape == p_s.shape:
                p_s.copy_(w)
                action = "selected"
                bias_name = name[: -len("weight")] + "bias"
                if name.endswith("weight") and bias_name in params_t:
                    dict(student.named_parameters())[bias_name].copy_(params_t[bias_name][out_idx])
                    report[bias_name] = "selected"
        elif p_t is not None and p_t.shape == p_s.shape and name not in report:
            p_s.copy_(p_t)
            action = "copied"
        report.setdefault(name, action)
    teacher.train(was_training[0])
    student.train(was_training[1])
    return report


class L1ChannelTransfer:
    """Config-friendly callable ``(teacher, student) -> report`` applying :func:`transfer_parameters`
    on a random ``probe_size`` x ``probe_size`` frame (:func:`~denoiser.frames.random_frame`,
    ``kind="probe"``)."""

    def __init__(self, probe_size: int = 32):
        self.probe_size = int(probe_size)

    def __call__(self, teacher: nn.Module, student: nn.Module) -> dict[str, str]:
        frame = random_frame(1, self.probe_size, self.probe_size, kind="probe")
        return transfer_parameters(teacher, student, frame)
