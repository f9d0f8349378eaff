"""The release Cycles kinds of scripts/blender_sequences.py (issue 62): each kind builds and renders
(32x32, 2 frames, 1-2 spp) into files ``layout=blender`` reads, its scene is drawn from the seed,
``--ref-check``'s noise floor is the project's PSNR, the unlabeled split is noisy only, a stopped
sequence resumes keeping its frames, and the release splits' seeds are disjoint from each other and from every earlier Cycles split."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.blender import CHECKOUT, blender_python_or_skip

from denoiser.configs import load_layout
from denoiser.data import exr
from denoiser.metrics import psnr

SCRIPT = CHECKOUT / "scripts" / "blender_sequences.py"
#: seeds of every Cycles split before the release: val, the retired test split (issue 49), test
EARLIER_SEEDS = {101, 102, 103, 201, 202, 203, 204, 205, 206, 301, 302, 303, 304, 305, 306}

#: prints the script's split tables as JSON (``-c TABLES``; ``-c TABLES draw``: with what two builds of
#: seed 7 and one of seed 8 of each kind drew)
TABLES = """
import json, sys
draw = sys.argv[1:] == ["draw"]
sys.argv = ["x"]
sys.path.insert(0, "scripts")
import blender_sequences as b
drawn = {}
for kind in (b.RELEASE_KINDS + b.RESERVED_KINDS) if draw else ():
    runs = []
    for seed in (7, 7, 8):
        b.reset_scene(32, 32, 1)
        runs.append(b.build(f"{kind}_{seed}", 2, 32))
    drawn[kind] = runs
print("TABLES" + json.dumps({"splits": b.RELEASE_SPLITS, "kinds": b.RELEASE_KINDS, "reserved": b.RESERVED_KINDS,
                             "noisy_only": b.RELEASE_NOISY_ONLY, "large": sorted(b.RELEASE_LARGE),
                             "moving": b.MOVING_SEEDS, "existing": b.SPLIT_SEQUENCES, "drawn": drawn}))
