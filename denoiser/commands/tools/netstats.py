"""Size of a network composed from ``conf/``: ``python -m denoiser.commands.tools.netstats``.

Usage::

    python -m denoiser.commands.tools.netstats net=student kernel=student
    python -m denoiser.commands.tools.netstats net=teacher kernel=teacher ablation=no_pyramid
    python -m denoiser.commands.tools.netstats net=student net.unet.encoder=[16,32,64] net.unet.decoder=[32,16]

A Hydra app over ``conf/netstats.yaml``, which composes only the groups ``net``, ``kernel``, ``lever``
and ``ablation`` (defaults ``student``, ``student``, none, ``none``), so it works without the training
configs; other ``key=value`` arguments are Hydra overrides. Prints the parameters per part,
the U-Net feature widths and the FLOPs of one ``flops_size`` x ``flops_size`` frame (default
256; :func:`denoiser.measure.count_flops`). A bad value is one line on stderr (exit 2).
"""

from __future__ import annotations

from omegaconf import DictConfig

from denoiser.commands.app import hydra_runtime
from denoiser.configs import build_net, plain
from denoiser.measure import count_flops


def describe(net, flops_size: int) -> list[tuple[str, str]]:
    """``(label, value)`` rows: parameters (total and per part), feature widths, pad multiple, GFLOP."""
    rows = [("parameters", f"{net.num_parameters():,}")]
    for name in ("embed", "unet"):
        rows.append((f"  {name}", f"{sum(p.numel() for p in getattr(net, name).parameters()):,}"))
    rows.append(("feature_channels", str(net.feature_channels)))
    rows.append(("pad multiple", str(net.multiple)))
    rows.append((f"GFLOP per {flops_size}x{flops_size} frame", f"{count_flops(net, flops_size, flops_size) / 1e9:.3f}"))
    return rows


def run(cfg: DictConfig) -> list[tuple[str, str]]:
    """The ``netstats`` task: print the network's size; returns the rows of :func:`describe`."""
    net = build_net(plain(cfg.net))
    rows = describe(net, int(cfg.flops_size))
    print(" ".join(["netstats", *hydra_runtime()[0]]))
    print(f"kernel.sizes={list(cfg.kernel.sizes)} filter={cfg.net.filter._target_.rsplit('.', 1)[-1]} "
          f"temporal={'off' if cfg.net.temporal is None else 'on'}")
    for key, value in rows:
        print(f"{key:<26} {value}")
    return rows


def main() -> None:
    from denoiser.commands.app import hydra_command

    hydra_command(run, "netstats")()


if __name__ == "__main__":
    main()
