"""Shared start-up for the console commands (Hydra apps over ``conf/``, and a few argparse ones).

``hydra_command(task, config_name)`` returns a ``main()`` suitable for a console script:
Hydra composes ``conf/<config_name>.yaml`` with the command line, then ``task(cfg)`` runs.
A :class:`~denoiser.errors.UserError` becomes one line on stderr and exit code 2; the full
traceback is shown only with ``DENOISER_DEBUG=1``. The commands that take no config
(``python -m denoiser.commands.tools.noise_response``, ``diagnose_history``, ``albedo_bound``,
``paper_budget``) parse with :class:`CommandParser` (argparse, ``key=value`` accepted) and end a
UserError with :func:`report_user_error` the same way.

The configs ship inside the package (:data:`denoiser.conf.CONF_DIR`), so a plain
``pip install`` of the project runs every command from any directory.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable

from denoiser.conf import CONF_DIR


def debug_enabled() -> bool:
    return os.environ.get("DENOISER_DEBUG", "") not in ("", "0", "false", "False")


def report_user_error(exc: BaseException) -> None:
    """Print a user error as one line (or the traceback in debug mode) and exit 2."""
    if debug_enabled():
        raise exc
    print(f"error: {exc}", file=sys.stderr)
    sys.exit(2)


def key_value_argv(argv: list[str]) -> list[str]:
    """The project's ``key=value`` command style for argparse scripts: each ``key=value`` (not
    starting with ``-``) becomes ``--key=value`` with ``_`` in the key read as ``-``; other
    arguments pass unchanged."""
    return [f"--{a.split('=', 1)[0].replace('_', '-')}={a.split('=', 1)[1]}"
            if "=" in a and not a.startswith("-") else a for a in argv]


class CommandParser(argparse.ArgumentParser):
    """``argparse`` for the commands that are not Hydra apps (``python -m denoiser.commands.tools.<name>``):
    ``--help`` prints the module docstring as written (``doc``: usage lines kept), ``key=value``
    arguments are read as ``--key=value`` (:func:`key_value_argv`), and a usage mistake (a missing
    or unknown argument, a bad value) is one line ``error: ...`` on stderr and exit 2, as a
    :class:`~denoiser.errors.UserError` is (:func:`report_user_error`)."""

    def __init__(self, module: str, doc: str, **kwargs):
        super().__init__(prog=f"python -m {module}", description=doc,
                         formatter_class=argparse.RawDescriptionHelpFormatter, **kwargs)

    def parse_known_args(self, args=None, namespace=None):
        return super().parse_known_args(key_value_argv(sys.argv[1:] if args is None else list(args)), namespace)

    def error(self, message: str):
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def guarded(task: Callable) -> Callable:
    """Wrap a task so user errors end the process with one line instead of a traceback."""
    from omegaconf.errors import InterpolationResolutionError, MissingMandatoryValue

    from denoiser.errors import ConfigError, UserError

    def wrapper(cfg):
        try:
            return task(cfg)
        except UserError as exc:  # a mistake in the input, not a bug
            report_user_error(exc)
        except (InterpolationResolutionError, MissingMandatoryValue) as exc:  # e.g. key=${no_such_key}, key=???
            if debug_enabled():
                raise
            report_user_error(ConfigError(_config_error_text(cfg, exc)))
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            sys.exit(130)

    wrapper.__name__ = getattr(task, "__name__", "task")
    wrapper.__doc__ = task.__doc__
    return wrapper


def _config_error_text(cfg, exc: BaseException) -> str:
    """``<key>: <problem>`` for an unresolvable config value (finds the key when ``exc`` lacks it)."""
    key = getattr(exc, "full_key", None)
    if not key:
        from omegaconf import OmegaConf

        try:  # resolving the whole config raises at the offending node, with its key
            OmegaConf.to_container(cfg, resolve=True, throw_on_missing=True)
        except Exception as again:  # noqa: BLE001 - only used to locate the key
            key = getattr(again, "full_key", None)
    first = (str(exc).strip().splitlines() or [type(exc).__name__])[0]
    return f"{key or 'config'}: {first}"


def hydra_runtime() -> tuple[list[str], dict[str, str]]:
    """``(command-line overrides, chosen option per config group)`` of the running Hydra app;
    empty outside one (e.g. a task called with a composed config)."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized():
        return [], {}
    hc = HydraConfig.get()
    return list(hc.overrides.task), {k: v for k, v in hc.runtime.choices.items() if v is not None}


def hydra_command(task: Callable, config_name: str) -> Callable[[], None]:
    """Build a console-script entry point running ``task`` as a Hydra app."""
    import hydra

    def main() -> None:
        if not debug_enabled():
            os.environ.setdefault("HYDRA_FULL_ERROR", "0")
        app = hydra.main(config_path=CONF_DIR, config_name=config_name, version_base="1.3")(guarded(task))
        app()

    return main