"""


def run(python: Path, *args: str) -> str:
    proc = subprocess.run([str(python), *args], cwd=CHECKOUT, capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def read_tables(*args: str) -> dict:
    out = run(blender_python_or_skip(), "-c", TABLES, *args)
    return json.loads(out[out.index("TABLES") + len("TABLES"):].splitlines()[0])


@pytest.fixture(scope="module")
def tables():
    return read_tables()


def seed_of(name: str) -> int:
    return int(name.rpartition("_")[2])


def kind_of(name: str) -> str:
    return name.rpartition("_")[0]


def test_release_splits_are_disjoint_by_seed_and_from_every_earlier_split(tables):
    splits = tables["splits"]
    assert len(splits["train"]) >= 40 and len(splits["val"]) >= 8 and len(splits["test"]) >= 12
    assert len(splits["unlabeled"]) >= 12 and splits["unlabeled"] and tables["noisy_only"] == ["unlabeled"]
    seen: dict[int, str] = {}
    for split, names in splits.items():
        for name in names:
            seed = seed_of(name)
            assert seed not in seen, f"seed {seed} in {split} and {seen[seed]}"
            assert seed not in EARLIER_SEEDS, f"{name} reuses an earlier Cycles seed"
            seen[seed] = split
    earlier = {s for v in tables["moving"].values() for s in v} | {seed_of(n) for v in tables["existing"].values()
                                                                   for n in v}
    assert earlier <= EARLIER_SEEDS and not earlier & set(seen)
    kinds, reserved = set(tables["kinds"]), set(tables["reserved"])
    assert len(reserved) >= 2 and not kinds & reserved
    for split in ("train", "val", "test", "unlabeled"):          # training kinds only, and all of them
        assert {kind_of(n) for n in splits[split]} == kinds, split
    assert {kind_of(n) for n in splits["reserved"]} == reserved
    assert {kind_of(n) for n in splits["timing"]} == kinds | reserved
    assert set(tables["large"]) <= set(splits["train"]) | set(splits["val"])


@pytest.mark.slow
def test_each_kind_is_drawn_from_its_seed():
    drawn = read_tables("draw")["drawn"]
    assert len(drawn) >= 9
    for kind, (a, again, other) in drawn.items():
        assert a["kind"] == kind and a["seed"] == 7 and "camera" in a, kind
        assert a == again, f"{kind}: one seed drew two scenes"
        assert a != {**other, "seed": 7}, f"{kind}: seeds 7 and 8 drew the same scene"


@pytest.mark.slow
def test_every_kind_renders_into_the_blender_layout_and_the_noise_floor_is_the_projects_psnr(tables, tmp_path):
    python = blender_python_or_skip()
    layout = load_layout("blender")
    names = [f"{k}_{s}" for s, k in enumerate(tables["kinds"] + tables["reserved"], 9001)]
    common = ["--root", str(tmp_path), "--set", "release", "--size", "32", "--frames", "2", "--spp", "1"]
    run(python, str(SCRIPT), *common, "--split", "kinds", "--ref-spp", "2", "--sequences", *names[1:])
    run(python, str(SCRIPT), *common, "--split", "kinds", "--ref-spp", "4", "--ref-check", "--sequences", names[0])
    for name in names:
        seq = tmp_path / "kinds" / name
        info = json.loads((seq / "render.json").read_text())
        assert info["scene"]["kind"] == kind_of(name) and info["builder"] == f"{kind_of(name)} v1"
        assert info["cpu_seconds"]["reference"] > 0
        source = layout.open_sequence(seq)
        assert {"color", "albedo", "normal", "depth", "motion"} <= set(source.buffers), name
        assert "reference" in source.files and (source.meta.width, source.meta.height) == (32, 32)
        for path in source.files["reference"]:
            rgb = np.stack([exr.read_channels(path)[f"ViewLayer.Combined.{c}"] for c in "RGB"])
            assert np.isfinite(rgb).all() and rgb.mean() > 1e-3, f"{path}: black or non-finite"

    seq = tmp_path / "kinds" / names[0]
    floor = json.loads((seq / "render.json").read_text())["noise_floor"]

    def frame(path: Path) -> torch.Tensor:
        channels = exr.read_channels(path)
        return torch.from_numpy(np.stack([channels[f"ViewLayer.Combined.{c}"] for c in "RGB"]))[None]

    ours = [float(psnr(frame(seq / "reference" / f"{f:04d}.exr"), frame(seq / "reference_check" / f"{f:04d}.exr")))
            for f in (1, 2)]
    assert floor["per_frame"] == pytest.approx({str(f): v for f, v in zip((1, 2), ours)}, abs=0.01)
    assert floor["psnr_db"] == pytest.approx(sum(ours) / 2, abs=0.01)

    # the unlabeled split: noisy only, read as unlabeled by the layout
    run(python, str(SCRIPT), *common, "--split", "unlabeled", "--sequences", names[1])
    seq = tmp_path / "unlabeled" / names[1]
    assert not (seq / "reference").exists() and "reference" not in json.loads((seq / "render.json").read_text())
    assert not layout.open_sequence(seq).labeled

    # a stopped run (render.pending.json holds its settings) resumes: frames on disk are kept
    info = json.loads((seq / "render.json").read_text())
    wanted = {k: info[k] for k in ("blender", "width", "height", "frames", "noisy", "builder")}
    (seq / "render.pending.json").write_text(json.dumps(wanted))
    (seq / "render.json").unlink()
    (seq / "noisy" / "0002.exr").unlink()
    kept = (seq / "noisy" / "0001.exr").stat().st_mtime_ns
    run(python, str(SCRIPT), *common, "--split", "unlabeled", "--sequences", names[1])
    info = json.loads((seq / "render.json").read_text())
    assert info["resumed"] and len(info["seconds"]["noisy"]) == 1 and (seq / "noisy" / "0002.exr").exists()
    assert (seq / "noisy" / "0001.exr").stat().st_mtime_ns == kept and not (seq / "render.pending.json").exists()
