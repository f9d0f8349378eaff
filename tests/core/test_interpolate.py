"""Weight interpolation between a network and its fine-tune (WiSE-FT):
:func:`denoiser.checkpoint.interpolate_checkpoints` and ``python -m denoiser.commands.tools.interpolate``.
The written weights against a plain loop over tensors and elements, the ends exact, the network
loadable by every command, and each user mistake one error line naming the file."""

from __future__ import annotations

import pytest
import torch
from helpers.checkpoints import tiny_checkpoint
from helpers.configs import compose_command

from denoiser.checkpoint import interpolate_checkpoints, load_denoiser, read_checkpoint, save_checkpoint
from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError, UserError


def weights(path) -> dict[str, torch.Tensor]:
    return {k.removeprefix("net."): v for k, v in read_checkpoint(path)["state_dict"].items()}


@pytest.fixture
def pair(tmp_path):
    return tiny_checkpoint(tmp_path / "start.ckpt", seed=1), tiny_checkpoint(tmp_path / "end.ckpt", seed=2)


def test_weights_are_the_interpolation_element_by_element(tmp_path, pair):
    start, end = pair
    out = interpolate_checkpoints(start, end, 0.25, tmp_path / "mid.ckpt")
    a, b, mid = weights(start), weights(end), weights(out)
    assert set(mid) == set(a) and any(not torch.equal(a[k], b[k]) for k in a)
    for key, tensor in mid.items():  # the reference: a plain loop over the elements
        if not tensor.is_floating_point():
            assert torch.equal(tensor, b[key])
            continue
        for x, y, z in zip(a[key].flatten().tolist(), b[key].flatten().tolist(), tensor.flatten().tolist()):
            assert z == pytest.approx(0.75 * x + 0.25 * y, rel=1e-6, abs=1e-7)
    assert read_checkpoint(out)["interpolation"] == {"start": str(start), "end": str(end), "alpha": 0.25}


def test_the_ends_are_the_two_networks_exactly(tmp_path, pair):
    start, end = pair
    for alpha, same in ((0.0, start), (1.0, end)):
        out = interpolate_checkpoints(start, end, alpha, tmp_path / f"a{alpha}.ckpt")
        assert all(torch.equal(v, weights(same)[k]) for k, v in weights(out).items())
        net, ref = load_denoiser(out), load_denoiser(same)  # a network every command loads
        assert all(torch.equal(p, q) for p, q in zip(net.state_dict().values(), ref.state_dict().values()))


def test_another_network_is_one_error_naming_the_file(tmp_path, pair):
    start, _ = pair
    cfg = compose_net_config("demo_student", "student")
    other = save_checkpoint(tmp_path / "other.ckpt", build_net(cfg), cfg)
    with pytest.raises(UserError, match=r"other\.ckpt: another network than .*start\.ckpt \(net config key"):
        interpolate_checkpoints(start, other, 0.5, tmp_path / "mid.ckpt")
    with pytest.raises(UserError, match=r"missing\.ckpt: checkpoint file does not exist"):
        interpolate_checkpoints(start, tmp_path / "missing.ckpt", 0.5, tmp_path / "mid.ckpt")
    with pytest.raises(ConfigError, match=r"^alpha=1\.5: must lie in \[0, 1\]"):
        interpolate_checkpoints(start, start, 1.5, tmp_path / "mid.ckpt")
    assert not (tmp_path / "mid.ckpt").exists()  # nothing half-written


def test_same_config_other_shapes_is_one_error(tmp_path, pair):
    start, end = pair
    ckpt = read_checkpoint(end)
    key = next(iter(ckpt["state_dict"]))
    ckpt["state_dict"][key] = torch.zeros(3, 1, 1)
    torch.save(ckpt, tmp_path / "bad.ckpt")
    with pytest.raises(UserError, match=r"bad\.ckpt: checkpoint weights do not fit the architecture"):
        interpolate_checkpoints(start, tmp_path / "bad.ckpt", 0.5, tmp_path / "mid.ckpt")


def test_command_writes_the_checkpoint_and_says_one_line_on_a_mistake(tmp_path, pair, capsys):
    from denoiser.commands.app import guarded
    from denoiser.commands.tools.interpolate import run

    start, end = pair
    out = tmp_path / "mid.ckpt"
    cfg = compose_command("interpolate", [f"start={start}", f"end={end}", "alpha=0.5", f"out={out}"])
    assert run(cfg) == out and read_checkpoint(out)["interpolation"]["alpha"] == 0.5
    assert f"{out}: alpha 0.5 between" in capsys.readouterr().out
    bad = compose_command("interpolate", [f"start={start}", f"end={tmp_path / 'nope.ckpt'}", "alpha=0.5",
                                          f"out={tmp_path / 'x.ckpt'}"])
    with pytest.raises(SystemExit) as exc:
        guarded(run)(bad)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.count("\n") == 1 and "nope.ckpt: checkpoint file does not exist" in err
    assert not (tmp_path / "x.ckpt").exists()
