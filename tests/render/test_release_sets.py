"""The model release's Mitsuba render sets (conf/render_set/release*.yaml, issue 62): new draws only
(no sequence seed of any other set), 10x the demo's training sequences of every training family,
a resolution above 128x128, val families that training never sees, a fresh test split."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from denoiser.commands.render import plan
from denoiser.conf import CONF_DIR
from denoiser.render.seeds import sequence_seed

SETS = sorted(p.stem for p in (Path(CONF_DIR) / "render_set").glob("*.yaml"))
RELEASE_TRAINING = ("release", "release_motion", "release_hires")


@pytest.fixture(scope="module")
def planned():
    """{set: (cfg, jobs)} for every render set of conf/render_set/."""
    out = {}
    with initialize_config_dir(CONF_DIR, version_base="1.3"):
        for name in SETS:
            cfg = compose("render", overrides=[f"render_set={name}"])
            out[name] = (cfg, plan(cfg))
    return out


def seeds(planned, name) -> set[int]:
    cfg, jobs = planned[name]
    return {sequence_seed(cfg.seed, j.scene_name, j.split, j.index) for j in jobs}


def test_release_sets_draw_no_sequence_of_another_set(planned):
    assert {*RELEASE_TRAINING, "release_test"} <= set(SETS)
    others = set().union(*(seeds(planned, s) for s in SETS if not s.startswith("release")))
    assert others, "the other sets plan sequences"
    for name in (*RELEASE_TRAINING, "release_test"):
        mine = seeds(planned, name)
        assert len(mine) == len(planned[name][1]), f"{name}: two sequences share a seed"
        assert not mine & others, f"{name} draws a sequence of an earlier set"
    training = set().union(*(seeds(planned, s) for s in RELEASE_TRAINING))
    assert not seeds(planned, "release_test") & training


def train_counts(planned, names) -> Counter:
    return Counter(j.scene_name for n in names for j in planned[n][1] if j.split == "train")


def test_release_trains_every_demo_family_at_ten_times_its_sequences(planned):
    demo = train_counts(planned, ["demo", "demo_motion"])
    release = train_counts(planned, RELEASE_TRAINING)
    assert set(demo) == set(release)
    for family, n in demo.items():
        assert release[family] >= 10 * n, (family, release[family], n)
    sizes = {(j.settings.width, j.settings.height) for n in RELEASE_TRAINING for j in planned[n][1] if j.split == "train"}
    assert max(w for w, _ in sizes) > 128
    assert all(j.settings.ref_spp >= 256 for n in RELEASE_TRAINING for j in planned[n][1] if j.split == "train")


def test_release_val_holds_families_train_never_sees_and_test_holds_only_test_families(planned):
    trained = set(train_counts(planned, RELEASE_TRAINING))
    val = {j.scene_name for n in RELEASE_TRAINING for j in planned[n][1] if j.split == "val"}
    assert val - trained >= {"courtyard", "lamp_room", "fast_spin"}
    _test_cfg, test_jobs = planned["release_test"]
    assert {j.split for j in test_jobs} == {"test"} and len(test_jobs) >= 42
    assert {j.scene_name for j in test_jobs} == {j.scene_name for j in planned["demo"][1] if j.split == "test"}
    assert not {j.scene_name for j in test_jobs} & (trained | val)


def test_the_joined_release_roots_share_no_sequence_name(planned):
    """Training joins the roots (data.extra_roots), which refuses a sequence name in two of them."""
    for split in ("train", "val", "unlabeled"):
        names = [j.directory for n in RELEASE_TRAINING for j in planned[n][1] if j.split == split]
        assert len(names) == len(set(names)), split
