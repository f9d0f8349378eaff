"""Parameter transfer: initialize a narrow student from a wide teacher of the same architecture.

Rules (ours; the paper only names "parameter transfer from teacher to student"):

1. **Hidden layers by importance.** The importance of an output channel ``o`` of a teacher
   convolution with weight ``W [C_out, C_in, k, k]`` is the L1 norm of its filter,
   ``sum_{i, y, x} |W[o, i, y, x]|``. Every convolution except the U-Net heads keeps the
   ``k_out`` most important output channels, ``k_out`` the student's width of that layer; the
   kept indices are sorted in ascending order so the relative channel order is preserved.
2. **Head outputs by meaning.** Every output channel of the U-Net's 1x1 heads has a meaning,
   read off the modules themselves (:func:`head_meanings`: ``filter.levels``,
   ``filter.kernel_sizes`` / ``filter.kernel_size``, ``temporal.head_layout``), and takes the
   teacher channel with the same meaning:

   * partition logit ``l`` -> partition logit ``l`` (when both pyramids have level ``l``);
   * kernel taps by their offset from the kernel centre, level by level: student tap ``(i, j)``
     of a ``k_s x k_s`` kernel takes teacher tap ``(i + d, j + d)`` of the ``k_t x k_t`` kernel of
     the same level, ``d = (k_t - k_s) / 2`` (the centred window; centre tap -> centre tap). The
     single-kernel ablation's kernel is a level-0 kernel;
   * blend logits ``h_in`` -> ``h_in``, ``h_out`` -> ``h_out``; state feature ``f`` -> ``f``
     (``f < min(F_s, F_t)``);
   * any other filter's channels (``DirectColor``) by position, between filters of one class.

   A head channel without a counterpart keeps the student's initialization, with one exception:
   when the student's kernel is larger than the teacher's (``k_s > k_t``), its taps outside the
   centred ``k_t x k_t`` window get a zero filter and the bias ``outer_tap_logit`` (default
   :data:`OUTER_TAP_LOGIT` = -1e4, what :func:`~denoiser.nn.kernels.kernel_weights` gives an
   infinite logit), so their softmax weight is exactly 0 and the renormalised student kernel *is*
   the teacher's. The price: their gradient is 0 as well, so these taps stay off in training;
   ``outer_tap_logit=None`` keeps their initialization instead (the taps can learn, the kernel
   starts different from the teacher's). Exactness holds for raw logits only: with scale-normalised
   logits (``net.filter.logit_scale``, the default of the net configs) every tap enters the
   normalisation, a -1e4 tap would flatten the others, so the distillation config uses None.
3. **Inputs by data flow.** The input channels of a convolution are the ones that carry the kept
   channels of the layers feeding it: the data flow is followed through every operation of one
   real ``Denoiser.step`` call (two steps, so the recurrent state has a provenance too).
   Channelwise operations (activations, pooling, resampling, elementwise arithmetic) pass the
   selection through; ``torch.cat`` along channels concatenates the selections of its parts with
   the teacher's offsets. Channels of unknown provenance (e.g. a reshape) keep the identity when
   teacher and student widths agree, else their first ``k`` indices. **Except** the U-Net input
   channels the temporal recurrence adds (``temporal.input_layout``: history output, history
   color, guide, state features, valid): they read the teacher's input channel of the same
   meaning, so state feature ``f`` is read where the head wrote feature ``f``. An input channel
   without a counterpart (state features ``f >= F_t``, everything temporal when the teacher has
   no recurrence) gets zero weights: the student does not read it at first, and can learn to.
4. The student's weight is ``W[out_idx][:, in_idx]`` and its bias ``b[out_idx]`` (with the
   exceptions above); a convolution whose spatial kernel size differs is left at its
   initialization, and every other parameter is copied when the shapes agree and left at its
   initialization otherwise.

Consequence (tested): if the teacher's discarded channels are dead (zero filters for hidden
channels, logits at -1e4 for the kernel taps and partitions the student lacks, state features
that are written but never read), the student computes exactly the teacher's function: its
renormalised kernels are the teacher's restricted to the student's window, its state features
are the teacher's first ``F_s``.

The traces of teacher and student are aligned operation by operation (longest matching blocks;
a convolution is identified by its parameter name), so kernel-size variants (k3, k7, the
teacher's 5/7/9 against the student's 5/5/5) transfer too; every student convolution must find
the teacher convolution of the same name, otherwise a ConfigError (another architecture).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
import torch.nn.functional as F
from torch import nn
from torch.overrides import TorchFunctionMode

from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.nn.filters import SingleKernelFilter
from denoiser.nn.pyramid import PyramidFilter
from denoiser.recurrent import RecurrentRunner

#: plan index of a student channel without a counterpart in the teacher: an output channel keeps
#: the student's initialization, an input channel gets zero weights (rules 2, 3)
NO_COUNTERPART = -1
#: plan index of a student kernel tap outside the (smaller) teacher kernel of its level (rule 2)
OUTER_TAP = -2
#: default bias of OUTER_TAP channels: softmax weight exactly 0 next to any logit a network predicts
OUTER_TAP_LOGIT = -1e4

#: meaning of a channel: ``("partition", l)``, ``("tap", level, dy, dx)``, ``(temporal part, c)``, ...
Meaning = tuple


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


def _taps(level: int, k: int) -> list[Meaning]:
    """Meanings of the k*k taps of a level's kernel, row-major (tap ``i*k + j``, i = row/y)."""
    r = k // 2
    return [("tap", level, i - r, j - r) for i in range(k) for j in range(k)]


