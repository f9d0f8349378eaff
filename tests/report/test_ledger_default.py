"""Which test ledger a look is recorded in when ``ledger=`` is not given
(:func:`denoiser.report.ledger.default_ledger`): the project's tracked ``docs/results/test_ledger.csv``
for its own datasets (``data/<a render set's name>``, ``data/blender``), a ``test_ledger.csv`` beside
a user's data root for any other."""

from __future__ import annotations

import json
import re
import shutil

from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command
from helpers.eval_data import write_dataset
from omegaconf import OmegaConf

from denoiser.report import ledger


def test_the_project_datasets_are_the_render_sets_and_make_blenders():
    """A render set's data root and make blender's are the project's; the same names elsewhere,
    or another folder under the checkout's data/, are a user's."""
    assert {"demo", "demo_motion", "demo_compare", "blender"} <= ledger.project_datasets()
    makefile = (ledger.ROOT / "Makefile").read_text()
    blender_data = re.search(r"^BLENDER_DATA\s*\?=\s*(\S+)", makefile, re.MULTILINE)[1]
    release_cycles = OmegaConf.to_container(OmegaConf.load(ledger.ROOT / "conf" / "pipeline" / "release.yaml"))["cycles"]
    for made in (blender_data, release_cycles):     # make blender's and make release's Cycles sets
        assert made.startswith(("data/", "${data_root}/")) and made.rsplit("/", 1)[1] in ledger.project_datasets()
    data = ledger.ROOT / "data"
    assert ledger.default_ledger(data / "demo") == ledger.LEDGER
    assert ledger.default_ledger(data / "blender") == ledger.LEDGER
    assert ledger.default_ledger(data / "my_renders") == data / "my_renders" / "test_ledger.csv"
    assert ledger.default_ledger("/elsewhere/demo") == ledger.LEDGER.__class__("/elsewhere/demo/test_ledger.csv")


def test_a_look_at_a_users_test_split_leaves_the_projects_ledger_alone(tmp_path, monkeypatch):
    """denoiser-eval on a user's test split without ``ledger=``: the row goes to
    ``<data.root>/test_ledger.csv`` (the second look is look 2 there, whatever out_dir is), and the
    project's ledger keeps its bytes. The project's ledger is a copy here (``ledger.LEDGER`` patched),
    so a wrong default would change the copy, not the tracked file."""
    from denoiser.commands.evaluate import run

    project = tmp_path / "project_ledger.csv"
    shutil.copyfile(ledger.LEDGER, project)
    before = project.read_bytes()
    monkeypatch.setattr(ledger, "LEDGER", project)
    root = tmp_path / "my_renders"
    write_dataset(root, sequences=1, frames=3, size=32)
    ckpt = tiny_checkpoint(tmp_path / "s.ckpt")
    base = ["data=tiny", f"data.root={root}", f"ckpt=[{ckpt}]", "~baselines.oidn_balanced", "~baselines.oidn_high",
            "metrics=[psnr]", "images.frame=null", "purpose=debug", "threads=1"]
    for k in range(2):
        run(compose_command("eval", [*base, "ledger=null", f"out_dir={tmp_path / f'out{k}'}"]))
    assert project.read_bytes() == before
    rows = ledger.read(root / "test_ledger.csv")
    assert [r["look"] for r in rows] == ["1", "2"] and rows[0]["dataset"] == str(root)
    told = json.loads((tmp_path / "out1" / "evaluation.json").read_text())
    assert told["look"] == 2 and told["ledger"] == str((root / "test_ledger.csv").resolve())
