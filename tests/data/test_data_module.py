"""SequenceDataModule from the Hydra configs: batches, unlabeled mixing, cache, NaN/Inf report."""

from __future__ import annotations

import logging
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from denoiser.buffers import FRAME_INPUTS
from denoiser.conf import CONF_DIR
from denoiser.data import exr
from denoiser.data.cache import FrameCache
from denoiser.data.datamodule import SequenceDataModule
from denoiser.data.dataset import index_split
from denoiser.data.layouts import NativeLayout
from denoiser.data.reader import FrameReader
from denoiser.data.synthetic import write_synthetic_sequence
from denoiser.errors import ConfigError, UserError

DATA_OPTIONS = sorted(p.stem for p in (Path(CONF_DIR) / "data").glob("*.yaml"))
LAYOUT_OPTIONS = sorted(p.stem for p in (Path(CONF_DIR) / "layout").glob("*.yaml"))
REQUIRED_KEYS = {"root", "layout", "window", "crop", "batch_size", "num_workers", "persistent_workers",
                 "pin_memory", "multiprocessing_context", "cache_dir", "augment", "use_unlabeled", "unlabeled_ratio", "val_split",
                 "test_split"}


@pytest.fixture(scope="module")
def root(tmp_path_factory):
    root = tmp_path_factory.mktemp("dm")
    for i in range(2):
        write_synthetic_sequence(root / "train" / f"t{i}", frames=4, width=32, height=32, seed=i, cuts=[2] if i else [])
    write_synthetic_sequence(root / "val" / "v0", frames=3, width=32, height=24, seed=10)
    write_synthetic_sequence(root / "test" / "x0", frames=2, width=32, height=32, seed=11)
    write_synthetic_sequence(root / "unlabeled" / "u0", frames=4, width=32, height=32, seed=12, labeled=False)
    return root


def make(root, *overrides, option="tiny"):
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(overrides=[f"+data={option}", f"data.root={root}", *overrides])
    dm = instantiate(cfg.data)
    assert isinstance(dm, SequenceDataModule)
    return dm


@pytest.mark.parametrize("option", DATA_OPTIONS)
@pytest.mark.parametrize("layout", LAYOUT_OPTIONS)
def test_every_data_option_composes(option, layout, root, tmp_path):
    assert {"default", "demo", "tiny"} <= set(DATA_OPTIONS) and {"native", "blender"} <= set(LAYOUT_OPTIONS)
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(overrides=[f"+data={option}", f"layout={layout}"])
    assert REQUIRED_KEYS <= set(cfg.data)
    assert cfg.data.layout._target_.endswith({"native": "NativeLayout", "blender": "BlenderLayout", "oidn": "OidnLayout"}[layout])
    cfg.data.root = str(root)
    cfg.data.cache_dir = str(tmp_path / "cache")
    dm = instantiate(cfg.data)
    assert dm.layout.name == layout
    if layout == "native":  # the fixture data is native: one real batch through the configured pipeline
        dm.num_workers, dm.persistent_workers, dm.crop = 0, False, 16
        dm.window = min(dm.window, 4)
        batch = next(iter(dm.train_dataloader()))
        assert batch["color"].shape[1:] == (dm.window, 3, 16, 16)


def test_train_batches_follow_the_contract(root):
    dm = make(root)
    dm.setup("fit")
    batches = list(dm.train_dataloader())
    assert sum(b["color"].shape[0] for b in batches) == len(dm.train_set) == 2 * (4 - 3 + 1)
    b = batches[0]
    B, T = b["color"].shape[:2]
    assert (B, T) == (2, 3)
    shapes = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2, "reference": 3}
    for k, c in shapes.items():
        assert b[k].shape == (B, T, c, 16, 16) and b[k].dtype == torch.float32, k
    assert b["reset"].shape == (B, T) and b["reset"].dtype == torch.bool and b["reset"][:, 0].all()
    assert b["labeled"].shape == (B,) and b["labeled"].dtype == torch.bool and b["labeled"].all()
    assert b["frame_index"].dtype == torch.int64 and b["frame_index"].shape == (B, T)
    assert isinstance(b["sequence"], list) and len(b["sequence"]) == B and b["sequence"][0].startswith("train/t")
    assert "samples" not in b
    resets = {(s, f[0].item()): r.tolist() for bb in batches for s, f, r in
              zip(bb["sequence"], bb["frame_index"], bb["reset"])}
    assert resets[("train/t1", 0)] == [True, False, True] and resets[("train/t1", 1)] == [True, True, False]
    assert resets[("train/t0", 1)] == [True, False, False]


