"""Checkpoints are read with ``torch.load(weights_only=True)`` only: a malicious ``.ckpt`` never runs code.

The malicious checkpoint is a real, loadable tiny checkpoint (``save_checkpoint``) with one more
entry: an object whose ``__reduce__`` makes the unpickler call ``os.system("touch <marker>")``.
Every command that reads a checkpoint (denoise, eval, bench, export, the distillation teacher
``model.teacher_ckpt`` and ``train.py ckpt_path=``) gets it; the test checks that the marker file
was never written and that the error is the one-line refusal naming the file. With the explicit
trust switch the same file loads and the payload runs (the marker appears): that proves the
switch, and that the refusal above was the loader's doing, not a broken payload.
"""

from __future__ import annotations

import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers.configs import compose_command

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.eval_data import write_dataset

from denoiser.checkpoint import load_denoiser, read_checkpoint, save_checkpoint
from denoiser.configs import build_net, compose_net_config
from denoiser.errors import UserError

VENV_BIN = Path(sys.executable).parent


class Payload:
    """Unpickles as ``os.system("touch <marker>")``: the code a foreign checkpoint could run."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {shlex.quote(str(self.marker))}",))


def refusal(path: Path, key: str = "trust_checkpoint") -> str:
    return (f"{path}: refused: the checkpoint holds pickled objects that could run code (posix.system); "
            f"load it only if you trust its source, with {key}=true")


@pytest.fixture(scope="module")
def tiny_cfg():
    return compose_net_config("tiny", "student")


@pytest.fixture
def evil(tmp_path, tiny_cfg):
    """``(checkpoint path, marker path)``: a working tiny checkpoint that also runs the payload when unpickled."""
    torch.manual_seed(0)
    marker = tmp_path / "payload_ran"
    path = save_checkpoint(tmp_path / "evil.ckpt", build_net(tiny_cfg), tiny_cfg, note=Payload(marker))
    return path, marker


compose = compose_command


def test_loader_refuses_and_trust_switch_loads(evil, caplog):
    path, marker = evil
    with pytest.raises(UserError) as info:
        load_denoiser(path)
    assert str(info.value) == refusal(path)
    assert not marker.exists()
    with pytest.raises(UserError, match="refused"):
        read_checkpoint(path)
    assert not marker.exists()

    with caplog.at_level("WARNING", logger="denoiser.checkpoint"):
        net = load_denoiser(path, trust=True)
    assert marker.exists()  # the switch really loads the whole pickle
    assert net.num_parameters() > 0
    assert any("trust_checkpoint=true" in r.getMessage() and "posix.system" in r.getMessage() for r in caplog.records)


def test_safe_checkpoints_load_without_trust_or_warning(tmp_path, tiny_cfg, caplog):
    path = save_checkpoint(tmp_path / "good.ckpt", build_net(tiny_cfg), tiny_cfg)
    with caplog.at_level("WARNING", logger="denoiser.checkpoint"):
        load_denoiser(path)
        load_denoiser(path, trust=True)
    assert not caplog.records


def test_legacy_format_and_other_unsafe_types_are_refused(tmp_path, tiny_cfg):
    """The legacy (non-zip) format and an OmegaConf container (a type Lightning does not write) are refused too."""
    from omegaconf import OmegaConf

    marker = tmp_path / "payload_ran"
    ckpt = {"state_dict": {}, "hyper_parameters": {"net": tiny_cfg}, "note": Payload(marker)}
    legacy = tmp_path / "legacy.ckpt"
    torch.save(ckpt, legacy, _use_new_zipfile_serialization=False)
    with pytest.raises(UserError) as info:
        read_checkpoint(legacy)
    assert str(info.value) == refusal(legacy) and not marker.exists()

    omega = tmp_path / "omega.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": OmegaConf.create({"net": tiny_cfg})}, omega)
    with pytest.raises(UserError, match=r"omega\.ckpt: refused: the checkpoint holds pickled objects that could run code \(.*omegaconf\..* in all\)"):
        read_checkpoint(omega)
    assert read_checkpoint(omega, trust=True)["hyper_parameters"]["net"]["_target_"] == tiny_cfg["_target_"]



def test_pickle_the_safe_loader_cannot_read(tmp_path, tiny_cfg):
    """A plain ``pickle.dumps`` (protocol-4 opcodes the safe loader lacks, no GLOBAL to name) is refused with
    torch's reason; trusted, the full loader finds it is no torch checkpoint at all."""
    import pickle
    import warnings

    path = tmp_path / "plain.ckpt"
    path.write_bytes(pickle.dumps({"state_dict": {}, "hyper_parameters": {"net": tiny_cfg}}, protocol=4))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch warns about the protocol before refusing
        with pytest.raises(UserError, match=r"plain\.ckpt: refused: the safe loader cannot read the checkpoint "
                                            r"\(.+\); load it only if you trust its source, with trust_checkpoint=true$"):
            read_checkpoint(path)
        with pytest.raises(UserError, match=r"plain\.ckpt: not a checkpoint \(Invalid magic number"):
            read_checkpoint(path, trust=True)

# ----------------------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    root = tmp_path_factory.mktemp("secdata")
    write_dataset(root, sequences=1, frames=2, size=16)
    return root


