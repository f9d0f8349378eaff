"""Configs from ``conf/`` (:data:`denoiser.conf.CONF_DIR`): composing a net config and
instantiating any ``_target_`` config, with one-line errors.

* :func:`instantiate_config`: ``hydra.utils.instantiate`` where a config mistake (a missing
  mandatory value, an unknown ``_target_``, a misspelled argument) is a one-line
  :class:`~denoiser.errors.ConfigError` naming the key, and a
  :class:`~denoiser.errors.UserError` raised by a constructor comes out as itself;
* :func:`compose_config`: any config of ``conf/`` with overrides, from anywhere (inside a
  running Hydra app too);
* :func:`compose_net_config`: the resolved net config of the groups ``net``, ``kernel``,
  ``lever`` and ``ablation`` plus overrides (what checkpoints store under ``hyper_parameters['net']``);
* :func:`current_overrides`: overrides naming an option where it used to be (``ablation=history_clamp``,
  now ``lever=history_clamp``: :data:`MOVED_OPTIONS`) rewritten to name where it is, so stored
  overrides (a run directory's ``.hydra/overrides.yaml``, a finished run's ``metrics.json``) compose;
* :func:`build_net`: that config instantiated, a :class:`~denoiser.nn.denoiser.Denoiser`;
* :func:`job_dirname`: a multirun job's folder name from its overrides (the resolver
  ``${job_dirname:...}`` of ``conf/train.yaml``'s ``hydra.sweep.subdir``).

Used by the commands (training, the benchmarks, netstats), checkpoints, the data module and
the tests.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from denoiser.errors import ConfigError, UserError, first_line


def plain(cfg: Any) -> Any:
    """A resolved plain-Python copy of a config node (DictConfig/ListConfig), else ``cfg`` itself."""
    from omegaconf import OmegaConf

    if OmegaConf.is_config(cfg):
        return OmegaConf.to_container(cfg, resolve=True)
    return cfg


def instantiate_config(node: Any, key: str, *, what: str | None = None, any_failure: bool = False,
                       **kwargs: Any) -> Any:
    """``hydra.utils.instantiate(node, **kwargs)`` with one-line errors naming ``key``.

    A missing mandatory value, an OmegaConf error, an unknown ``_target_`` or a misspelled
    argument becomes ``ConfigError("<key>: <problem>")`` (``"<key>: <what> cannot be
    instantiated (<problem>)"`` when ``what`` is given). A UserError raised inside a
    constructor (e.g. a missing teacher checkpoint, a bad ``kernel.sizes``) is re-raised as
    is. Any other exception is a bug and propagates, unless ``any_failure``: then it is the
    config's mistake too (a config read from a file, such as a checkpoint's net config).
    """
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate
    from omegaconf.errors import MissingMandatoryValue, OmegaConfBaseException

    def mistake(exc: BaseException) -> ConfigError:
        problem = first_line(exc, 300)
        return ConfigError(f"{key}: {what} cannot be instantiated ({problem})" if what else f"{key}: {problem}")

    try:
        return instantiate(node, **kwargs)
    except MissingMandatoryValue as exc:
        raise ConfigError(f"{_full_key(exc, key)}: missing mandatory value (give it on the command line)") from None
    except OmegaConfBaseException as exc:
        raise mistake(exc) from None
    except InstantiationException as exc:
        chain: list[BaseException] = []
        cause: BaseException | None = exc
        while cause is not None and len(chain) < 20:
            chain.append(cause)
            cause = cause.__cause__ or cause.__context__
        for cause in chain:
            if isinstance(cause, UserError):
                raise cause from None
            if isinstance(cause, MissingMandatoryValue):
                raise ConfigError(f"{_full_key(cause, key)}: missing mandatory value (give it on the command line)") \
                    from None
        for cause in chain:  # config mistakes: unknown _target_, misspelled argument
            text = str(cause)
            if "Error locating target" in text or isinstance(cause, (ImportError, AttributeError)) or (
                    isinstance(cause, TypeError) and "argument" in text):
                raise mistake(cause) from None
        if any_failure:
            raise mistake(exc) from None
        raise
    except UserError:
        raise
    except Exception as exc:
        if any_failure:
            raise mistake(exc) from None
        raise


def _full_key(exc: BaseException, key: str) -> str:
    full = getattr(exc, "full_key", None)
    return f"{key}.{full}" if full and not str(full).startswith(key) else (full or key)


#: options that moved to another config group: ``{(old group, option): new group}``. The levers (an
#: added mechanism, not a part removed or replaced) left ``conf/ablation/`` for ``conf/lever/``
#: (issue 63); run directories from before store ``ablation=<lever>`` in their overrides.
MOVED_OPTIONS = {("ablation", name): "lever" for name in (
    "demodulation", "filtered_remodulation", "hdr_loss", "hdr_loss_distill", "history_clamp",
    "history_disagreement", "log_filter", "noise_scale")}
_OVERRIDE = re.compile(r"^(?P<prefix>[+~]*)(?P<group>[\w/.@-]+)=(?P<option>[\w.-]+)$")


def current_overrides(overrides: Sequence[str]) -> list[str]:
    """``overrides`` with each ``<group>=<option>`` of a moved option (:data:`MOVED_OPTIONS`) naming
    its group now: ``ablation=history_clamp`` -> ``lever=history_clamp`` (``+``/``~`` kept); every
    other override as given. Where stored overrides are read (:func:`compose_config`, a sweep's
    jobs: :func:`denoiser.report.pareto.read_job`)."""
    out = []
    for override in map(str, overrides):
        m = _OVERRIDE.match(override)
        group = MOVED_OPTIONS.get((m["group"], m["option"])) if m else None
        out.append(f"{m['prefix']}{group}={m['option']}" if group else override)
    return out


def compose_config(overrides: Sequence[str] = (), config_name: str | None = None):
    """Compose ``conf/<config_name>.yaml`` (None: an empty config) with Hydra ``overrides`` -> DictConfig.

    An override naming a moved option is read as its new place (:func:`current_overrides`).
    Works inside a running Hydra app too (its ``conf/`` is the same directory). Hydra's and
    OmegaConf's exceptions propagate (callers name what they composed).
    """
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from denoiser.conf import CONF_DIR

    overrides = current_overrides(overrides)
    if GlobalHydra.instance().is_initialized():  # inside a Hydra app
        return compose(config_name, overrides=list(overrides))
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name, overrides=list(overrides))


def compose_net_config(net: str = "student", kernel: str | None = None, overrides: Sequence[str] = (),
                       ablation: str = "none", lever: str | None = None) -> dict:
    """Resolved net config composed from ``conf/net/<net>.yaml``, ``conf/kernel/<kernel>.yaml``,
    ``conf/lever/<lever>.yaml`` (None: no lever) and ``conf/ablation/<ablation>.yaml`` (in the order
    of ``conf/train.yaml``), then Hydra ``overrides`` (e.g. ``["net.unet.encoder=[8,8,8]"]``).

    ``kernel`` defaults to ``net``'s own name when such a kernel file exists, else ``student``.
    Returns the plain dict that :func:`build_net` instantiates and checkpoints store under
    ``hyper_parameters['net']``. A missing group option or a bad override is a one-line ConfigError.
    """
    from hydra.errors import HydraException
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    from denoiser.conf import CONF_DIR

    if kernel is None:
        kernel = net if (Path(CONF_DIR) / "kernel" / f"{net}.yaml").exists() else "student"
    groups = (f"net={net} kernel={kernel}" + (f" lever={lever}" if lever else "")
              + (f" ablation={ablation}" if ablation != "none" else ""))
    try:
        cfg = compose_config([f"+net={net}", f"+kernel={kernel}", *([f"+lever={lever}"] if lever else []),
                              f"+ablation={ablation}", *overrides])
        return OmegaConf.to_container(cfg.net, resolve=True)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"{groups}: {first_line(exc)}") from None


def load_layout(name: str, buffers: Mapping[str, Any] | None = None):
    """The data layout of ``conf/layout/<name>.yaml`` (``native``, ``blender``), instantiated.

    ``buffers``: more entries for its buffer table (``{name: {file, passes, channels}}``, as in
    the YAML), e.g. a pass a tool reads that training does not. ConfigError naming the options
    for an unknown ``name``.
    """
    from omegaconf import OmegaConf

    from denoiser.conf import CONF_DIR

    names = sorted(p.stem for p in (Path(CONF_DIR) / "layout").glob("*.yaml"))
    if name not in names:
        raise ConfigError(f"layout: unknown {name!r}; use {' or '.join(names)}")
    node = compose_config([f"+layout={name}"]).data.layout
    if buffers:
        OmegaConf.set_struct(node, False)
        node = OmegaConf.merge(node, {"buffers": dict(buffers)})
    return instantiate_config(node, "layout")


def build_net(cfg: Any, where: str = "net"):
    """Instantiate a net config (``_target_``, e.g. from :func:`compose_net_config`) -> the network.

    Any failure is a one-line UserError naming ``where`` (the config's key, or the checkpoint
    holding it): ``<where>: net config cannot be instantiated (...)``, or the constructor's
    own UserError (e.g. ``kernel.sizes: ...``).
    """
    import torch

    net = instantiate_config(plain(cfg), str(where), what="net config", any_failure=True, _convert_="all")
    if not isinstance(net, torch.nn.Module):
        raise ConfigError(f"{where}: net config builds a {type(net).__name__}, not a torch module")
    return net


#: the longest job folder name :func:`job_dirname` gives (a longer one is cut and ends in a hash)
MAX_DIRNAME = 80
_UNSAFE = re.compile(r"[^A-Za-z0-9._=,+-]+")


def group_options(group: str) -> str:
    """The options of the config group ``group`` (``data``, ``hydra/launcher``: a folder of ``conf/``),
    sorted and joined by ``|``: the group lists of a command's ``--help`` (``${options:data}``),
    written from the folders, not by hand. ConfigError for a group that is no folder of ``conf/``."""
    from denoiser.conf import CONF_DIR

    folder = Path(CONF_DIR) / group
    if not folder.is_dir():
        raise ConfigError(f"{folder}: no such config group")
    return "|".join(sorted(p.stem for p in folder.glob("*.yaml")))


def job_dirname(overrides: str, limit: int = MAX_DIRNAME) -> str:
    """A folder name from a multirun job's ``hydra.job.override_dirname`` (``ablation=k3,model.optimizer.lr=0.001``):
    every run of characters other than letters, digits and ``._=,+-`` (``/``, spaces, quotes,
    brackets) becomes one ``_``; ``""`` (no override left) is ``defaults``; a name longer than
    ``limit`` keeps its first ``limit - 9`` characters and ends in ``_`` and 8 hex digits of the
    SHA-1 of the whole, so two long names stay apart."""
    name = _UNSAFE.sub("_", str(overrides)).strip("_") or "defaults"
    if len(name) > limit:
        name = name[: limit - 9] + "_" + hashlib.sha1(str(overrides).encode()).hexdigest()[:8]
    return name
