"""The backend config group conf/backends/: every option instantiates, the commands accept exactly
its names, and a backend added the README's way (a class plus one YAML) is selectable by
denoiser-bench, denoiser-denoise, denoiser-pareto and denoiser-train's time objective with no other edit."""

import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command
from omegaconf import OmegaConf

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from helpers.eval_data import write_dataset, write_sequence

from denoiser.conf import CONF_DIR
from denoiser.data.exr import read_channels
from denoiser.errors import ConfigError
from denoiser.inference import backends

GROUP_FILES = sorted(p.stem for p in (Path(CONF_DIR) / "backends").glob("*.yaml"))
VENV_BIN = Path(sys.executable).parent


def listed(message: str) -> list[str]:
    """The names an error line offers: ``...is not one of a, b, c`` (up to a parenthesis or the end)."""
    return sorted(n.strip() for n in re.search(r"is not one of ([\w, ]+)", message)[1].split(","))


def test_every_option_instantiates():
    """Each YAML of conf/backends/ is a backend: label, device, dtype, available() (None or a reason here)."""
    assert GROUP_FILES and backends.backend_names() == GROUP_FILES
    for name in GROUP_FILES:
        b = backends.load_backend(name)
        assert isinstance(b.label, str) and b.label and b.dtype in ("fp32", "bf16", "fp16"), name
        assert isinstance(b.device, str) and callable(b.prepare), name
        reason = b.available()
        assert reason is None or isinstance(reason, str), name
        if isinstance(b, backends.OpenVinoBackend):
            assert b.label.endswith((" (fused)", " (plain)")), b.label  # which graph ran, in every row


def test_commands_accept_exactly_the_group():
    """bench, denoise, pareto and the train objective name the same options when one is unknown."""
    from denoiser.commands.denoise import make_backend
    from denoiser.commands.pareto import select_backend
    from denoiser.commands.train import measure_time
    from denoiser.report.bench_timing import load_backends

    errors = []
    for call in (lambda: load_backends(OmegaConf.create({"use_backends": ["eager", "tensorrt"]})),
                 lambda: make_backend("tensorrt", None, torch.device("cpu")),
                 lambda: select_backend(OmegaConf.create({"backend": "tensorrt"})),
                 lambda: measure_time(OmegaConf.create({"objectives": {"time": {"size": [8, 8], "backend": "tensorrt"}}}),
                                      None)):
        with pytest.raises(ConfigError) as info:
            call()
        errors.append(str(info.value))
    assert [m.split(":")[0] for m in errors] == ["use_backends", "backend", "backend", "objectives.time.backend"]
    assert all("\n" not in m and "'tensorrt'" in m and listed(m) == GROUP_FILES for m in errors), errors
    for config in ("bench", "pareto"):  # no inline backends left: names only
        assert "backends" not in compose_command(config, ["sweep_dir=x"] if config == "pareto" else [])
    bench = compose_command("bench", [])
    assert set(bench.use_backends) <= set(GROUP_FILES)
    assert set(backends.PRECISION_ARGUMENT) <= set(GROUP_FILES)
    assert {o for options in backends.PRECISION_OPTIONS.values() for o in options.values()} <= set(GROUP_FILES)


def test_bench_networks_variants_are_backends():
    """bench_networks' variants are group options, except the weight-format experiments, none a duplicate."""
    from denoiser.commands.tools import bench_networks

    assert set(bench_networks.BACKEND_VARIANTS) <= set(GROUP_FILES)
    others = set(bench_networks.VARIANTS) - set(bench_networks.BACKEND_VARIANTS)
    assert others == {"channels_last_bf16_weights", "channels_last_bf16_weights_compiled"}
    assert not others & set(GROUP_FILES)
    assert all("Not a backend" in bench_networks.VARIANTS[v].__doc__ for v in others)


FAKE_MODULE = '''
from denoiser.inference.backends import TorchBackend


class FakeBackend(TorchBackend):
    """Eager PyTorch under another name; counts what it prepared."""

    prepared = 0

    def __init__(self, label="fake eager", device="cpu", shout=False):
        super().__init__(label, device=device)
        self.shout = shout

    def prepare(self, net, example, threads):
        type(self).prepared += 1
        return super().prepare(net, example, threads)
'''


@pytest.fixture()
def fake_backend(tmp_path, monkeypatch):
    """The README's recipe in a temporary place: a class in an importable module and one YAML in a
    directory holding ``backends/fake.yaml``, added to the group's search path."""
    mods = tmp_path / "mods"
    mods.mkdir()
    (mods / "fake_backend_mod.py").write_text(textwrap.dedent(FAKE_MODULE))
    search = tmp_path / "search"
    (search / "backends").mkdir(parents=True)
    (search / "backends" / "fake.yaml").write_text("_target_: fake_backend_mod.FakeBackend\nlabel: fake eager\n"
                                                  "shout: true\n")
    monkeypatch.syspath_prepend(str(mods))
    monkeypatch.setattr(backends, "SEARCHPATH", [f"file://{search}"])
    import fake_backend_mod

    fake_backend_mod.FakeBackend.prepared = 0
    return fake_backend_mod.FakeBackend, mods, search


