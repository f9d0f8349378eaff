"""Bad input for every command that reads it: one clear line, non-zero exit, no traceback, no output.

Table of the combinations tested (command x bad input); each cell is one case below:

| bad input                              | train.py | distill | eval | denoise | export | render |
|----------------------------------------|----------|---------|------|---------|--------|--------|
| truncated EXR                          | x        |         | x    | x       |        |        |
| PNG renamed to .exr                    | x        |         | x    | x       |        |        |
| wrong channel names (no color.R/G/B)   | x        |         | x    | x       |        |        |
| frames of different sizes             | x        |         | x    | x       |        |        |
| missing frame in the middle            | x        |         | x    | x       |        |        |
| empty dataset / input directory        | x        |         | x    | x       |        |        |
| sequence.json disagrees with the frames| x        |         | x    | x       |        |        |
| checkpoint of another architecture     |          | x       | x    | x       | x      |        |
| a file that is not a checkpoint        |          |         | x    | x       | x      |        |
| config key that does not exist         | x        |         | x    | x       | x      | x      |
| group option that does not exist       | x        |         | x    | x       |        | x      |
| value interpolating a missing key      | x        |         | x    | x       | x      | x      |
| scene: unknown material / effect       |          |         |      |         |        | x      |

How the commands run: each command's real console entry point (``train.main``,
``denoiser.commands.evaluate:main``, ...) runs in its own child process with its own argv, stdout and
stderr, and the test reads that process's exit status and stderr. To keep the whole table
within the test budget on 2 cores, the children are forked from one driver subprocess per
command that has imported the command's module once (this file, run as a script); the forked
child then does exactly what the console script does. :func:`test_console_scripts` also runs
each installed console script (``.venv/bin/denoiser-*``, ``python train.py``) as a plain
subprocess on one bad input each, so the script wiring itself is covered.

Every data case puts a good sequence (``a_good``) before the bad one (``b_bad``), so a command
that writes output per sequence would have written something before it meets the bad input:
"no output left behind" is then a real check. The messages of every case are printed by
``pytest -s -k messages`` (:func:`test_print_messages`), for the report.
"""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: helpers also when run as a script (below)
from helpers.session import TEST_LEDGER

from denoiser.conf import CONF_DIR

REPO = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent

#: commands: console entry point (module:function) and argv[0]
ENTRIES = {
    "train": ("denoiser.commands.train:main", "denoiser-train"),
    "eval": ("denoiser.commands.evaluate:main", "denoiser-eval"),
    "denoise": ("denoiser.commands.denoise:main", "denoiser-denoise"),
    "export": ("denoiser.commands.export:main", "denoiser-export"),
    "render": ("denoiser.commands.render:main", "denoiser-render"),
}
#: modules the driver imports before forking (what every child would import anyway; saves time)
PRELOAD = {
    "train": ["lightning.pytorch", "lightning.pytorch.loggers", "torch.utils.tensorboard", "tensorboard",
              "denoiser.lit.supervised", "denoiser.lit.distill", "denoiser.data.datamodule", "denoiser.checkpoint"],
    "eval": ["denoiser.methods.baselines", "denoiser.data.dataset", "pyoidn"],
    "denoise": ["denoiser.data.dataset", "denoiser.checkpoint"],
    "export": ["onnx", "onnxruntime", "denoiser.checkpoint"],
    "render": ["mitsuba"],
}

# ----------------------------------------------------------------------------- bad data