def test_val_and_test_are_whole_sequences_in_order(root):
    dm = make(root)
    val = list(dm.val_dataloader())
    assert len(val) == 1 and val[0]["color"].shape == (1, 3, 3, 24, 32)
    assert val[0]["reset"].tolist() == [[True, False, False]] and val[0]["sequence"] == ["val/v0"]
    test = list(dm.test_dataloader())
    assert test[0]["color"].shape == (1, 2, 3, 32, 32) and test[0]["labeled"].tolist() == [True]
    pieces = list(make(root, "data.val_window=2").val_dataloader())
    assert [p["frame_index"].tolist() for p in pieces] == [[[0, 1]], [[2]]]
    assert [p["reset"].tolist() for p in pieces] == [[[True, False]], [[False]]]
    assert list(make(root, "data.val_split=null").val_dataloader()) == []


def test_unlabeled_mixed_in(root):
    dm = make(root, "data.use_unlabeled=true", "data.unlabeled_ratio=0.5", "data.batch_size=8")
    dm.setup("fit")
    n_lab, n_unl = len(dm.train_set), len(dm.unlabeled_set)
    assert (n_lab, n_unl) == (4, 2)
    torch.manual_seed(0)
    batches = list(dm.train_dataloader())
    labeled = torch.cat([b["labeled"] for b in batches])
    assert labeled.sum() == n_lab and (~labeled).sum() == 4  # ratio 0.5: as many unlabeled as labeled
    for b in batches:
        assert b["reference"].shape == b["color"].shape
        assert b["reference"][~b["labeled"]].abs().sum() == 0
        assert (b["reference"][b["labeled"]].flatten(1).abs().sum(1) > 0).all()
        for s, lab in zip(b["sequence"], b["labeled"].tolist()):
            assert s.startswith("unlabeled/") != lab
    quarter = make(root, "data.use_unlabeled=true", "data.unlabeled_ratio=0.2")
    quarter.setup("fit")
    assert len(quarter.train_dataloader().sampler) == 4 + 1


def test_worker_processes_and_cache(root, tmp_path):
    """Two persistent workers over the cache: same pixels as decoding, each file decoded once."""
    cache = tmp_path / "cache"
    plain = make(root, "data.window=4", "data.crop=null", "data.batch_size=1")
    cached = make(root, f"data.cache_dir={cache}", "data.num_workers=2", "data.persistent_workers=true",
                  "data.window=4", "data.crop=null", "data.batch_size=1")
    loader = cached.train_dataloader()
    assert loader.num_workers == 2 and loader.persistent_workers
    for _ in range(2):  # second epoch entirely from the cache
        got = {b["sequence"][0]: b for b in loader}
    want = {b["sequence"][0]: b for b in plain.train_dataloader()}
    assert set(got) == {"train/t0", "train/t1"}
    for s in got:
        for k in (*FRAME_INPUTS, "reference"):
            assert torch.equal(got[s][k], want[s][k]), (s, k)
    entries = list(cache.rglob("*.npy"))
    assert len(entries) == 2 * 4 * 6  # sequences x frames x buffers
    assert not list(cache.rglob("*.tmp"))
    assert np.load(entries[0], mmap_mode="r").dtype == np.float32


