"""Issue 44: OpenVINO leaves the thread's alternate signal stack as it found it, so DataLoader
workers forked after OpenVINO ran (and the SIGCHLD their exit sends) no longer kill the process.

OpenVINO's CPU plugin gives the thread that makes a plugin or a compiled model a signal stack of its
own and sets the saved one back when that object goes; two compiled models freed first-first left
the thread on an unmapped stack, and the next signal Python handles (torch's SIGCHLD handler)
ended in SIGSEGV (si_code SI_KERNEL). See denoiser/inference/sigstack.py."""

from __future__ import annotations

import gc
import mmap
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from denoiser.inference import sigstack

REPO = Path(__file__).resolve().parents[2]
linux_only = pytest.mark.skipif(sigstack.current() is None, reason="sigaltstack is Linux only")


def mapped(address: int, size: int = 1) -> bool:
    """Whether ``[address, address + size)`` lies in this process's mappings (``/proc/self/maps``)."""
    try:
        with open("/proc/self/maps") as maps:
            for line in maps:
                lo, _, hi = line.split(" ", 1)[0].partition("-")
                if int(lo, 16) <= address and address + size <= int(hi, 16):
                    return True
    except OSError:
        return True  # cannot tell: assume it is
    return False


def own_stack(size: int = 1 << 16):
    """An alternate signal stack this test owns (mmap'd, kept alive by the returned buffer)."""
    import ctypes

    buf = mmap.mmap(-1, size)
    address = ctypes.addressof(ctypes.c_char.from_buffer(buf))
    return buf, sigstack.SignalStack(address, 0, size)


@linux_only
def test_kept_gives_back_the_stack_a_block_changed():
    before = sigstack.current()
    buf, mine = own_stack()
    try:
        with sigstack.kept():
            sigstack.install(mine)
            assert sigstack.current() == mine
        assert sigstack.current() == before
        sigstack.install(mine)  # nested blocks: each gives back what it found
        with sigstack.kept():
            with sigstack.kept():
                sigstack.install(sigstack.SignalStack(0, sigstack.SS_DISABLE, 0))
            assert sigstack.current() == mine
        assert mapped(mine.address, mine.size) and not mapped(8, 1)
    finally:
        sigstack.install(before)
    buf.close()