def png_bytes(width: int = 4, height: int = 4) -> bytes:
    """A valid 8-bit RGB PNG (grey), built by hand (no image library needed)."""
    raw = b"".join(b"\x00" + b"\x80" * (3 * width) for _ in range(height))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def truncate(seq: Path) -> Path:
    f = seq / "frame_0001.exr"
    data = f.read_bytes()
    f.write_bytes(data[: len(data) // 2])
    return f


def png_as_exr(seq: Path) -> Path:
    f = seq / "frame_0001.exr"
    f.write_bytes(png_bytes())
    return f


def wrong_channels(seq: Path) -> Path:
    """color.R/G/B renamed to rgb.R/G/B in frame 1 (every other channel kept)."""
    from denoiser.data.exr import read_channels, write_channels

    f = seq / "frame_0001.exr"
    channels = read_channels(f)
    write_channels(f, {k.replace("color.", "rgb."): v for k, v in channels.items()})
    return f


def other_size(seq: Path) -> Path:
    """Frame 2 cropped to 16x16 (the others are 32x32)."""
    from denoiser.data.exr import read_channels, write_channels

    f = seq / "frame_0002.exr"
    write_channels(f, {k: v[:16, :16] for k, v in read_channels(f).items()})
    return f


def missing_frame(seq: Path) -> Path:
    f = seq / "frame_0002.exr"
    f.unlink()
    return seq


def json_disagrees(seq: Path) -> Path:
    """sequence.json says 6 frames; 4 are on disk."""
    f = seq / "sequence.json"
    data = json.loads(f.read_text())
    data["frames"] = 6
    data["cameras"] = data["cameras"] + data["cameras"][:2]
    f.write_text(json.dumps(data))
    return f


#: data case -> (mutation of the bad sequence, what the message must name)
DATA_CASES = {
    "truncated_exr": (truncate, "frame_0001.exr"),
    "png_as_exr": (png_as_exr, "frame_0001.exr"),
    "wrong_channels": (wrong_channels, "frame_0001.exr"),
    "frame_sizes": (other_size, "frame_0002.exr"),
    "missing_frame": (missing_frame, "b_bad"),
    "sequence_json": (json_disagrees, "sequence.json"),
}


#: data cases found only when the pixels are decoded (the data is indexed from headers)
READ_TIME = {"truncated_exr", "png_as_exr", "wrong_channels"}


def write_good(directory: Path, seed: int) -> None:
    from denoiser.data.synthetic import write_synthetic_sequence

    write_synthetic_sequence(directory, frames=4, width=32, height=32, seed=seed)


@pytest.fixture(scope="module")
def work(tmp_path_factory) -> Path:
    """Datasets (one per data case), checkpoints and scene files shared by all cases."""
    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config

    root = tmp_path_factory.mktemp("robust")
    for case, (mutate, _) in DATA_CASES.items():
        for split in ("train", "val", "test"):
            write_good(root / "data" / case / split / "a_good", seed=1)
        for split in ("train", "test"):
            write_good(root / "data" / case / split / "b_bad", seed=2)
            mutate(root / "data" / case / split / "b_bad")
        # denoise reads one directory of frames: the bad test sequence itself
    for split in ("train", "val", "test"):
        (root / "data" / "empty" / split).mkdir(parents=True)
    (root / "empty_input").mkdir()

    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(0)
    save_checkpoint(root / "good.ckpt", build_net(cfg), cfg)
    # another architecture: weights of net=tiny under a config whose U-Net is wider (the config
    # builds a network the weights do not fit), as after a config change between train and eval
    wider = dict(cfg, unet=dict(cfg["unet"], encoder=[16, 24, 32]))
    save_checkpoint(root / "other_arch.ckpt", build_net(cfg), wider)
    # a Lightning checkpoint of some other model: no denoiser weights under net.
    torch.save({"state_dict": {"backbone.fc.weight": torch.zeros(10, 4)}, "hyper_parameters": {"lr": 0.1},
                "global_step": 3, "epoch": 0}, root / "classifier.ckpt")
    (root / "notes.ckpt").write_text("these are my notes, not a checkpoint\n")

    scenes = root / "search" / "scene"
    scenes.mkdir(parents=True)
    cornell = (Path(CONF_DIR) / "scene" / "cornell.yaml").read_text()
    (scenes / "bad_effect.yaml").write_text(
        cornell.replace("name: cornell", "name: bad_effect").replace("camera_motion]", "camera_motion, wobble]"))
    bad_mat = cornell.replace("name: cornell", "name: bad_material").replace(
        "material: {type: diffuse, color: {uniform: [[0.5", "material: {type: velvet, color: {uniform: [[0.5")
    assert "velvet" in bad_mat and "wobble" in (scenes / "bad_effect.yaml").read_text()
    (scenes / "bad_material.yaml").write_text(bad_mat)
    return root


# ----------------------------------------------------------------------------- cases

#: quiet, tiny training runs
TRAIN = ["data=tiny", "net=tiny", "threads=1", "trainer.enable_progress_bar=false", "callbacks.progress=null",
         "trainer.enable_model_summary=false", "trainer.max_steps=2", "trainer.val_check_interval=2",
         "trainer.limit_val_batches=1"]
#: evaluation with the noisy-input baseline and one checkpoint (no OIDN: faster)
EVAL = ["data=tiny", "~baselines.oidn_fast", "~baselines.oidn_balanced", "~baselines.oidn_high",
        "metrics=[psnr]", "images.size=16", "purpose=test-suite", f"ledger={TEST_LEDGER}"]


def cases(work: Path, command: str) -> dict[str, dict]:
    """``{case: {"args": argv, "names": text the error line must contain, "outputs": [paths]}}``."""
    data = work / "data"
    out = work / "out" / command
    good = work / "good.ckpt"
    c: dict[str, dict] = {}

    def add(name, args, names, outputs, hydra_error=False, env=None):
        c[name] = {"args": [str(a) for a in args], "names": names, "outputs": [str(o) for o in outputs],
                   "hydra_error": hydra_error, "env": env or {}}

    if command == "train":
        def train(name, root, names, *extra, hydra_error=False):
            run = out / name
            add(name, [*TRAIN, f"data.root={root}", f"hydra.run.dir={run}", *extra], names,
                [run / "checkpoints", run / "tb"], hydra_error)

        for case, (_, names) in DATA_CASES.items():
            train(case, data / case, names)
            if case in READ_TIME:  # met in the first batch, after the logger started: only logs remain
                c[case]["outputs"] = [str(out / case / "checkpoints")]
        train("empty_dataset", data / "empty", "empty/train")
        train("unknown_key", data / "truncated_exr", "trainer.max_stpes", "trainer.max_stpes=3", hydra_error=True)
        train("unknown_option", data / "truncated_exr", "net/huge", "net=huge", hydra_error=True)
        train("missing_interpolation_key", "${no_such_key}", "data: Interpolation key 'no_such_key'")
        train("distill_teacher_other_arch", data / "truncated_exr", "other_arch.ckpt", "model=distill", "net=tiny",
              f"model.teacher_ckpt={work / 'other_arch.ckpt'}")
        train("distill_teacher_classifier", data / "truncated_exr", "classifier.ckpt", "model=distill", "net=tiny",
              f"model.teacher_ckpt={work / 'classifier.ckpt'}")
    elif command == "eval":
        def ev(name, root, names, *extra, ckpt=good, hydra_error=False):
            dest = out / name
            add(name, [*EVAL, f"data.root={root}", f"ckpt={ckpt}", f"out_dir={dest}", f"hydra.run.dir={dest}",
                       *extra], names, [dest / "metrics.csv", dest / "metrics.md", dest / "images", dest / "exr"],
                hydra_error)

        for case, (_, names) in DATA_CASES.items():
            ev(case, data / case, names, "save_exr=true")
        ev("empty_dataset", data / "empty", "empty/test")
        ev("other_arch_ckpt", data / "truncated_exr", "other_arch.ckpt", ckpt=work / "other_arch.ckpt")
        ev("classifier_ckpt", data / "truncated_exr", "classifier.ckpt", ckpt=work / "classifier.ckpt")
        ev("not_a_ckpt", data / "truncated_exr", "notes.ckpt", ckpt=work / "notes.ckpt")
        ev("unknown_key", data / "truncated_exr", "warmpu", "warmpu=3", hydra_error=True)
        ev("unknown_option", data / "truncated_exr", "layout/exotic", "layout=exotic", hydra_error=True)
        ev("missing_interpolation_key", data / "truncated_exr", "warmup: Interpolation key 'no_such_key'",
           "warmup=${no_such_key}")
    elif command == "denoise":
        def dn(name, src, names, *extra, ckpt=good, hydra_error=False):
            dest = out / name
            add(name, [f"ckpt={ckpt}", f"input={src}", f"output={dest}", f"hydra.run.dir={out / (name + '_run')}",
                       *extra], names, [dest], hydra_error)

        for case, (_, names) in DATA_CASES.items():
            dn(case, data / case / "test" / "b_bad", names)
        dn("empty_input", work / "empty_input", "empty_input")
        src = data / "truncated_exr" / "test" / "a_good"
        dn("other_arch_ckpt", src, "other_arch.ckpt", ckpt=work / "other_arch.ckpt")
        dn("classifier_ckpt", src, "classifier.ckpt", ckpt=work / "classifier.ckpt")
        dn("not_a_ckpt", src, "notes.ckpt", ckpt=work / "notes.ckpt")
        dn("unknown_key", src, "outptu", "outptu=x", hydra_error=True)
        dn("unknown_option", src, "layout", "layout=exotic", hydra_error=True)
        dn("missing_interpolation_key", src, "threads: Interpolation key 'no_such_key'", "threads=${no_such_key}")
    elif command == "export":
        def ex(name, ckpt, names, *extra, hydra_error=False):
            dest = out / f"{name}.onnx"
            add(name, [f"ckpt={ckpt}", f"out={dest}", *extra], names, [dest, dest.parent], hydra_error)

        ex("other_arch_ckpt", work / "other_arch.ckpt", "other_arch.ckpt")
        ex("classifier_ckpt", work / "classifier.ckpt", "classifier.ckpt")
        ex("not_a_ckpt", work / "notes.ckpt", "notes.ckpt")
        ex("unknown_key", good, "opste", "opste=13", hydra_error=True)
        ex("missing_interpolation_key", "${no_such_key}", "ckpt: Interpolation key 'no_such_key'")
    elif command == "render":
        def rn(name, names, *extra, hydra_error=False):
            dest = out / name
            add(name, [f"root={dest}", "frames=2", "width=16", "height=16", "spp=1", "ref_spp=2", "variant=scalar_rgb",
                       f"hydra.searchpath=[file://{work / 'search'}]", *extra], names, [dest], hydra_error)

        rn("unknown_effect", "wobble", "scene=bad_effect")
        rn("unknown_material", "velvet", "scene=bad_material")
        rn("unknown_key", "sp", "sp=4", hydra_error=True)
        rn("unknown_option", "scene/atlantis", "scene=atlantis", hydra_error=True)
        rn("missing_interpolation_key", "frames: Interpolation key 'no_such_key'", "frames=${no_such_key}")
        rn("debug_trace", "wobble", "scene=bad_effect", hydra_error=False)
        c["debug_trace"]["env"] = {"DENOISER_DEBUG": "1"}
    return c


# ----------------------------------------------------------------------------- driver


def drive(entry: str, prog: str, cases_file: Path, out_file: Path, preload: list[str]) -> None:
    """Run every case of ``cases_file`` in a forked child that calls the console entry ``entry``.

    Runs as ``python tests/commands/test_robust_inputs.py <entry> <prog> <cases.json> <results.json> [modules]``. The
    parent only imports the command's module (no torch work, so forking is safe); each child gets
    its own argv, environment, stdout and stderr files and exits like the console script would.
    """
    import importlib
    import traceback

    sys.path.insert(0, str(REPO))
    module, func = entry.split(":")
    main = getattr(importlib.import_module(module), func)
    for name in preload:
        try:
            importlib.import_module(name)
        except ImportError:
            pass
    cases_ = json.loads(cases_file.read_text())
    results = {}
    for name, case in cases_.items():
        err = out_file.with_name(f"{out_file.stem}.{name}.stderr")
        out = out_file.with_name(f"{out_file.stem}.{name}.stdout")
        pid = os.fork()
        if pid == 0:  # child: behave as `<prog> <args>` would
            code = 1
            try:
                os.dup2(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 1)
                os.dup2(os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 2)
                os.environ.update(case["env"])
                sys.argv = [prog, *case["args"]]
                main()
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
            except BaseException:  # noqa: BLE001 - what the interpreter does with an uncaught exception
                traceback.print_exc()
                code = 1
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        results[name] = {"returncode": os.waitstatus_to_exitcode(status), "stderr": err.read_text(),
                         "stdout": out.read_text()}
    out_file.write_text(json.dumps(results, indent=1))


def run_command(work: Path, command: str) -> dict[str, dict]:
    """All cases of ``command``: ``{case: {"returncode", "stderr", "stdout", **case}}``."""
    entry, prog = ENTRIES[command]
    spec = cases(work, command)
    cases_file = work / f"cases_{command}.json"
    out_file = work / f"results_{command}.json"
    cases_file.write_text(json.dumps(spec))
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("DENOISER_DEBUG", None)
    proc = subprocess.run([sys.executable, __file__, entry, prog, str(cases_file), str(out_file),
                           *PRELOAD.get(command, [])], check=False, cwd=work,
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    results = json.loads(out_file.read_text())
    return {k: {**spec[k], **v} for k, v in results.items()}


_results: dict[str, dict] = {}


@pytest.fixture(scope="module")
def results(work):
    def get(command: str) -> dict[str, dict]:
        if command not in _results:
            _results[command] = run_command(work, command)
        return _results[command]

    return get


def last_line(text: str) -> str:
    lines = [line for line in text.strip().splitlines() if line.strip()]
    return lines[-1] if lines else ""


def check_case(result: dict) -> None:
    """The contract of a bad input: exit != 0, no traceback, one line naming the file/key, no output."""
    stderr = result["stderr"]
    assert result["returncode"] != 0, f"exit 0 on bad input; stderr: {stderr[-2000:]}"
    if result["env"].get("DENOISER_DEBUG"):
        assert "Traceback" in stderr, "DENOISER_DEBUG=1 must show the full traceback"
    else:
        assert "Traceback" not in stderr, stderr[-3000:]
        if result["hydra_error"]:
            # Hydra's own message: short, no traceback; its first line names the key/option
            assert result["names"] in stderr.strip().splitlines()[0], stderr
            assert result["returncode"] == 1
        else:
            line = last_line(stderr)
            assert line.startswith("error: "), stderr[-2000:]
            assert result["names"] in line, f"error line does not name {result['names']!r}: {line}"
            assert result["returncode"] == 2
    for path in map(Path, result["outputs"]):
        if path.is_dir():
            left = [p for p in path.rglob("*") if p.is_file()]
            assert not left, f"output left behind: {left}"
        else:
            assert not path.exists(), f"output left behind: {path}"


def case_ids(command: str) -> list[str]:
    return list(cases(Path("/nonexistent"), command))


@pytest.mark.slow
@pytest.mark.parametrize("case", case_ids("train"))
def test_train(results, case):
    check_case(results("train")[case])


@pytest.mark.parametrize("case", case_ids("eval"))
def test_eval(results, case):
    check_case(results("eval")[case])


@pytest.mark.parametrize("case", case_ids("denoise"))
def test_denoise(results, case):
    check_case(results("denoise")[case])


@pytest.mark.parametrize("case", case_ids("export"))
def test_export(results, case):
    check_case(results("export")[case])


@pytest.mark.parametrize("case", case_ids("render"))
def test_render(results, case):
    check_case(results("render")[case])


def test_console_scripts(work):
    """The installed console scripts themselves: one bad input each, plain subprocesses (denoiser-eval's
    entry point is the same ``hydra_command`` wrapper; train.py runs as a script in test_crash_train)."""
    runs = {
        "denoiser-export": [str(BIN / "denoiser-export"), f"ckpt={work / 'notes.ckpt'}",
                            f"out={work / 'cs_export' / 'x.onnx'}"],
        "denoiser-render": [str(BIN / "denoiser-render"), "scene=bad_effect", f"root={work / 'cs_render'}",
                            f"hydra.searchpath=[file://{work / 'search'}]"],
        "denoiser-denoise": [str(BIN / "denoiser-denoise"), f"ckpt={work / 'other_arch.ckpt'}",
                             f"input={work / 'data' / 'truncated_exr' / 'test' / 'a_good'}",
                             f"output={work / 'cs_denoise'}", f"hydra.run.dir={work / 'cs_denoise_run'}"],
    }
    names = {"denoiser-export": "notes.ckpt", "denoiser-render": "wobble",
             "denoiser-denoise": "other_arch.ckpt"}
    env = {k: v for k, v in os.environ.items() if k != "DENOISER_DEBUG"}
    procs = {script: subprocess.Popen(argv, cwd=work, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                      text=True) for script, argv in runs.items()}  # at once: start-up overlaps
    for script, proc in procs.items():
        _, stderr = proc.communicate(timeout=300)
        assert proc.returncode == 2, (script, stderr[-2000:])
        assert "Traceback" not in stderr, (script, stderr[-2000:])
        assert last_line(stderr).startswith("error: ") and names[script] in last_line(stderr), (script, stderr[-2000:])
    assert not any((work / d).exists() for d in ("cs_export", "cs_render", "cs_denoise"))


def test_print_messages(results, capsys):
    """Print every case's exit code and error line (``pytest -s -k messages`` for the report)."""
    lines = []
    for command in ENTRIES:
        for name, r in results(command).items():
            msg = r["stderr"].strip().splitlines()[0] if r["hydra_error"] else last_line(r["stderr"])
            lines.append(f"| {command} | {name} | {r['returncode']} | `{msg}` |")
    with capsys.disabled():
        print("\n" + "\n".join(lines))
    assert len(lines) == sum(len(case_ids(c)) for c in ENTRIES)


if __name__ == "__main__":
    drive(sys.argv[1], sys.argv[2], Path(sys.argv[3]), Path(sys.argv[4]), sys.argv[5:])