def test_cache_decodes_once_and_notices_changes(tmp_path):
    seq = tmp_path / "train" / "s"
    written = write_synthetic_sequence(seq, frames=2, width=16, height=16)
    layout = NativeLayout({"color": ["color.R", "color.G", "color.B"], "depth": ["depth.Z"]})
    [src] = index_split(layout, tmp_path, "train")
    reader = FrameReader(layout, tmp_path / "cache")
    a = reader.read(src, 1, ["color", "depth"], crop=(2, 3, 8, 5))
    assert reader.decoded == 1
    b = reader.read(src, 1, ["color", "depth"], crop=(2, 3, 8, 5))
    full = reader.read(src, 1, ["color"])
    assert reader.decoded == 1  # every later read comes from the memmaps
    np.testing.assert_array_equal(a["color"], b["color"])
    np.testing.assert_array_equal(full["color"], written["color"][1].transpose(2, 0, 1))
    for got in (a, b):  # decoded, then from the cache
        np.testing.assert_array_equal(got["depth"], written["depth"][1][2:10, 3:8].transpose(2, 0, 1))
        np.testing.assert_array_equal(got["color"], written["color"][1][2:10, 3:8].transpose(2, 0, 1))
    # rewriting the EXR (new size/mtime) makes a new key: the new pixels are read
    hdr = np.full((16, 16, 3), 1e6, np.float32)  # far above float16's 65504: must survive the cache
    exr.write_frame(seq / "frame_0001.exr", {**{k: v[1] for k, v in written.items()}, "color": hdr})
    os.utime(seq / "frame_0001.exr", ns=(1, 10**18))
    c = reader.read(src, 1, ["color"])
    assert reader.decoded == 2 and (c["color"] == 1e6).all()
    d = FrameReader(layout, tmp_path / "cache")
    assert (d.read(src, 1, ["color"])["color"] == 1e6).all() and d.decoded == 0
    # a damaged cache entry is a miss and gets rewritten
    key = FrameCache.key(seq / "frame_0001.exr", "color", layout.spec_key("color"))
    FrameCache(tmp_path / "cache").entry(key).write_bytes(b"garbage")
    assert (d.read(src, 1, ["color"])["color"] == 1e6).all() and d.decoded == 1
    off = FrameReader(layout, None)
    off.read(src, 0, ["color"])
    off.read(src, 0, ["color"])
    assert off.decoded == 2


def test_nonfinite_reported_once_per_file(tmp_path, caplog):
    seq = tmp_path / "train" / "s"
    written = write_synthetic_sequence(seq, frames=2, width=16, height=16)
    color = written["color"][0].copy()
    color[0, 0, 0], color[1, 1, 1], color[2, 2, 2] = np.nan, np.inf, -np.inf
    exr.write_frame(seq / "frame_0000.exr", {**{k: v[0] for k, v in written.items()}, "color": color})
    layout = NativeLayout({"color": ["color.R", "color.G", "color.B"]})
    [src] = index_split(layout, tmp_path, "train")
    reader = FrameReader(layout, None)
    with caplog.at_level(logging.WARNING, logger="denoiser.data.reader"):
        for _ in range(3):
            out = reader.read(src, 0, ["color"])
            reader.read(src, 1, ["color"])
    msgs = [r.getMessage() for r in caplog.records if r.name == "denoiser.data.reader"]
    assert len(msgs) == 1 and "frame_0000.exr" in msgs[0] and "replaced 3 NaN/Inf" in msgs[0]
    assert np.isfinite(out["color"]).all() and out["color"][1, 1, 1] == exr.POS_INF_REPLACEMENT


def test_precache_fills_the_cache_once(root, tmp_path):
    dm = make(root, f"data.cache_dir={tmp_path / 'c'}", "data.precache=true", "data.use_unlabeled=true")
    dm.prepare_data()
    assert len(list((tmp_path / "c").rglob("*.npy"))) == 2 * 4 * 6 + 3 * 6 + 2 * 6 + 4 * 5
    assert dm.fill_cache() == 0  # everything is already there
    dm.setup("fit")
    list(dm.train_dataloader())
    list(dm.val_dataloader())
    assert dm.train_set.reader.decoded == 0 and dm.unlabeled_set.reader.decoded == 0
    assert dm.val_set.reader.decoded == 0
    [v] = dm.sequences("val")
    assert v.name == "val/v0" and v.meta.scene_name == "synthetic" and v.meta.renderer["name"] == "synthetic"


