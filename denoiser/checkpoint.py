"""Load a trained :class:`~denoiser.nn.denoiser.Denoiser` from a Lightning checkpoint.

Checkpoint contract (``docs/contracts.md``): a Lightning ``.ckpt`` (a dict written by ``torch.save``)
whose ``hyper_parameters["net"]`` is the resolved net config (a plain dict with ``_target_``)
and whose ``state_dict`` holds the denoiser's weights under the prefix ``net.`` (the
Lightning module keeps the network it trains as attribute ``net``; a distillation module's
frozen teacher sits under ``teacher.`` and is not loaded).

Every way a file can be wrong is a one-line :class:`~denoiser.errors.UserError` naming it:
missing file, not a checkpoint, no net config, a net config that cannot be built, and a
checkpoint of another architecture (state-dict keys or shapes that do not match the net its
own config builds).

Loading is safe by default: ``torch.load(weights_only=True)`` only, whose unpickler builds
tensors, containers and plain values but calls nothing it has not been told is safe. Every
checkpoint the project writes (:func:`save_checkpoint`, the Lightning checkpoints of
``train.py`` for every model, distillation included) loads that way. A file that needs more (a
pickled object whose reconstruction could run code: ``os.system``, any class) is refused with
one line naming the file and the first refused globals (listed by torch's own
``torch.serialization.get_unsafe_globals_in_checkpoint``), unless the caller passes
``trust=True`` (config ``trust_checkpoint=true``): then it is loaded with
``weights_only=False`` and a warning, as one would load any pickle from a trusted source.
``train.py ckpt_path=`` goes through :func:`resume_weights_only` before Lightning reads the file.

Every loader also takes a training run directory (``hydra.run.dir`` of ``denoiser-train``) for a
file: its ``checkpoints/best.ckpt`` (best validation PSNR), else its ``checkpoints/last.ckpt``
(:func:`resolve_checkpoint`), so ``ckpt=reports/demo/runs/teacher`` works in every command.
"""

from __future__ import annotations

import logging
import os
import pickle
import re
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from denoiser.atomic import atomic_path
from denoiser.configs import build_net, plain
from denoiser.errors import ConfigError, UserError, first_line

NET_PREFIX = "net."
#: config key that lets a command load a checkpoint the safe loader refuses (the default for ``trust_key``)
TRUST_KEY = "trust_checkpoint"
#: refused globals named in the one-line message (the rest are counted)
SHOWN_GLOBALS = 3

log = logging.getLogger(__name__)


def read_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu", *, trust: bool = False,
                    trust_key: str = TRUST_KEY) -> dict:
    """The raw checkpoint dict of ``path``, read with ``torch.load(weights_only=True)``.

    UserError naming ``path`` if it is missing or not a torch checkpoint, and if the safe loader
    refuses it (it holds pickled objects that could run code) unless ``trust``: then it is
    loaded with ``weights_only=False`` after a warning. ``trust_key``: the config key named in
    the refusal and the warning (``trust_checkpoint``, ``model.trust_teacher_ckpt``).
    """
    path = _check_file(path)
    ckpt = _load_safe(path, map_location, trust, trust_key)
    if ckpt is None:  # refused by the safe loader, and trusted
        try:
            ckpt = torch.load(path, map_location=map_location, weights_only=False)
        except Exception as exc:  # noqa: BLE001 - any failure means "not a checkpoint"
            raise UserError(f"{path}: not a checkpoint ({first_line(exc)})") from None
    if not isinstance(ckpt, Mapping):
        raise UserError(f"{path}: not a Lightning checkpoint (top level is a {type(ckpt).__name__}, not a dict)")
    return dict(ckpt)


def resume_weights_only(path: str | os.PathLike | None, trust: bool = False, trust_key: str = TRUST_KEY) -> bool:
    """Check a checkpoint that another loader (Lightning's resume, ``trainer.fit(ckpt_path=...)``) will read.

    Reads ``path`` with the safe loader first, so a refused file is the one-line UserError of
    :func:`read_checkpoint` before anything unpickles it. Returns the ``weights_only`` flag to
    give that loader: True, or False only when ``trust`` and the file needs it (warning logged).
    ``path`` None (a fresh start): True.
    """
    if path is None:
        return True
    return _load_safe(_check_file(path), "cpu", trust, trust_key) is not None


#: the files of a run directory a loader takes, in order of preference
RUN_CHECKPOINTS = ("checkpoints/best.ckpt", "checkpoints/last.ckpt")