def head_meanings(net: nn.Module) -> list[list[Meaning]] | None:
    """Meaning of every output channel of ``net``'s U-Net heads, one list per level (finest first).

    Read off ``net.filter`` (pyramid: ``levels`` partition logits, then the level-0 taps; level
    ``i``: ``kernel_sizes[i]**2`` taps; single kernel: ``kernel_size**2`` level-0 taps; another
    filter: ``head_channels`` by position, tagged with its class) and ``net.temporal``
    (``head_layout`` appended to level 0), then the remodulation kernel's taps
    (``remodulate: filtered``). None for a network without ``filter`` and ``unet``.
    """
    filt, unet = getattr(net, "filter", None), getattr(net, "unet", None)
    if filt is None or unet is None or not hasattr(unet, "head_channels"):
        return None
    levels: list[list[Meaning]] = [[] for _ in unet.head_channels]
    if isinstance(filt, PyramidFilter):
        levels[0] += [("partition", level) for level in range(filt.levels)]
        for level, k in enumerate(filt.kernel_sizes):
            levels[level] += _taps(level, k)
    elif isinstance(filt, SingleKernelFilter):
        levels[0] += _taps(0, filt.kernel_size)
    else:
        for level, n in enumerate(filt.head_channels):
            levels[level] += [(type(filt).__name__, level, c) for c in range(n)]
    temporal = getattr(net, "temporal", None)
    if temporal is not None:
        levels[0] += [(part, c) for part, n in temporal.head_layout for c in range(n)]
    remodulation = getattr(net, "remodulation_channels", 0)
    if remodulation:
        levels[0] += [("remodulation",) + tap[1:] for tap in _taps(0, math.isqrt(remodulation))]
    if [len(m) for m in levels] != list(unet.head_channels):
        raise ConfigError(f"model.param_transfer: cannot read the head channels of {type(filt).__name__} "
                          f"({[len(m) for m in levels]} meanings for {list(unet.head_channels)} channels); "
                          "set model.param_transfer=null")
    return levels


def unet_input_meanings(net: nn.Module) -> list[Meaning | None] | None:
    """Meaning of every U-Net input channel: None for the EmbedNet outputs (their provenance is the
    data flow, rule 3), then the temporal inputs in ``temporal.input_layout`` order. None for a
    network without ``embed`` and ``unet``."""
    embed, unet = getattr(net, "embed", None), getattr(net, "unet", None)
    if embed is None or unet is None:
        return None
    temporal = getattr(net, "temporal", None)
    layout = temporal.input_layout if temporal is not None else ()
    return [None] * embed.out_channels + [(part, c) for part, n in layout for c in range(n)]


def _head_convs(net: nn.Module, names: dict[int, str]) -> dict[str, list[Meaning]]:
    """``{weight name of a head conv: meanings of its output channels}``."""
    meanings = head_meanings(net)
    if meanings is None:
        return {}
    return {names[id(head.weight)]: m for head, m in zip(net.unet.heads, meanings)
            if isinstance(head, nn.Conv2d) and id(head.weight) in names}


def _unet_input_conv(net: nn.Module, names: dict[int, str]) -> tuple[str, list[Meaning | None]] | None:
    """``(weight name, meanings of its input channels)`` of the convolution reading the U-Net input."""
    meanings = unet_input_meanings(net)
    if meanings is None:
        return None
    first = next((m for m in net.unet.modules() if isinstance(m, nn.Conv2d)), None)
    if first is None or first.in_channels != len(meanings) or id(first.weight) not in names:
        return None
    return names[id(first.weight)], meanings


def match_meanings(student: list[Meaning | None], teacher: list[Meaning | None]) -> torch.Tensor:
    """Teacher index of every student channel by meaning: ``[len(student)]`` long, with
    :data:`OUTER_TAP` for a tap of a level whose teacher kernel lacks that offset and
    :data:`NO_COUNTERPART` for anything else the teacher lacks (and for None)."""
    where = {m: i for i, m in enumerate(teacher) if m is not None}
    tap_levels = {m[1] for m in where if m[0] == "tap"}

    def index(m: Meaning | None) -> int:
        if m is None:
            return NO_COUNTERPART
        if m in where:
            return where[m]
        return OUTER_TAP if m[0] == "tap" and m[1] in tap_levels else NO_COUNTERPART

    return torch.tensor([index(m) for m in student], dtype=torch.long)