def test_benchmark_runs_small():
    from denoiser.commands.tools import data_throughput as bench

    rows = bench.measure_loader(size=32, crop=16, window=2, sequences=1, frames=3, workers=[0], batch=2, repeat=1)
    assert [r["mode"].split()[0] for r in rows] == ["cold", "fill", "warm"]
    assert all(r["frames"] == 2 * 2 and r["seconds"] > 0 for r in rows)
    assert "| warm (from cache, median of 1) | 0 | 4 |" in bench.table(rows, type("A", (), {
        "sequences": 1, "frames": 3, "size": 32, "window": 2, "crop": 16, "batch": 2})())


def test_whole_frames_of_different_sizes_cannot_batch(root):
    dm = make(root, "data.crop=null", "data.train_split=mixed_sizes")
    shutil.copytree(root / "train" / "t0", root / "mixed_sizes" / "a", dirs_exist_ok=True)
    shutil.copytree(root / "val" / "v0", root / "mixed_sizes" / "b", dirs_exist_ok=True)
    with pytest.raises(UserError, match=r"data.crop: null .* batch_size 2 needs one frame size, .* 32x24, 32x32"):
        dm.setup("fit")


def test_collate_matches_default_and_rejects_mixed_keys():
    from torch.utils.data._utils.collate import default_collate

    from denoiser.data.collate import collate_items

    items = [{"color": torch.rand(2, 3, 4, 4), "reset": torch.tensor([True, False]), "labeled": torch.tensor(True),
              "sequence": f"train/s{i}", "frame_index": torch.arange(2)} for i in range(3)]
    got, want = collate_items(items), default_collate(items)
    assert got.keys() == want.keys() and got["sequence"] == want["sequence"]
    for k in ("color", "reset", "labeled", "frame_index"):
        assert torch.equal(got[k], want[k]) and got[k].dtype == want[k].dtype, k
    items[1] = {**items[1], "reference": torch.zeros(2, 3, 4, 4)}
    with pytest.raises(UserError, match=r"batch mixes items of train/s0 and train/s1 with different buffers "
                                        r"\(reference\)"):
        collate_items(items)


def test_bad_worker_start_method_is_one_config_error(root):
    from denoiser.configs import instantiate_config

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(overrides=["+data=tiny", f"data.root={root}", "data.multiprocessing_context=threads"])
    with pytest.raises(UserError, match="data.multiprocessing_context: 'threads' is not one of fork, spawn"):
        instantiate_config(cfg.data, "data")


@pytest.fixture(scope="module")
def extra_root(tmp_path_factory):
    """A second dataset root: more train and val sequences, no test split."""
    extra = tmp_path_factory.mktemp("extra")
    write_synthetic_sequence(extra / "train" / "f0", frames=4, width=32, height=32, seed=20)
    write_synthetic_sequence(extra / "val" / "fv0", frames=3, width=32, height=24, seed=21)
    return extra


def test_extra_roots_join_the_splits_they_have(root, extra_root):
    layout = NativeLayout({"color": ["color.R", "color.G", "color.B"]})
    train = index_split(layout, root, "train", [extra_root])
    assert [s.name for s in train] == ["train/t0", "train/t1", "train/f0"]
    assert Path(train[-1].directory) == extra_root / "train" / "f0"
    assert [s.name for s in index_split(layout, root, "test", [extra_root])] == ["test/x0"]  # no extra test split
    dm = make(root, f"data.extra_roots=[{extra_root}]", "data.batch_size=1")
    dm.setup("fit")
    assert [s.name for s in dm.sequences("val")] == ["val/v0", "val/fv0"]
    # windows of the extra sequence are drawn too: f0's 4 frames add 4 - window + 1 windows
    alone = make(root, "data.batch_size=1")
    alone.setup("fit")
    assert len(dm.train_set) - len(alone.train_set) == 4 - dm.window + 1
    assert len(dm.val_set) == 2


