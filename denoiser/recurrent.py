"""The one recurrent runner: steps a network over a sequence's frames, carrying its state and
resetting it at the first frame and at camera cuts.

Every consumer steps networks through this module: training and validation windows
(:func:`unroll`, through ``Denoiser.forward``), evaluation and the baselines, the benchmark's
backends, ``denoiser-denoise``, the export check and the network benchmark
(:class:`RecurrentRunner`). A new backend (ONNX Runtime, OpenVINO, ...) or baseline only has to
provide a *step function*; a test checks that nothing else loops over ``step`` by itself.

Step function contract::

    step(frame, state) -> (output, new_state, *extras)

``frame`` is ``{buffer: [B, C, H, W]}`` (tensors or arrays, :mod:`denoiser.buffers`),
``state`` the previous call's ``new_state`` or None, which means "no history": the first frame
of a sequence or a camera cut. :meth:`Denoiser.step <denoiser.nn.denoiser.Denoiser.step>`,
the exported graph's :class:`~denoiser.inference.step_graph.OnnxStep` and every backend's
:class:`Stepper` (what a backend prepares, :mod:`denoiser.inference.backends`) follow it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, Protocol, runtime_checkable

StepFn = Callable[..., tuple]


@runtime_checkable
class Temporal(Protocol):
    """A network's recurrence, as the exporter and the backends see it."""

    def state_channels(self) -> dict[str, int]:
        """``{state key: channels}`` of the state ``step`` carries, in graph order."""
        ...


@runtime_checkable
class Network(Protocol):
    """The network contract: what training, the runner, the exporter, the backends and
    :class:`~denoiser.methods.baselines.NetworkMethod` call on a denoising network
    (:class:`~denoiser.nn.denoiser.Denoiser`, with any of its filters: the pyramid, NPPD's
    learned upsampling, WS). :func:`is_network` checks that the members exist.

    ``step(frame, state=None, reset=None) -> (output, state, extras)``: one frame, the step
    function contract above (``frame`` ``{buffer: [B, C, H, W]}``, ``output [B, 3, H, W]``
    float32 linear HDR, ``state`` ``{key: [B, C, H, W]}``, ``reset`` bool ``[B]`` or None);
    ``extras["features"]`` holds one U-Net map per level, ``feature_channels`` wide (feature
    distillation); ``multiple``: height and width are padded to it inside ``step``;
    ``temporal``: the recurrence (:class:`Temporal`) or None for a per-frame network.
    """

    feature_channels: list[int]
    multiple: int
    temporal: Temporal | None

    def step(self, frame: Mapping[str, Any], state: dict | None = None, reset: Any = None) -> tuple:
        ...


NETWORK_MEMBERS = ("step", "feature_channels", "multiple", "temporal")


def is_network(x: Any) -> bool:
    """Whether ``x`` has the members of :class:`Network` (``step`` callable). Use this, not
    ``isinstance(x, Network)``: from Python 3.12 that looks the members up with
    ``inspect.getattr_static``, which does not see an ``nn.Module``'s submodules (``temporal``
    lives in ``_modules``), so a real Denoiser failed it on a lent GPU machine's Python 3.12."""
    return callable(getattr(x, "step", None)) and all(hasattr(x, m) for m in NETWORK_MEMBERS[1:])


@runtime_checkable
class Method(Protocol):
    """The evaluation contract of :mod:`denoiser.methods.baselines`: every method compared
    (the noisy input, OIDN, ONND, a network through :class:`RecurrentRunner`, a backend's
    stepper) is called frame by frame in sequence order: ``reset()`` before a sequence, then
    ``method(frame, reset) -> [1, 3, H, W]`` linear HDR (``reset`` True at the first frame and
    at camera cuts). ``label`` names it in the tables; ``recurrent`` says whether it carries
    history (its frames 2+ are then the figure that shows the history's worth)."""

    label: str
    recurrent: bool

    def reset(self) -> None:
        ...

    def __call__(self, frame: Mapping[str, Any], reset: bool = False) -> Any:
        ...