#: ``_target_`` prefixes that checkpoints of earlier layouts store, and where those classes live now:
#: the training loss and transfer were root modules before ``lit/`` (``tests/fixtures/student_v0.ckpt``,
#: written at d77d64e, stores ``denoiser.losses.DenoiseLoss``). Only stored configs are mapped;
#: ``conf/`` and new code name the current paths.
OLD_TARGETS = {"denoiser.losses.": "denoiser.lit.losses.", "denoiser.transfer.": "denoiser.lit.transfer."}


def current_targets(cfg: Any) -> Any:
    """A stored config (mappings, lists, values) with each ``_target_`` that starts with a key of
    :data:`OLD_TARGETS` at its current path; everything else as given (a new object where changed)."""
    if isinstance(cfg, Mapping):
        out = {key: current_targets(value) for key, value in cfg.items()}
        target = out.get("_target_")
        if isinstance(target, str):
            old = next((o for o in OLD_TARGETS if target.startswith(o)), None)
            if old is not None:
                out["_target_"] = OLD_TARGETS[old] + target[len(old):]
        return out
    if isinstance(cfg, list | tuple):
        return type(cfg)(current_targets(value) for value in cfg)
    return cfg


def resolve_checkpoint(path: str | os.PathLike) -> Path:
    """``path`` itself, or for a training run directory the checkpoint it is evaluated with:
    ``checkpoints/best.ckpt``, else ``checkpoints/last.ckpt``. UserError naming ``path`` when it
    does not exist or is a directory holding neither. ``release:teacher`` / ``release:student``: the
    shipped networks (:func:`denoiser.release.release_file`)."""
    from denoiser.release import is_release_name, release_file

    if is_release_name(path):
        return release_file(path)
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: checkpoint file does not exist")
    if path.is_dir():
        for name in RUN_CHECKPOINTS:
            if (path / name).is_file():
                return path / name
        raise UserError(f"{path}: is a directory with no {' or '.join(RUN_CHECKPOINTS)} "
                        "(give a checkpoint file or a training run directory)")
    return path


def _check_file(path: str | os.PathLike) -> Path:
    path = resolve_checkpoint(path)
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if not (magic.startswith(b"PK\x03\x04") or magic[:1] == b"\x80"):  # torch.save: zip; legacy: pickle
        raise UserError(f"{path}: not a checkpoint (not a file written by torch.save or Lightning)")
    return path


def _load_safe(path: Path, map_location, trust: bool, trust_key: str):
    """``torch.load(weights_only=True)`` of ``path``; None when it refuses the file and ``trust`` (warned)."""
    try:
        return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:  # what the weights-only unpickler raises for anything it does not allow
        error = exc
    except Exception as exc:  # noqa: BLE001 - any other failure means "not a checkpoint"
        raise UserError(f"{path}: not a checkpoint ({first_line(exc)})") from None
    refused = _refused_globals(path, error)
    if refused:
        shown = ", ".join(refused[:SHOWN_GLOBALS]) + (f", ... {len(refused)} in all" if len(refused) > SHOWN_GLOBALS
                                                      else "")
        what = f"the checkpoint holds pickled objects that could run code ({shown})"
    else:  # refused for another reason (e.g. pickle opcodes the safe loader does not implement)
        what = f"the safe loader cannot read the checkpoint ({_unpickler_reason(error)})"
    if not trust:
        raise UserError(f"{path}: refused: {what}; load it only if you trust its source, with {trust_key}=true")
    log.warning("%s: %s; loading it anyway (weights_only=False) because %s=true", path, what, trust_key)
    return None


def _refused_globals(path: Path, exc: BaseException) -> list[str]:
    """The pickle GLOBALs the safe loader refuses in ``path``: first the one that stopped it (named in
    its message, ``GLOBAL <name>``), then the others of torch's static scan of the file, sorted.

    The scan (``torch.serialization.get_unsafe_globals_in_checkpoint``) reads the zip format that
    ``torch.save`` writes; for the legacy format only the loader's message names one.
    """
    try:
        scanned = sorted(set(torch.serialization.get_unsafe_globals_in_checkpoint(path)))
    except Exception:  # noqa: BLE001 - legacy format, or no scan in this torch version
        scanned = []
    return list(dict.fromkeys([*re.findall(r"GLOBAL ([\w.]+)", str(exc)), *scanned]))


def _unpickler_reason(exc: BaseException) -> str:
    """The line of a weights-only UnpicklingError that says what was refused."""
    text = str(exc)
    match = re.search(r"WeightsUnpickler error:\s*(\S[^\n]*)", text)
    return match.group(1).strip()[:200] if match else first_line(exc)