def test_share_sampler_draws_each_group_its_share_without_repeats_before_a_pass_ends():
    from collections import Counter

    from denoiser.data.sampler import ShareSampler, share_counts

    assert share_counts([0.5, 0.25, 0.25], 10) == [5, 3, 2] or share_counts([0.5, 0.25, 0.25], 10) == [5, 2, 3]
    assert sum(share_counts([1 / 3] * 3, 100)) == 100 and share_counts([0.0, 1.0], 7) == [0, 7]
    groups = [[0, 1, 2, 3, 4, 5], [10, 11], [20, 21, 22]]
    sampler = ShareSampler(groups, [0.5, 0.25, 0.25], 20)
    order = list(sampler)
    assert len(order) == len(sampler) == 20
    counts = Counter("abc"[i // 10] for i in order)
    assert (counts["a"], counts["b"] + counts["c"]) == (10, 10) and {counts["b"], counts["c"]} == {5}
    # a plain check of "whole passes before a repeat": group a (6 windows) drawn 10 times holds all 6, 4 twice
    seen = Counter(i for i in order if i < 10)
    assert sorted(seen.values()) == [1, 1, 2, 2, 2, 2]
    with pytest.raises(ConfigError, match="has no windows"):
        ShareSampler([[0], []], [0.5, 0.5], 4)
    with pytest.raises(ConfigError, match="summing to 1"):
        ShareSampler([[0], [1]], [0.5, 0.6], 4)


def test_extra_share_draws_that_share_of_the_labeled_windows_from_extra_roots(root, extra_root):
    dm = make(root, f"data.extra_roots=[{extra_root}]", "data.batch_size=1", "data.extra_share=0.75", "data.window=2",
              "data.num_workers=0", "data.crop=16")
    dm.setup("fit")
    extra = dm.extra_windows()
    assert extra == [dm.train_set.sources[i].name == "train/f0" for i, _ in dm.train_set.windows]
    n = len(dm.train_set)
    sampler = dm.train_dataloader().sampler
    drawn = list(sampler)
    assert len(drawn) == n and sum(extra[i] for i in drawn) == round(0.75 * n)
    # null: the loader of today (shuffled, every window once), untouched
    plain = make(root, f"data.extra_roots=[{extra_root}]", "data.batch_size=1", "data.num_workers=0")
    assert sorted(plain.train_dataloader().sampler) == list(range(len(plain.train_set)))
    from denoiser.configs import instantiate_config

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(overrides=["+data=tiny", f"data.root={root}", "data.extra_share=0.5"])
    with pytest.raises(ConfigError, match="data.extra_share: 0.5 needs data.extra_roots"):
        instantiate_config(cfg.data, "data")  # how the commands build it: the one line, no Hydra wrapper


def test_extra_share_with_no_extra_windows_is_one_line_naming_the_roots(root, tmp_path):
    """experiment=demo joins data/demo_motion at extra_share 0.25: a user who rendered only data/demo
    gets one line naming the missing root and both ways out, not a sampler's error."""
    missing = tmp_path / "demo_motion"
    dm = make(root, f"data.extra_roots=[{missing}]", "data.extra_share=0.25", "data.num_workers=0")
    with pytest.raises(ConfigError) as err:
        dm.train_dataloader()
    line = str(err.value)
    assert "\n" not in line and str(missing) in line and "render_set=demo_motion" in line
    assert "data.extra_share=null" in line
    # a share of 0 asks for none of them: no error
    assert len(make(root, f"data.extra_roots=[{missing}]", "data.extra_share=0", "data.num_workers=0").train_dataloader())


def test_extra_roots_reach_evaluation(root, extra_root):
    from omegaconf import OmegaConf

    from denoiser.data.evalset import open_test_split

    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        cfg = compose(overrides=["+data=tiny", f"data.root={root}", f"data.extra_roots=[{extra_root}]"])
    _, sources, _ = open_test_split(cfg.data, "val")
    assert [s.name for s in sources] == ["val/v0", "val/fv0"]
    plain = OmegaConf.masked_copy(cfg.data, [k for k in cfg.data if k != "extra_roots"])  # a config without the key
    assert [s.name for s in open_test_split(plain, "val")[1]] == ["val/v0"]


def test_a_sequence_name_in_two_roots_is_one_error_naming_both(root, tmp_path):
    clash = tmp_path / "clash"
    write_synthetic_sequence(clash / "train" / "t1", frames=2, width=32, height=32, seed=30)
    with pytest.raises(UserError, match=r"clash/train/t1: sequence train/t1 is also in .*/train/t1"):
        index_split(NativeLayout({"color": ["color.R", "color.G", "color.B"]}), root, "train", [clash])