def _denoise(ckpt: Path, data: Path, out: Path, *extra: str):
    from denoiser.commands.denoise import run

    return run(compose("denoise", [f"ckpt={ckpt}", f"input={data / 'test' / 'seq_000'}", f"output={out}",
                                   "threads=1", *extra]))


def _eval(ckpt: Path, data: Path, out: Path, *extra: str):
    from denoiser.commands.evaluate import run

    return run(compose("eval", ["data=tiny", f"data.root={data}", f"ckpt=[{ckpt}]", "~baselines",
                                "metrics=[psnr]", "images.frame=null", "threads=1", f"out_dir={out}", *extra]))


def _bench(ckpt: Path, data: Path, out: Path, *extra: str):
    from denoiser.commands.bench import run

    return run(compose("bench", ["data=tiny", f"data.root={data}", f"ckpt=[{ckpt}]", "~baselines",
                                 "sizes=[[16,16]]", "use_backends=[eager]", "warmup=0", "repeats=1", "threads=1",
                                 f"out_dir={out}", *extra]))


def _export(ckpt: Path, data: Path, out: Path, *extra: str):
    from denoiser.commands.export import run

    return run(compose("export", [f"ckpt={ckpt}", f"out={out / 'net.onnx'}", "trace_size=[16,16]",
                                  "check_size=[8,24]", "threads=1", *extra]))


COMMANDS = {"denoise": _denoise, "eval": _eval, "bench": _bench, "export": _export}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_command_refuses_malicious_checkpoint(command, evil, data, tmp_path):
    path, marker = evil
    out = tmp_path / "out"
    with pytest.raises(UserError) as info:
        COMMANDS[command](path, data, out)
    assert str(info.value) == refusal(path)
    assert not marker.exists()
    assert not out.exists() or not any(p.is_file() for p in out.rglob("*"))


@pytest.mark.parametrize("command", list(COMMANDS))
def test_command_loads_it_with_trust_checkpoint(command, evil, data, tmp_path):
    path, marker = evil
    COMMANDS[command](path, data, tmp_path / "out", "trust_checkpoint=true")
    assert marker.exists()


def test_console_script_prints_one_line_and_runs_nothing(evil, data, tmp_path):
    """What the user of ``denoiser-denoise ckpt=evil.ckpt ...`` sees: exit 2, one line, no traceback."""
    path, marker = evil
    env = {k: v for k, v in os.environ.items() if k != "DENOISER_DEBUG"}
    proc = subprocess.run([str(VENV_BIN / "denoiser-denoise"), f"ckpt={path}", f"input={data / 'test' / 'seq_000'}",
                           f"output={tmp_path / 'out'}", f"hydra.run.dir={tmp_path / 'run'}"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert proc.stderr.strip().splitlines() == ["error: " + refusal(path)]
    assert not marker.exists() and not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- training


@pytest.fixture(scope="module")
def train_data(tmp_path_factory):
    from denoiser.data.synthetic import write_synthetic_sequence

    root = tmp_path_factory.mktemp("sectrain")
    for split in ("train", "val"):
        write_synthetic_sequence(root / split / "seq0", frames=4, width=32, height=32, seed=len(split))
    return root


def train(data: Path, out: Path, *overrides: str) -> dict:
    from helpers.train_args import FAST

    from denoiser.commands import train as train_script

    cfg = compose("train", [*FAST, f"data.root={data}", f"output_dir={out}", "trainer.max_steps=2",
                            "final_validation=false", *overrides])
    return train_script.train(cfg)


def test_distillation_teacher(evil, train_data, tmp_path):
    path, marker = evil
    with pytest.raises(UserError) as info:
        train(train_data, tmp_path / "refused", "model=distill", f"model.teacher_ckpt={path}")
    assert str(info.value) == refusal(path, "model.trust_teacher_ckpt")
    assert not marker.exists()

    train(train_data, tmp_path / "trusted", "model=distill", f"model.teacher_ckpt={path}",
          "model.trust_teacher_ckpt=true", "ablation=no_adversarial")
    assert marker.exists()
    assert load_denoiser(tmp_path / "trusted" / "checkpoints" / "last.ckpt").num_parameters() > 0


def test_resume_with_ckpt_path(train_data, tmp_path):
    """``train.py ckpt_path=<file>``: a real Lightning checkpoint with a payload added is refused before
    Lightning reads it; with ``trust_checkpoint=true`` training resumes from it."""
    train(train_data, tmp_path / "first")
    ckpt = read_checkpoint(tmp_path / "first" / "checkpoints" / "last.ckpt")  # Lightning's own file: safe
    assert ckpt["global_step"] == 2
    marker = tmp_path / "payload_ran"
    ckpt["hyper_parameters"]["note"] = Payload(marker)
    evil = tmp_path / "evil.ckpt"
    torch.save(ckpt, evil)

    with pytest.raises(UserError) as info:
        train(train_data, tmp_path / "refused", "trainer.max_steps=4", f"ckpt_path={evil}")
    assert str(info.value) == refusal(evil)
    assert not marker.exists() and not (tmp_path / "refused" / "checkpoints").exists()

    train(train_data, tmp_path / "trusted", "trainer.max_steps=4", f"ckpt_path={evil}", "trust_checkpoint=true")
    assert marker.exists()
    assert read_checkpoint(tmp_path / "trusted" / "checkpoints" / "last.ckpt")["global_step"] == 4