class Stepper:
    """A prepared network: ``step(frame, state) -> (output, state)`` (the contract above:
    ``state=None`` starts a sequence); ``sync()`` waits for the device.
    ``profile()``, where the backend can say, gives the last step's time per operation type:
    ``{op type: ms}``; None where it cannot; ``extension_profile()`` the same for the operations of
    the project's OpenVINO extension alone (within the op type ``Reference``). ``kernels()``, where
    the engine can say, names the implementations the last step ran: ``{"openvino": {node type:
    {implementation: count}}, "extension": what the extension was built for, or None}``
    (:func:`denoiser.inference.step_graph.compiled_kernels`, :func:`denoiser.inference.ovext.built_for`).
    ``threads()``, where the engine can say, is the
    thread count it actually uses, read back from it (after a step: OpenVINO resolves it when
    compiling); ``engine`` names the library that runs the step (``torch``, ``onnxruntime``,
    ``openvino``, ``oidn``), for its version in the tables."""

    def __init__(self, step: Callable, sync: Callable[[], None] = lambda: None,
                 profile: Callable[[], dict[str, float]] | None = None,
                 threads: Callable[[], int] | None = None, engine: str = "",
                 extension_profile: Callable[[], dict[str, float]] | None = None,
                 kernels: Callable[[], dict] | None = None):
        self.step = step
        self.kernels = kernels
        self.sync = sync
        self.profile = profile
        self.extension_profile = extension_profile
        self.threads = threads
        self.engine = engine


class RecurrentRunner:
    """A step function with its state carried from call to call (one sequence at a time).

    ``runner(frame, reset)`` -> output; ``reset=True`` (first frame, camera cut) drops the
    history before stepping. ``extras`` holds what the last step returned after the state
    (``Denoiser.step``'s extras dict), ``state`` the carried state.
    """

    def __init__(self, step: StepFn):
        self.step = step
        self.state: Any = None
        self.extras: tuple = ()

    def reset(self) -> None:
        """Forget the history: the next frame starts a sequence."""
        self.state = None

    def __call__(self, frame: Mapping[str, Any], reset: bool = False):
        """One step: ``frame`` ``{buffer: [B, C, H, W]}`` -> the step's output ``[B, 3, H, W]``."""
        if reset:
            self.state = None
        output, self.state, *self.extras = self.step(frame, self.state)
        return output

    def run(self, frames: Iterable[tuple[Mapping[str, Any], bool]]) -> Iterator:
        """Step over ``(frame, reset)`` pairs in order, yielding each output (state carried)."""
        for frame, reset in frames:
            yield self(frame, reset)


def unroll(step: StepFn, frames: Mapping[str, Any], keys: Iterable[str], state: Any = None, reset: Any = None,
           detach_every: int = 0, detach: Callable[[Any], Any] | None = None):
    """Unroll ``step`` over a batch of windows (training, validation).

    frames: ``{buffer: [B, T, C, H, W]}`` (``samples [B, T, S, 3, H, W]``); only ``keys`` that
        are present and not None are stepped. reset: bool ``[B, T]`` or None; ``reset[:, t]``
        is passed to ``step(frame, state, reset)`` so items of a batch reset independently.
    detach_every: k > 0 applies ``detach`` to the state before every k-th step (truncated BPTT).

    Returns ``(outputs: list of T outputs [B, 3, H, W], final state, list of T extras)``.
    """
    keys = [k for k in keys if frames.get(k) is not None]
    steps = frames["color"].shape[1]
    outputs, extras_list = [], []
    for t in range(steps):
        if detach_every and t > 0 and t % detach_every == 0 and detach is not None:
            state = detach(state)
        frame = {k: frames[k][:, t] for k in keys}
        output, state, *extras = step(frame, state, None if reset is None else reset[:, t])
        outputs.append(output)
        extras_list.append(extras[0] if len(extras) == 1 else tuple(extras))
    return outputs, state, extras_list