def test_a_new_backend_is_selectable_everywhere(fake_backend, tmp_path):
    from denoiser.commands.bench import run as bench
    from denoiser.commands.denoise import make_backend
    from denoiser.commands.denoise import run as denoise
    from denoiser.commands.pareto import select_backend
    from denoiser.commands.train import measure_time
    from denoiser.configs import build_net, compose_net_config

    fake, _, _ = fake_backend
    assert backends.backend_names() == sorted([*GROUP_FILES, "fake"])
    assert isinstance(backends.load_backend("fake"), fake) and backends.load_backend("fake").shout is True

    # denoiser-bench use_backends=[eager,fake]
    write_dataset(tmp_path / "data", sequences=1, frames=2, size=16)
    ckpt = tiny_checkpoint(tmp_path / "student.ckpt")
    rows = bench(compose_command("bench", ["data=tiny", f"data.root={tmp_path / 'data'}", "threads=1", f"ckpt=[{ckpt}]",
                                           "sizes=[[16,16]]", "repeats=1", "warmup=0", "use_backends=[eager,fake]",
                                           "baselines={}", "quality=false", f"out_dir={tmp_path / 'bench'}"]))
    fake_rows = [r for r in rows if r["backend"] == "fake eager"]
    assert len(fake_rows) == 1 and fake_rows[0]["status"] == "ok" and fake_rows[0]["ms_median"] > 0
    assert fake.prepared == 1

    # denoiser-denoise backend=fake: the frames of eager
    seq = write_sequence(tmp_path / "shot", frames=2, size=(16, 16), seed=1)
    assert isinstance(make_backend("fake", None, torch.device("cpu"))[1], fake)
    for name in ("eager", "fake"):
        denoise(compose_command("denoise", [f"ckpt={ckpt}", f"input={seq}", f"output={tmp_path / name}",
                                            f"backend={name}", "write=rgb", "threads=1"]))
    assert fake.prepared == 2
    for t in range(2):
        a, b = (read_channels(tmp_path / name / f"frame_{t:04d}.exr") for name in ("eager", "fake"))
        assert all(np.array_equal(a[c], b[c]) for c in "RGB")

    # denoiser-pareto backend=fake
    assert isinstance(select_backend(compose_command("pareto", ["sweep_dir=x", "backend=fake"])), fake)

    # denoiser-train objectives.time.backend=fake
    net = build_net(compose_net_config("tiny")).eval()
    spec = {"objectives": {"time": {"size": [16, 16], "backend": "fake", "warmup": 0, "repeats": 1}}}
    assert measure_time(OmegaConf.create(spec), net)["time/ms"] > 0
    assert fake.prepared == 3


def test_a_new_backend_through_hydra_searchpath_on_the_command_line(fake_backend, tmp_path):
    """A console script: hydra.searchpath on its command line adds the option (no monkeypatching in it)."""
    _, mods, search = fake_backend
    seq = write_sequence(tmp_path / "shot", frames=2, size=(16, 16), seed=2)
    ckpt = tiny_checkpoint(tmp_path / "s.ckpt")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(mods), os.environ.get("PYTHONPATH", "")]),
           "OMP_NUM_THREADS": "1"}
    proc = subprocess.run([str(VENV_BIN / "denoiser-denoise"), f"ckpt={ckpt}", f"input={seq}",
                           f"output={tmp_path / 'out'}", "backend=fake", "threads=1", "write=rgb",
                           f"hydra.searchpath=[file://{search}]", f"hydra.run.dir={tmp_path / 'run'}"],
                          check=False, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert (tmp_path / "out" / "frame_0001.exr").exists()
    proc = subprocess.run([str(VENV_BIN / "denoiser-denoise"), f"ckpt={ckpt}", f"input={seq}",
                           f"output={tmp_path / 'out2'}", "backend=fake", f"hydra.run.dir={tmp_path / 'run2'}"],
                          check=False, capture_output=True, text=True, env=env, timeout=300)
    assert proc.returncode != 0 and "backend: 'fake' is not one of" in proc.stderr


def test_summaries_find_the_labels_with_the_graph():
    """ablation_summary's configured labels (openvino f32) find bench.csv's (openvino f32 (fused))."""
    from denoiser.commands.tools.ablation_summary import bench_label

    labels = {"openvino f32 (fused)", "openvino bf16 (plain)", "eager fp32"}
    assert [bench_label(b, labels) for b in ("openvino f32", "openvino bf16", "eager fp32", "onnxruntime")] == [
        "openvino f32 (fused)", "openvino bf16 (plain)", "eager fp32", "onnxruntime"]


def test_gpu_check_rows_name_options_of_the_group():
    """make gpu-check's rows (conf/gpu_check.yaml) are options of the group with argument overrides."""
    rows = OmegaConf.to_container(compose_command("gpu_check", []).inference.rows)
    for spec in rows:
        spec = {k: v for k, v in spec.items() if k not in ("method", "net", "target_ms")}
        backend = backends.load_backend(spec.pop("backend"), "inference.rows", **spec)
        assert backend.label == spec.get("label", backend.label) and backend.device.startswith("cuda")
