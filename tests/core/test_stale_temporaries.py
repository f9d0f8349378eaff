"""Temporaries left by killed atomic writes (``denoiser.atomic``, ``AtomicCheckpointIO``) are removed
when the same command starts again: train (the run's ``checkpoints/``), eval (its output folder and
staging folders of dead evaluations), denoise (its output folder)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import torch
from helpers.session import TEST_LEDGER
from hydra import compose, initialize_config_dir

from denoiser.atomic import atomic_path, is_temporary, remove_stale_temporaries
from denoiser.conf import CONF_DIR
from denoiser.data.synthetic import write_synthetic_sequence


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _leave(directory: Path, *names: str) -> list[Path]:
    directory.mkdir(parents=True, exist_ok=True)
    paths = [directory / n for n in names]
    for p in paths:
        p.write_bytes(b"partial")
    return paths


def test_names_of_atomic_temporaries(tmp_path):
    with atomic_path(tmp_path / "last.ckpt") as tmp:
        assert is_temporary(tmp.name)  # what atomic_path really uses
    for name in (".last.ckpt.tmp", ".frame_0001.exr.k2j_9x0a.tmp.exr", ".metrics.md.abcdefgh.tmp.md"):
        assert is_temporary(name), name
    for name in ("last.ckpt", "frame_0001.exr", ".hydra", "tmp", ".tmp_notes.txt", "x.tmp"):
        assert not is_temporary(name), name
    stale = _leave(tmp_path, ".a.ckpt.abcdefgh.tmp.ckpt", ".last.ckpt.tmp")
    kept = _leave(tmp_path, "a.ckpt", ".keep")
    dead = tmp_path / f".eval-{_dead_pid()}.partial"
    live = tmp_path / ".eval-1.partial"  # pid 1 runs
    for d in (dead, live):
        _leave(d / "images", "x.png")
    removed = remove_stale_temporaries(tmp_path, partial_dirs=".eval-*.partial")
    assert sorted(removed) == sorted([*stale, dead])
    assert all(p.exists() for p in kept) and live.is_dir() and not dead.exists()


def test_train_removes_stale_checkpoint_temporaries(tmp_path):
    from denoiser.commands import train as train_script

    data = tmp_path / "data"
    for split in ("train", "val"):
        write_synthetic_sequence(data / split / "seq0", frames=4, width=32, height=32, seed=3)
    out = tmp_path / "run"
    stale = _leave(out / "checkpoints", ".last.ckpt.abcdefgh.tmp.ckpt", ".last.ckpt.tmp")
    threads = torch.get_num_threads()
    try:
        with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
            cfg = compose("train", overrides=[
                "data=tiny", "net=tiny", "threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null",
                "trainer.enable_model_summary=false", "trainer.max_steps=1", "trainer.val_check_interval=1",
                "trainer.limit_val_batches=1", "model.image_interval=0", "final_validation=false",
                f"data.root={data}", f"output_dir={out}"])
        train_script.train(cfg)
    finally:
        torch.set_num_threads(threads)
    assert not any(p.exists() for p in stale)
    assert (out / "checkpoints" / "last.ckpt").is_file()
    assert [p.name for p in (out / "checkpoints").iterdir() if p.name.startswith(".")] == []


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory) -> Path:
    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config

    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.ckpt", build_net(cfg), cfg)


def test_eval_removes_stale_temporaries_and_dead_staging(tiny_ckpt, tmp_path):
    from denoiser.commands.evaluate import run

    data = tmp_path / "data"
    write_synthetic_sequence(data / "test" / "seq0", frames=3, width=32, height=32, seed=4)
    out = tmp_path / "out"
    stale = _leave(out, ".metrics.md.abcdefgh.tmp.md")
    dead = out / f".eval-{_dead_pid()}.partial"
    _leave(dead / "images", "test_seq0.png")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("eval", overrides=["data=tiny", f"data.root={data}", f"ckpt=[{tiny_ckpt}]", f"out_dir={out}",
                                         "threads=1", "~baselines.oidn_fast", "~baselines.oidn_balanced",
                                         "~baselines.oidn_high", "metrics=[psnr]", "images.size=16",
                                         "purpose=test-suite", f"ledger={TEST_LEDGER}"])
    run(cfg)
    assert not stale[0].exists() and not dead.exists()
    assert (out / "metrics.md").is_file()
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


def test_denoise_removes_stale_frame_temporaries(tiny_ckpt, tmp_path):
    from denoiser.commands.denoise import run

    src = tmp_path / "shot"
    write_synthetic_sequence(src, frames=3, width=32, height=32, seed=5)
    out = tmp_path / "out"
    stale = _leave(out, ".frame_0001.exr.abcdefgh.tmp.exr")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        cfg = compose("denoise", overrides=[f"ckpt={tiny_ckpt}", f"input={src}", f"output={out}", "threads=1"])
    threads = torch.get_num_threads()
    try:
        assert run(cfg)["written"] == 3
    finally:
        torch.set_num_threads(threads)
    assert not stale[0].exists()
    written = ["flicker.png", "frame_0000.exr", "frame_0001.exr", "frame_0002.exr", "report.json", "report.md"]  # + the report (issue 64)
    assert sorted(p.name for p in out.iterdir() if p.name != "denoise_precision.json") == written  # auto's record


def test_a_test_session_leaves_nothing_in_the_temporary_directory(tmp_path):
    """A pytest session of this suite (its conftest makes the extension's build cache and the test
    ledger's folder), and a script that imports the conftest, leave no folder of their own behind:
    only pytest's ``pytest-of-<user>``."""
    import os

    tmp = tmp_path / "tmp"
    tmp.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "DENOISER_CACHE"} | {"TMPDIR": str(tmp)}
    proc = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                           "tests/core/test_metrics.py::test_tonemap_is_aces_then_srgb"],
                          cwd=Path(__file__).resolve().parents[2], env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    assert sorted(p.name for p in tmp.iterdir() if not p.name.startswith("pytest-of-")) == []
    # a script a test runs that imports conftest (as tests/inference/test_signal_stack.py's does): nothing left either
    tests = Path(__file__).resolve().parents[1]
    proc = subprocess.run([sys.executable, "-c", f"import sys; sys.path.insert(0, {str(tests)!r}); import conftest"],
                          env=env, capture_output=True, text=True, timeout=300, check=False)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert sorted(p.name for p in tmp.iterdir() if not p.name.startswith("pytest-of-")) == []
