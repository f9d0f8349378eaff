"""The network and evaluation-method contracts as ``typing.Protocol`` s (``denoiser.recurrent``):
every network config builds a :class:`Network`, every baseline is a :class:`Method`, and the
consumers refuse what is not, with one line naming it."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from denoiser.conf import CONF_DIR
from denoiser.configs import build_net, compose_net_config
from denoiser.errors import ConfigError
from denoiser.frames import random_frame
from denoiser.methods.baselines import NetworkMethod, NoisyInput, OidnDenoiser, StepperMethod, build_baselines
from denoiser.methods.onnd import OnlineCrossRegression
from denoiser.recurrent import NETWORK_MEMBERS, Method, Network, Stepper, Temporal, is_network

NETS = sorted(p.stem for p in (Path(CONF_DIR) / "net").glob("*.yaml"))


@pytest.mark.parametrize("name", NETS)
def test_every_network_config_builds_a_network(name):
    net = build_net(compose_net_config(name))
    assert is_network(net)
    assert net.temporal is None or isinstance(net.temporal, Temporal)
    # the members say what step does: features as wide as feature_channels, state as state_channels
    frame = random_frame(1, 16, 24, seed=0)
    with torch.no_grad():
        out, state, extras = net.step(frame)
    assert out.shape == (1, 3, 16, 24)
    assert [f.shape[1] for f in extras["features"]] == list(net.feature_channels)
    assert all(f.shape[-2] * 2 ** i >= 16 and (f.shape[-2] * 2 ** i) % net.multiple == 0
               for i, f in enumerate(extras["features"]))
    channels = net.temporal.state_channels() if net.temporal is not None else {}
    assert {k: v.shape[1] for k, v in state.items()} == channels


def test_a_module_without_step_is_not_a_network():
    class Plain(torch.nn.Module):
        feature_channels, multiple, temporal = [8], 1, None

    assert not is_network(Plain())
    with pytest.raises(ConfigError, match="tiny: a Plain is not a denoising network module"):
        NetworkMethod(Plain(), "tiny")


def test_the_network_check_sees_members_held_as_submodules():
    """Python 3.12's isinstance() on a runtime protocol looks members up with inspect.getattr_static,
    which misses an nn.Module's submodules: a lent H200 (Python 3.12) refused a real Denoiser there.
    is_network looks them up as attributes, on any Python."""
    import inspect

    net = build_net(compose_net_config("demo_student", "student"))
    assert "temporal" in net._modules  # where the static lookup does not look
    with pytest.raises(AttributeError):
        inspect.getattr_static(net, "temporal")
    assert set(NETWORK_MEMBERS) == {*Network.__annotations__, "step"}  # the protocol's members, said once
    assert is_network(net)
    NetworkMethod(net, "student")  # accepted


def test_every_baseline_is_a_method():
    net = build_net(compose_net_config("tiny"))
    stepper = Stepper(lambda frame, state: (frame["color"], state))
    methods = [NoisyInput(), NetworkMethod(net, "tiny"), StepperMethod(stepper, "eager"), OnlineCrossRegression()]
    try:
        import pyoidn  # noqa: F401 - an optional extra
    except ImportError:
        pass
    else:
        methods.append(OidnDenoiser("fast"))
    for method in methods:
        assert isinstance(method, Method), type(method).__name__


class NoReset:
    label = "no reset"
    recurrent = False

    def __call__(self, frame, reset=False):
        return frame["color"]


def test_a_baseline_that_is_not_a_method_is_one_line_naming_its_key():
    with pytest.raises(ConfigError) as err:
        build_baselines({"mine": {"_target_": f"{__name__}.NoReset"}})
    assert str(err.value) == ("baselines.mine: a NoReset is not an evaluation method (denoiser.recurrent.Method); "
                              "it lacks reset")