def net_config(ckpt: Mapping, path: str | os.PathLike) -> dict:
    """The resolved net config (plain dict with ``_target_``) stored in a checkpoint dict."""
    hparams = plain(ckpt.get("hyper_parameters"))
    if not isinstance(hparams, Mapping) or "state_dict" not in ckpt:
        raise UserError(f"{path}: not a Lightning checkpoint (keys: {', '.join(sorted(map(str, ckpt))) or 'none'}; "
                        "need 'state_dict' and 'hyper_parameters')")
    cfg = plain(hparams.get("net"))
    if not isinstance(cfg, Mapping) or "_target_" not in cfg:
        raise UserError(f"{path}: checkpoint has no net config (hyper_parameters['net'] with _target_); "
                        f"hyper_parameters keys: {', '.join(sorted(map(str, hparams))) or 'none'}")
    return dict(cfg)


def net_state_dict(ckpt: Mapping, path: str | os.PathLike, prefix: str = NET_PREFIX) -> dict[str, torch.Tensor]:
    """The entries of ``ckpt["state_dict"]`` under ``prefix``, with the prefix removed."""
    state = ckpt.get("state_dict")
    if not isinstance(state, Mapping):
        raise UserError(f"{path}: checkpoint 'state_dict' is not a mapping")
    out = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
    if not out:
        prefixes = sorted({k.split(".", 1)[0] for k in state})
        raise UserError(f"{path}: checkpoint has no weights under '{prefix}' (prefixes: {', '.join(prefixes) or 'none'})")
    return out


def describe_mismatch(model: torch.nn.Module, state: Mapping[str, torch.Tensor]) -> str | None:
    """One line describing how ``state`` differs from ``model.state_dict()``, or None if it fits."""
    own = model.state_dict()
    missing = [k for k in own if k not in state]
    unexpected = [k for k in state if k not in own]
    shapes = [f"{k} {tuple(state[k].shape)} vs {tuple(own[k].shape)}" for k in own
              if k in state and tuple(state[k].shape) != tuple(own[k].shape)]
    parts = []
    if missing:
        parts.append(f"{len(missing)} missing (e.g. {missing[0]})")
    if unexpected:
        parts.append(f"{len(unexpected)} unexpected (e.g. {unexpected[0]})")
    if shapes:
        parts.append(f"{len(shapes)} with other shapes (e.g. {shapes[0]})")
    return "; ".join(parts) if parts else None


def load_denoiser(path: str | os.PathLike, map_location: str | torch.device = "cpu", *, trust: bool = False,
                  trust_key: str = TRUST_KEY):
    """Build the checkpoint's ``Denoiser`` from its stored config and load its weights.

    Returns the network in eval mode on ``map_location``. Errors (all ``UserError`` naming
    ``path``): missing file, not a checkpoint, refused by the safe loader (without ``trust``,
    see :func:`read_checkpoint`), no net config, another architecture.
    """
    path = resolve_checkpoint(path)
    ckpt = read_checkpoint(path, map_location, trust=trust, trust_key=trust_key)
    cfg = net_config(ckpt, path)
    state = net_state_dict(ckpt, path)
    try:
        net = build_net(cfg, path)
    except UserError as exc:  # a constructor's own message (e.g. kernel.sizes): say which file
        if str(exc).startswith(str(path)):
            raise
        raise UserError(f"{path}: net config: {exc}") from None
    problem = describe_mismatch(net, state)
    if problem:
        raise UserError(f"{path}: checkpoint weights do not fit the architecture of its net config "
                        f"{cfg.get('_target_')} ({problem})")
    net.load_state_dict(state, strict=True)
    return net.to(map_location).eval()


def load_weights(net: torch.nn.Module, path: str | os.PathLike, *, trust: bool = False) -> torch.nn.Module:
    """Load the network weights of the checkpoint at ``path`` into ``net`` (fine-tuning from it).

    The checkpoint's architecture must be ``net``'s: a missing or extra weight or another shape is
    a ``UserError`` naming ``path`` and the first difference. Returns ``net``.
    """
    path = resolve_checkpoint(path)
    ckpt = read_checkpoint(path, "cpu", trust=trust)
    state = net_state_dict(ckpt, path)
    problem = describe_mismatch(net, state)
    if problem:
        raise UserError(f"{path}: its weights do not fit the network being trained ({problem})")
    net.load_state_dict(state, strict=True)
    return net


