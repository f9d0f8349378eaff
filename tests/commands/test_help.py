"""Each console script's ``--help``: the command's name and what it does first, then its own config
groups (with their options) and its own keys, nothing of the other commands, and no generic Hydra
page (which listed every training group for every command).

The help text comes from ``hydra.help`` of each entry config (template ``conf/hydra/help/command.yaml``);
the groups are written there by hand and checked here against what Hydra composes.
"""

from __future__ import annotations

import functools
import importlib
import logging
import re
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from denoiser.conf import CONF_DIR

#: console script -> (module with ``main``, entry config)
COMMANDS = {
    "denoiser-train": ("denoiser.commands.train", "train"),
    "denoiser-eval": ("denoiser.commands.evaluate", "eval"),
    "denoiser-bench": ("denoiser.commands.bench", "bench"),
    "denoiser-export": ("denoiser.commands.export", "export"),
    "denoiser-denoise": ("denoiser.commands.denoise", "denoise"),
    "denoiser-render": ("denoiser.commands.render", "render"),
    "denoiser-pareto": ("denoiser.commands.pareto", "pareto"),
    "denoiser-flicker": ("denoiser.commands.flicker", "flicker"),
    "denoiser-adapt": ("denoiser.commands.adapt", "adapt"),
}
#: Hydra's own groups a command's help also lists (only training runs multiruns)
HYDRA_GROUPS = {"denoiser-train": {"hydra/launcher", "hydra/sweeper"}}


@pytest.fixture(autouse=True)
def restore_logging():
    """Hydra configures logging for --help too (handlers on this test's captured stdout): undo it,
    or later tests' log records would go to a closed stream."""
    loggers = [logging.getLogger(), *(lg for lg in logging.Logger.manager.loggerDict.values()
                                       if isinstance(lg, logging.Logger))]
    saved = [(lg, lg.handlers[:], lg.level, lg.propagate, lg.disabled) for lg in loggers]
    yield
    for lg, handlers, level, propagate, disabled in saved:
        lg.handlers[:] = handlers
        lg.setLevel(level)
        lg.propagate, lg.disabled = propagate, disabled
    known = {id(lg) for lg in loggers}
    for lg in list(logging.Logger.manager.loggerDict.values()):  # loggers created meanwhile
        if isinstance(lg, logging.Logger) and id(lg) not in known:
            lg.handlers.clear()


def run_help(script: str, monkeypatch, capsys, *overrides: str) -> str:
    """``<script> [overrides] --help`` in this process: the console script's own ``main``."""
    module, _ = COMMANDS[script]
    main = importlib.import_module(module).main
    monkeypatch.setattr(sys, "argv", [script, *overrides, "--help"])
    try:
        main()
    except SystemExit as exc:  # Hydra returns after printing the help; an exit must be a clean one
        assert exc.code in (0, None), exc.code
    return capsys.readouterr().out


@functools.cache
def composed(config: str):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config, return_hydra_config=True)


def own_groups(script: str) -> set[str]:
    """The config groups the command composes (Hydra's choices, without Hydra's own groups)."""
    choices = composed(COMMANDS[script][1]).hydra.runtime.choices
    return {g for g in choices if not g.startswith("hydra/")} | HYDRA_GROUPS.get(script, set())


def own_keys(script: str) -> set[str]:
    return {k for k in composed(COMMANDS[script][1]) if k != "hydra"}


def listed_groups(text: str) -> dict[str, set[str]]:
    """``{group: options}`` of the help's group lines (``  group=a|b|c   what it is``)."""
    return {m.group(1): set(m.group(2).split("|")) for m in re.finditer(r"^  ([\w/]+)=([\w|]+)", text, re.MULTILINE)}


def options(group: str) -> set[str]:
    return {p.stem for p in (Path(CONF_DIR) / group).glob("*.yaml")}


@pytest.mark.parametrize("script", list(COMMANDS))
def test_help_names_the_command_and_lists_only_its_groups_and_keys(script, monkeypatch, capsys):
    text = run_help(script, monkeypatch, capsys)
    lines = text.splitlines()
    # the name, what it does in two lines, then a blank line
    assert lines[0].startswith(f"{script}: ") and lines[1].strip() and not lines[2].strip(), lines[:3]
    assert "powered by hydra" not in text.lower() and "$" not in text.split("== Keys")[0]
    # its own groups, each with exactly the options of its directory
    groups = own_groups(script)
    assert listed_groups(text) == {g: options(g) for g in groups}
    # its own keys: the composed config is printed
    keys = own_keys(script)
    printed = set(re.findall(r"^(\w+):", text.split("== Keys")[1], re.MULTILINE))
    assert printed == keys
    # nothing of the other commands: neither their groups nor their keys
    other_groups = set().union(*(own_groups(s) for s in COMMANDS if s != script)) - groups
    other_keys = set().union(*(own_keys(s) for s in COMMANDS if s != script)) - keys
    found = {g for g in other_groups if re.search(rf"(^|\s){re.escape(g)}=", text, re.MULTILINE)}
    found |= {k for k in other_keys if re.search(rf"^{re.escape(k)}:", text, re.MULTILINE)}
    assert not found, f"{script} --help shows other commands' groups or keys: {found}"


def test_denoise_help_is_about_denoising_only(monkeypatch, capsys):
    text = run_help("denoiser-denoise", monkeypatch, capsys)
    assert "layout=native|blender" in text and "(now: native)" in text
    for word in ("callbacks", "trainer", "experiment", "ablation", "lever", "data=", "scene", "model"):
        assert word not in text, word
    for key in ("ckpt", "input", "output", "write", "channel_prefix", "replay_frames", "layout"):
        assert f"\n{key}:" in text
    blender = run_help("denoiser-denoise", monkeypatch, capsys, "layout=blender")
    assert "(now: blender)" in blender and "BlenderLayout" in blender


def test_train_help_shows_the_current_choices(monkeypatch, capsys):
    text = run_help("denoiser-train", monkeypatch, capsys, "model=teacher", "layout=blender")
    assert "(now: teacher)" in text and "(now: blender)" in text and "BlenderLayout" in text
    assert OmegaConf.to_container(composed("train").hydra.help)["app_name"] == "denoiser-train"


#: the argparse commands (``python -m denoiser.commands.tools.<name>``, no config of their own)
ARGPARSE_COMMANDS = ("noise_response", "diagnose_history", "albedo_bound", "paper_budget", "nn_fingerprint")


@pytest.mark.parametrize("name", ARGPARSE_COMMANDS)
def test_argparse_commands_help_and_usage_mistakes(name, capsys):
    """``--help``: the ``python -m`` name, what the command does (its docstring) and every option;
    a usage mistake: one line ``error: ...`` naming ``--help``, exit 2, no traceback."""
    module = importlib.import_module(f"denoiser.commands.tools.{name}")
    with pytest.raises(SystemExit) as exit_:
        module.main(["--help"])
    assert exit_.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith(f"usage: python -m denoiser.commands.tools.{name} ")
    assert module.__doc__.splitlines()[0] in text and "Usage::" in text and "--help" in text
    with pytest.raises(SystemExit) as exit_:
        module.main(["--no-such-option"])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith("error: ") and f"denoiser.commands.tools.{name} --help" in err
    assert "--no-such-option" in err or "arguments are required" in err   # argparse names the first mistake
