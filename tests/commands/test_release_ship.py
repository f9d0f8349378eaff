"""Shipping release networks (issue 62): weights only, loaded by name everywhere, their card generated
and checked, and denoiser-denoise's default."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command
from helpers.eval_data import write_sequence

from denoiser.checkpoint import load_denoiser, load_weights, read_checkpoint
from denoiser.commands.tools.release_ship import main as ship_main
from denoiser.data.exr import read_channels
from denoiser.errors import UserError
from denoiser.release import fp16_output_error, models_dir
from denoiser.report.model_card import check_release, render_card

pytestmark = pytest.mark.slow  # each ships two networks (about 10 s on 2 busy cores)


@pytest.fixture()
def shipped(tmp_path, monkeypatch):
    """A teacher and a student checkpoint shipped into tmp/models (DENOISER_MODELS)."""
    teacher, student = tiny_checkpoint(tmp_path / "t.ckpt", seed=1), tiny_checkpoint(tmp_path / "s.ckpt", seed=2)
    (tmp_path / "summary.md").write_text("| method | PSNR |\n|---|---|\n| student | 30.0 |\n")
    out = tmp_path / "models"
    monkeypatch.setenv("DENOISER_MODELS", str(out))
    assert ship_main([f"teacher={teacher}", f"student={student}", "data=release,release_motion",
                      f"figure=Val:{tmp_path / 'summary.md'}"]) == 0
    return out, teacher, student


def test_shipped_networks_load_by_name_with_the_same_weights_and_no_pickled_object(shipped):
    out, teacher, student = shipped
    assert models_dir() == out
    for name, src in (("teacher", teacher), ("student", student)):
        got, want = load_denoiser(f"release:{name}"), load_denoiser(src)
        for (k, a), (_, b) in zip(got.state_dict().items(), want.state_dict().items()):
            assert torch.allclose(a, b, atol=1e-3 * (1 + b.abs().max())), k
        raw = torch.load(out / f"{name}.pt", weights_only=True)  # the safe loader reads it
        assert set(raw) == {"hyper_parameters", "state_dict"}
    manifest = json.loads((out / "release.json").read_text())
    assert manifest["data"] == ["release", "release_motion"]
    assert manifest["networks"]["student"]["dtype"] in ("float16", "float32")
    assert manifest["networks"]["student"]["fp16_output_error"] < 1e-3 or manifest["networks"]["student"]["dtype"] == "float32"
    card = (out / "README.md").read_text()
    assert "| student | 30.0 |" in card and "release:student" in card
    net = load_weights(load_denoiser(teacher), "release:teacher")  # model.init_ckpt=release:teacher
    assert net is not None and read_checkpoint("release:student")["state_dict"]


def test_the_check_fails_when_the_weights_or_the_card_change(shipped):
    out, _, _ = shipped
    assert check_release(out) == []
    card = (out / "README.md").read_text()
    (out / "README.md").write_text(card.replace("30.0", "31.0"))
    assert any("README.md" in p for p in check_release(out))
    (out / "README.md").write_text(card)
    raw = torch.load(out / "student.pt", weights_only=True)
    key = next(iter(raw["state_dict"]))
    raw["state_dict"][key] = raw["state_dict"][key] + 1
    torch.save(raw, out / "student.pt")
    assert any("student.pt" in p for p in check_release(out))
    manifest = json.loads((out / "release.json").read_text())
    assert card == render_card(manifest)


def test_release_names_fail_in_one_line(tmp_path, monkeypatch):
    monkeypatch.setenv("DENOISER_MODELS", str(tmp_path / "none"))
    with pytest.raises(UserError, match="no release student is shipped .*make release"):
        load_denoiser("release:student")
    with pytest.raises(UserError, match="not a release network"):
        load_denoiser("release:pupil")


def test_fp16_output_error_is_small_for_a_small_network_and_grows_with_huge_weights(tmp_path):
    net = load_denoiser(tiny_checkpoint(tmp_path / "a.ckpt"))
    small = fp16_output_error(net)
    assert 0 <= small < 1e-2
    with torch.no_grad():
        for p in net.parameters():
            p.add_(torch.randn_like(p) * 1e-4 + 1 / 3)  # values fp16 cannot hold exactly
    assert fp16_output_error(net) > 0


def test_denoise_without_ckpt_uses_the_release_student(shipped, tmp_path, capsys):
    from denoiser.commands.denoise import run

    out, _, _student = shipped
    seq = write_sequence(tmp_path / "shot", frames=3, size=(24, 32), seed=4)
    run(compose_command("denoise", [f"input={seq}", f"output={tmp_path / 'a'}", "backend=eager", "precision=f32"], threads=1))
    assert "release student" in capsys.readouterr().err
    run(compose_command("denoise", [f"ckpt={out / 'student.pt'}", f"input={seq}", f"output={tmp_path / 'b'}",
                                    "backend=eager", "precision=f32"], threads=1))
    for t in range(3):
        a = read_channels(tmp_path / "a" / f"frame_{t:04d}.exr")
        b = read_channels(tmp_path / "b" / f"frame_{t:04d}.exr")
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_readme_check_fails_on_a_shipped_folder_whose_card_disagrees(shipped, tmp_path):
    import runpy
    from pathlib import Path

    out, _, _ = shipped
    check = runpy.run_path(str(Path(__file__).parents[2] / "scripts" / "readme_check.py"))
    repo = tmp_path / "repo"
    (repo / "denoiser").mkdir(parents=True)
    out.rename(repo / "denoiser" / "models")
    assert check["release_problems"](repo) == []
    (repo / "denoiser" / "models" / "README.md").write_text("# typed by hand\n")
    assert check["release_problems"](repo) == [(f"{repo / 'denoiser' / 'models' / 'README.md'}: not the card "
                                                "release.json renders to (generated, never edited): ship again")]