@dataclass
class TransferPlan:
    """Teacher indices per student conv weight name: ``{name: (out_idx [k_out], in_idx [k_in])}``.

    Negative entries: :data:`NO_COUNTERPART` (output: own initialization; input: zero weights),
    :data:`OUTER_TAP` (output only: zero filter, bias ``outer_tap_logit``).
    """

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
    heads_t, heads_s = _head_convs(teacher, names_t), _head_convs(student, names_s)
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
                same = name is not None and name == names_s.get(id(w_s)) and name in params_s
                if same and name in heads_t and name in heads_s:
                    # rule 2; the head outputs feed no convolution directly (slices, filters, the
                    # state), so they start no selection
                    plan.convs[name] = (match_meanings(heads_s[name], heads_t[name]), in_idx)
                    continue
                k_out = int(w_s.shape[0])
                importance = w_t.detach().abs().flatten(1).sum(dim=1)
                out = torch.sort(torch.topk(importance, k_out).indices).values if k_out < w_t.shape[0] \
                    else torch.arange(k_out)
                if same:
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
    # rule 3, the exception: the U-Net input channels of the temporal recurrence by meaning
    first_t, first_s = _unet_input_conv(teacher, names_t), _unet_input_conv(student, names_s)
    if first_t is not None and first_s is not None and first_t[0] == first_s[0] and first_s[0] in plan.convs:
        name, meanings = first_s
        out_idx, in_idx = plan.convs[name]
        if len(in_idx) == len(meanings):
            fixed = torch.tensor([m is not None for m in meanings])
            plan.convs[name] = (out_idx, torch.where(fixed, match_meanings(meanings, first_t[1]), in_idx))
    missing = [n for n, p in params_s.items() if p.dim() == 4 and n not in plan.convs]
    if missing:
        raise ConfigError(f"model.param_transfer: teacher and student are not the same architecture (student "
                          f"layer {missing[0]} has no counterpart in the teacher); set model.param_transfer=null")
    return plan


def _assign(dst: torch.Tensor, src: torch.Tensor, out_idx: torch.Tensor, in_idx: torch.Tensor | None,
            outer: float | None) -> None:
    """``dst[r] = src[out_idx[r]]`` (columns ``in_idx``, zero where ``in_idx < 0``) for the rows with a
    counterpart; ``dst[r] = outer`` for OUTER_TAP rows unless ``outer`` is None; other rows unchanged."""
    rows = out_idx >= 0
    value = src[out_idx[rows]]
    if in_idx is not None:
        value = value[:, in_idx.clamp_min(0)]
        value[:, in_idx < 0] = 0
    dst[rows] = value
    if outer is not None:
        dst[out_idx == OUTER_TAP] = outer


@torch.no_grad()
def transfer_parameters(teacher: nn.Module, student: nn.Module, frame: dict[str, torch.Tensor] | None = None,
                        outer_tap_logit: float | None = OUTER_TAP_LOGIT) -> dict[str, str]:
    """Initialize ``student`` in place from ``teacher`` (rule 4). Returns ``{param name: action}``
    with action ``selected`` (sliced by the plan), ``copied`` (same shape) or ``kept`` (own init).

    outer_tap_logit: bias of the student kernel taps outside a smaller teacher kernel (their
    filters are zeroed); None keeps their initialization (rule 2).
    """
    was_training = (teacher.training, student.training)
    teacher.eval()
    student.eval()
    plan = plan_transfer(teacher, student, frame)
    params_t, params_s = dict(teacher.named_parameters()), dict(student.named_parameters())
    report: dict[str, str] = {}
    for name, p_s in student.named_parameters():
        p_t = params_t.get(name)
        action = "kept"
        if name in plan.convs and p_t is not None and p_t.shape[2:] == p_s.shape[2:]:
            out_idx, in_idx = plan.convs[name]
            if len(out_idx) == p_s.shape[0] and len(in_idx) == p_s.shape[1]:
                outer = None if outer_tap_logit is None else 0.0
                _assign(p_s, p_t, out_idx, in_idx, outer)
                action = "selected"
                bias_name = name[: -len("weight")] + "bias"
                bias_s = params_s.get(bias_name)
                if name.endswith("weight") and bias_name in params_t and bias_s is not None:
                    _assign(bias_s, params_t[bias_name], out_idx, None, outer_tap_logit)
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
    ``kind="probe"``; ``outer_tap_logit``: see there)."""

    def __init__(self, probe_size: int = 32, outer_tap_logit: float | None = OUTER_TAP_LOGIT):
        self.probe_size = int(probe_size)
        self.outer_tap_logit = None if outer_tap_logit is None else float(outer_tap_logit)

    def __call__(self, teacher: nn.Module, student: nn.Module) -> dict[str, str]:
        frame = random_frame(1, self.probe_size, self.probe_size, kind="probe")
        return transfer_parameters(teacher, student, frame, self.outer_tap_logit)