def save_checkpoint(path: str | os.PathLike, net: torch.nn.Module, net_cfg: Mapping, **extra: Any) -> Path:
    """Write ``net`` as a minimal checkpoint in the Lightning format above, atomically.

    ``net_cfg``: the resolved net config (with ``_target_``) that builds ``net``. Used by
    tests and tools that need a checkpoint without running a trainer; ``extra`` keys go to
    the top level (e.g. ``epoch``).
    """
    path = Path(path)
    ckpt = {
        "state_dict": {NET_PREFIX + k: v.detach().cpu() for k, v in net.state_dict().items()},
        "hyper_parameters": {"net": dict(plain(net_cfg))},
        "epoch": 0,
        "global_step": 0,
        "pytorch-lightning_version": _lightning_version(),
    }
    ckpt.update(extra)
    with atomic_path(path) as tmp:
        torch.save(ckpt, tmp)
    return path


def interpolate_checkpoints(start: str | os.PathLike, end: str | os.PathLike, alpha: float,
                            out: str | os.PathLike, *, trust: bool = False) -> Path:
    """Write to ``out`` the network whose weights are ``(1 - alpha) * start + alpha * end``.

    Weight-space interpolation between a network and its own fine-tune (WiSE-FT, Wortsman et al.,
    CVPR 2022): ``alpha`` 0 is ``start``, 1 is ``end``, and a value between keeps part of what the
    fine-tune gained and part of what it cost. Every floating tensor of the state dict (weights,
    biases, running statistics) is interpolated; any other (an integer counter) is ``end``'s. ``start`` and ``end`` are checkpoint files or run
    directories (:func:`resolve_checkpoint`) of the same network: the same net config and the same
    weight names and shapes. ``out`` is a checkpoint of ``end``'s net config (:func:`save_checkpoint`,
    atomic) whose top-level ``interpolation`` records ``{start, end, alpha}``.

    Errors: ``alpha`` outside [0, 1] (ConfigError); ``start`` or ``end`` unreadable, or two
    networks (UserError naming ``end`` and the first difference).
    """
    alpha = float(alpha)
    if not 0.0 <= alpha <= 1.0:
        raise ConfigError(f"alpha={alpha}: must lie in [0, 1] (0 is start, 1 is end)")
    start, end = resolve_checkpoint(start), resolve_checkpoint(end)
    nets = []
    for path in (start, end):
        ckpt = read_checkpoint(path, "cpu", trust=trust)
        nets.append((net_config(ckpt, path), net_state_dict(ckpt, path)))
    (cfg_a, state_a), (cfg_b, state_b) = nets
    if cfg_a != cfg_b:
        key = next(k for k in sorted(set(cfg_a) | set(cfg_b), key=str) if cfg_a.get(k) != cfg_b.get(k))
        raise UserError(f"{end}: another network than {start} (net config key '{key}' differs)")
    net = build_net(cfg_b, str(end))
    for path, state in ((start, state_a), (end, state_b)):
        problem = describe_mismatch(net, state)
        if problem:
            raise UserError(f"{path}: checkpoint weights do not fit the architecture of its net config ({problem})")
    mixed = {}
    for key, b in state_b.items():
        a = state_a[key]
        if b.is_floating_point():
            mixed[key] = torch.lerp(a.to(torch.float32), b.to(torch.float32), alpha).to(b.dtype)
        else:
            mixed[key] = b
    net.load_state_dict(mixed, strict=True)
    return save_checkpoint(out, net, cfg_b, interpolation={"start": str(start), "end": str(end), "alpha": alpha})


def _lightning_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lightning")  # without importing it (slow)
    except PackageNotFoundError:  # pragma: no cover
        return ""


def checkpoint_paths(spec) -> OrderedDict[str, Path]:
    """``ckpt`` config -> ordered ``{name: path}``.

    ``spec``: None/empty, one path, a list of paths (names are the file stems, or a run
    directory's name; made unique with the run directory, else the parent directory, when two
    stems clash) or a mapping ``{name: path}``. A path may be a run directory
    (:func:`resolve_checkpoint`); the loaders resolve it.
    """
    spec = plain(spec)
    if spec is None or spec == "" or spec == []:
        return OrderedDict()
    if isinstance(spec, (str, os.PathLike)):
        spec = [spec]
    if isinstance(spec, Mapping):
        return OrderedDict((str(k), Path(v)) for k, v in spec.items())
    if not isinstance(spec, (list, tuple)):
        raise ConfigError(f"ckpt: expected a path, a list of paths or a mapping name -> path, got {spec!r}")
    paths = [Path(p) for p in spec]
    stems = [p.stem for p in paths]
    out: OrderedDict[str, Path] = OrderedDict()
    for p in paths:
        # <run>/checkpoints/best.ckpt of two runs: named by their run directories
        parent = p.parent.parent if p.parent.name == "checkpoints" else p.parent
        name = p.stem if stems.count(p.stem) == 1 else f"{parent.name}/{p.stem}"
        if name in out:
            raise ConfigError(f"ckpt: {p} is given twice")
        out[name] = p
    return out
