"""Compose a network config from ``conf/`` and print its size: ``python -m denoiser.commands.netstats``.

Usage::

    python -m denoiser.commands.netstats net=student kernel=student
    python -m denoiser.commands.netstats net=teacher kernel=teacher ablation=no_pyramid
    python -m denoiser.commands.netstats net=student net.unet.encoder=[16,32,64] net.unet.decoder=[32,16]

Only the groups ``net``, ``kernel`` and ``ablation`` are composed (defaults ``student``,
``student``, ``none``), so this works without the training configs. Other ``key=value``
arguments are passed to Hydra as overrides. Prints parameters per part, the U-Net feature
widths and the FLOPs of one 256x256 frame.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from denoiser.errors import ConfigError

#: frame size (square) of the FLOP count printed by ``main``
FLOPS_SIZE = 256

#: config groups composed for a network, in composition order
NET_GROUPS = {"net": "student", "kernel": "student", "ablation": "none"}


def compose_net_config(args: Sequence[str] = ()):
    """Compose ``net``/``kernel``/``ablation`` from ``conf/`` with ``key=value`` arguments.

    Returns the whole composed DictConfig (``cfg.net`` instantiates the Denoiser).
    """
    from hydra import compose, initialize_config_dir
    from hydra.errors import HydraException
    from omegaconf.errors import OmegaConfBaseException

    from denoiser.conf import CONF_DIR

    groups = dict(NET_GROUPS)
    rest = []
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep:
            raise ConfigError(f"argument {arg!r}: expected key=value")
        if key in groups:
            groups[key] = value
        else:
            rest.append(arg)
    overrides = [f"+{k}={v}" for k, v in groups.items()] + rest
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            return compose(config_name=None, overrides=overrides)
    except (HydraException, OmegaConfBaseException) as exc:
        raise ConfigError(f"conf/: {str(exc).splitlines()[0]}") from exc


def build_net(cfg):
    """Instantiate ``cfg.net`` (a composed config) -> :class:`~denoiser.nn.denoiser.Denoiser`.

    A :class:`~denoiser.errors.UserError` raised by a constructor (e.g. a bad ``kernel.sizes``)
    comes out as itself, not wrapped in Hydra's ``InstantiationException``.
    """
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    from denoiser.errors import UserError

    try:
        return instantiate(cfg.net)
    except InstantiationException as exc:
        cause = exc.__cause__
        if isinstance(cause, UserError):
            raise cause from None
        raise ConfigError(f"net: {str(exc).splitlines()[0]}") from exc


def count_flops(net, height: int, width: int) -> int:
    """FLOPs of one ``step`` on a ``1 x height x width`` frame with history.

    Counted by ``torch.utils.flop_counter.FlopCounterMode`` on fake tensors
    (``FakeTensorMode``: shapes only, no arithmetic), so even 1080p counts in about a second.
    """
    import torch
    from torch._subclasses.fake_tensor import FakeTensorMode
    from torch.utils.flop_counter import FlopCounterMode

    from denoiser.frames import random_frame

    with FakeTensorMode(allow_non_fake_inputs=True) as mode, torch.inference_mode():
        frame = {k: mode.from_tensor(v) for k, v in random_frame(1, height, width).items()}
        _, state, _ = net.step(frame, None)
        with FlopCounterMode(display=False) as counter:
            net.step(frame, state)
    return counter.get_total_flops()


def describe(net) -> list[tuple[str, str]]:
    rows = [("parameters", f"{net.num_parameters():,}")]
    for name in ("embed", "unet"):
        rows.append((f"  {name}", f"{sum(p.numel() for p in getattr(net, name).parameters()):,}"))
    rows.append(("feature_channels", str(net.feature_channels)))
    rows.append(("pad multiple", str(net.multiple)))
    rows.append((f"GFLOP per {FLOPS_SIZE}x{FLOPS_SIZE} frame",
                 f"{count_flops(net, FLOPS_SIZE, FLOPS_SIZE) / 1e9:.3f}"))
    return rows


def main(argv: Sequence[str] | None = None) -> None:
    from denoiser.commands.app import report_user_error
    from denoiser.errors import UserError

    args = list(sys.argv[1:] if argv is None else argv)
    try:
        cfg = compose_net_config(args)
        net = build_net(cfg)
    except UserError as exc:
        report_user_error(exc)
        return
    print(" ".join(args) or "net=student kernel=student")
    print(f"kernel.sizes={list(cfg.kernel.sizes)} filter={cfg.net.filter._target_.rsplit('.', 1)[-1]} "
          f"temporal={'off' if cfg.net.temporal is None else 'on'}")
    for key, value in describe(net):
        print(f"{key:<26} {value}")


if __name__ == "__main__":
    main()