def openvino_steppers():
    """Two OpenVINO steppers of a tiny network, stepped once each: f32 and bf16 where the CPU has
    bf16, else two f32 (two compiled models are what it takes)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")
    from denoiser.configs import build_net, compose_net_config
    from denoiser.frames import random_frame
    from denoiser.inference.backends import load_backend

    net = build_net(compose_net_config("tiny", "student")).eval()
    frame = random_frame(1, 32, 32)
    names = ["openvino_f32", "openvino_bf16"]
    if load_backend("openvino_bf16").available():
        names[1] = "openvino_f32"
    steppers = []
    for name in names:
        stepper = load_backend(name).prepare(net, frame, 1)
        stepper.step(frame, None, True)
        steppers.append(stepper)
    return steppers


@linux_only
@pytest.mark.parametrize("start", ["none", "own"])
def test_openvino_leaves_the_signal_stack_as_it_found_it(start):
    """Two compiled models made, stepped and freed first-first: the thread's signal stack is the
    one it had before, and mapped (it was a freed one of OpenVINO's before the fix)."""
    before = sigstack.current()
    buf, mine = own_stack()
    if start == "own":  # as faulthandler (pytest's) would have one
        sigstack.install(mine)
    try:
        entered = sigstack.current()
        steppers = openvino_steppers()
        assert sigstack.current() == entered
        steppers.pop(0)
        gc.collect()
        assert sigstack.current() == entered
        steppers.pop(0)
        gc.collect()
        now = sigstack.current()
        assert now == entered, (now, entered)
        assert not now.enabled or mapped(now.address, now.size)
    finally:
        sigstack.install(before)
    buf.close()


#: the forced sequence of the issue, in its own process: OpenVINO f32 and bf16 (bench), then
#: fork-started persistent DataLoader workers over the frame cache, 10 times
FORCED = textwrap.dedent("""
    import faulthandler, sys
    from pathlib import Path
    faulthandler.enable()
    sys.path.insert(0, {tests!r})
    import conftest  # noqa: F401 - the session's folders (the extension's build cache), removed at exit
    from helpers.checkpoints import tiny_checkpoint
    from helpers.configs import compose_command
    from helpers.eval_data import write_dataset
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate
    from denoiser.conf import CONF_DIR
    from denoiser.commands.bench import run as bench
    from denoiser.data.synthetic import write_synthetic_sequence

    tmp = Path({tmp!r})
    write_dataset(tmp / "data", sequences=1, frames=4, size=32)
    ckpt = tiny_checkpoint(tmp / "student.ckpt")
    rows = bench(compose_command("bench", ["data=tiny", f"data.root={{tmp / 'data'}}", "threads=1", f"ckpt=[{{ckpt}}]",
                 "sizes=[[32,32]]", "repeats=2", "warmup=1", "use_backends=[openvino_f32,openvino_bf16]",
                 "quality=false", "baselines={{}}", f"out_dir={{tmp / 'bench'}}"]))
    root = tmp / "dm"
    for i in range(2):
        write_synthetic_sequence(root / "train" / f"t{{i}}", frames=4, width=32, height=32, seed=i)
    write_synthetic_sequence(root / "val" / "v0", frames=3, width=32, height=24, seed=10)
    for k in range(10):
        with initialize_config_dir(CONF_DIR, version_base="1.3"):
            cfg = compose(overrides=["+data=tiny", f"data.root={{root}}", f"data.cache_dir={{tmp}}/cache{{k}}",
                                     "data.num_workers=2", "data.persistent_workers=true", "data.window=4",
                                     "data.crop=null", "data.batch_size=1", "data.multiprocessing_context=fork"])
        loader = instantiate(cfg.data).train_dataloader()
        for _ in range(2):
            got = [b["color"].shape for b in loader]
        assert len(got) == 2
    print("survived")
""")


@pytest.mark.slow
@linux_only
def test_forked_workers_after_openvino_survive(tmp_path):
    """The issue's sequence (crashed 6 times in 6 on an Intel Xeon with AMX before the fix)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    script = tmp_path / "forced.py"
    script.write_text(FORCED.format(tests=str(REPO / "tests"), tmp=str(tmp_path)))
    proc = subprocess.run([sys.executable, str(script)], cwd=REPO, capture_output=True, text=True, timeout=600, check=False,
                          env={**os.environ, "DENOISER_CACHE": os.environ.get("DENOISER_CACHE", str(tmp_path))})
    assert proc.returncode == 0 and "survived" in proc.stdout, (proc.returncode, proc.stderr[-3000:])


@pytest.mark.slow
@linux_only
def test_train_with_an_openvino_time_objective_and_two_workers(tmp_path):
    """denoiser-train -m: two jobs in one process, each 20 steps with 2 persistent forked workers and
    an OpenVINO time objective after training (the second job forks after the first ran OpenVINO)."""
    pytest.importorskip("openvino", reason="openvino is not installed")
    from denoiser.data.synthetic import write_synthetic_sequence
    from denoiser.inference.backends import load_backend

    root = tmp_path / "data"
    for split, n in (("train", 2), ("val", 1)):
        for i in range(n):
            write_synthetic_sequence(root / split / f"s{i}", frames=4, width=32, height=32, seed=i)
    backend = "openvino_f32" if load_backend("openvino_bf16").available() else "openvino_bf16"
    argv = [sys.executable, "-m", "denoiser.commands.train", "-m", "data=tiny", f"data.root={root}", "net=tiny",
            "threads=1", "seed=0,1", "data.num_workers=2", "data.persistent_workers=true",
            "data.multiprocessing_context=fork", "data.window=2", "data.crop=16", "trainer.max_steps=20",
            "trainer.val_check_interval=10", "trainer.limit_val_batches=1", "trainer.enable_progress_bar=false",
            "callbacks.progress=null", "trainer.enable_model_summary=false", "model.image_interval=0",
            f"objectives.time={{size:[32,32],backend:{backend},warmup:1,repeats:2}}",
            f"hydra.sweep.dir={tmp_path / 'sweep'}", "hydra/job_logging=disabled", "hydra/hydra_logging=disabled"]
    proc = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=600, check=False,
                          env={**os.environ, "PYTHONFAULTHANDLER": "1"})
    assert proc.returncode == 0, (proc.returncode, proc.stderr[-3000:])
    metrics = sorted((tmp_path / "sweep").rglob("metrics.json"))
    assert len(metrics) == 2
    import json

    for path in metrics:
        got = json.loads(path.read_text())["metrics"]
        assert got["time/ms"] > 0 and got["val/psnr"] > 0, got
