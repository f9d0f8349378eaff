"""`make compare`: its data (dataset=demo_compare: demo's test job with per-sample radiance, in
its own root) and its summary (the Fig. A.2 / A.3 tables of conf/compare_summary.yaml, their
mean ± std over seeds, 1080p times and ranking lines), checked against plain computations."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from hydra import compose, initialize_config_dir

from denoiser.commands.render import plan
from denoiser.conf import CONF_DIR


def _render_cfg(*overrides: str):
    with initialize_config_dir(CONF_DIR, version_base=None):
        return compose("render", overrides=list(overrides))


def test_demo_compare_renders_exactly_demos_test_job_with_samples_in_its_own_root():
    demo, compare = _render_cfg("dataset=demo"), _render_cfg("dataset=demo_compare")
    demo_test = [j for j in plan(demo) if j.split == "test"]
    jobs = plan(compare)
    assert demo_test and len(jobs) == len(demo_test)
    for ours, theirs in zip(jobs, demo_test):
        assert ours.directory == theirs.directory and ours.index == theirs.index
        assert ours.scene_config == theirs.scene_config
        assert ours.settings.save_samples and not theirs.settings.save_samples
        assert ours.settings == dataclasses.replace(theirs.settings, save_samples=True)
    # sequence seeds derive from seed, scene, split and index: the same scenes, cameras and references
    assert compare.seed == demo.seed
    assert Path(compare.root).name == "demo_compare" and Path(compare.root).parent == Path(demo.root).parent
    with initialize_config_dir(CONF_DIR, version_base=None):
        data = compose("eval", overrides=["data=demo_compare"]).data
        demo_data = compose("eval", overrides=["data=demo"]).data
    assert data.root == compare.root
    assert {k: v for k, v in data.items() if k != "root"} == {k: v for k, v in demo_data.items() if k != "root"}
