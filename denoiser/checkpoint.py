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

Checkpoints are loaded with ``torch.load(weights_only=True)`` first; a Lightning checkpoint
holding other pickled objects (e.g. OmegaConf containers in ``hyper_parameters``) is then
loaded with ``weights_only=False``: only load checkpoints you trust, as with Lightning itself.
"""

from __future__ import annotations

import os
import pickle
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch

from denoiser.atomic import atomic_path
from denoiser.configs import build_net, plain
from denoiser.errors import ConfigError, UserError, first_line

NET_PREFIX = "net."


def read_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> dict:
    """The raw checkpoint dict of ``path`` (UserError if missing or not a torch checkpoint)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: checkpoint file does not exist")
    if path.is_dir():
        raise UserError(f"{path}: is a directory, not a checkpoint file")
    with open(path, "rb") as fh:
        magic = fh.read(4)
    if not (magic.startswith(b"PK\x03\x04") or magic[:1] == b"\x80"):  # torch.save: zip; legacy: pickle
        raise UserError(f"{path}: not a checkpoint (not a file written by torch.save or Lightning)")
    try:
        ckpt = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError:
        try:
            ckpt = torch.load(path, map_location=map_location, weights_only=False)
        except Exception as exc:  # noqa: BLE001 - any failure means "not a checkpoint"
            raise UserError(f"{path}: not a checkpoint ({first_line(exc)})") from None
    except Exception as exc:  # noqa: BLE001
        raise UserError(f"{path}: not a checkpoint ({first_line(exc)})") from None
    if not isinstance(ckpt, Mapping):
        raise UserError(f"{path}: not a Lightning checkpoint (top level is a {type(ckpt).__name__}, not a dict)")
    return dict(ckpt)


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


def load_denoiser(path: str | os.PathLike, map_location: str | torch.device = "cpu"):
    """Build the checkpoint's ``Denoiser`` from its stored config and load its weights.

    Returns the network in eval mode on ``map_location``. Errors (all ``UserError`` naming
    ``path``): missing file, not a checkpoint, no net config, another architecture.
    """
    ckpt = read_checkpoint(path, map_location)
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


def _lightning_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("lightning")  # without importing it (slow)
    except PackageNotFoundError:  # pragma: no cover
        return ""


def checkpoint_paths(spec) -> OrderedDict[str, Path]:
    """``ckpt`` config -> ordered ``{name: path}``.

    ``spec``: None/empty, one path, a list of paths (names are the file stems, made unique
    with the parent directory when two stems clash) or a mapping ``{name: path}``.
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
        name = p.stem if stems.count(p.stem) == 1 else f"{p.parent.name}/{p.stem}"
        if name in out:
            raise ConfigError(f"ckpt: {p} is given twice")
        out[name] = p
    return out
