"""The shipped release networks (issue 62): where they are, their names, how they are stored.

The networks are data, not code: the folder ``denoiser/models/`` (package data of ``denoiser``) holds,
once ``make release`` has shipped (``python -m denoiser.commands.tools.release_ship``)::

    denoiser/models/teacher.pt     # {"hyper_parameters": {"net": <net config>}, "state_dict": {"net.<name>": tensor}}
    denoiser/models/student.pt     #   (no pickled object: torch.load(weights_only=True) reads it)
    denoiser/models/release.json   # the manifest: per network its file's SHA-256, bytes, storage dtype,
                                   # parameters, source run, steps and seed; the data, the commit, the figures
    denoiser/models/README.md      # the model card, generated from release.json (never typed)

Wherever a command takes a checkpoint (``ckpt=``, ``model.teacher_ckpt=``, ``model.init_ckpt=``), the
names ``release:teacher`` and ``release:student`` are these files (:func:`release_file`, through
:func:`denoiser.checkpoint.resolve_checkpoint`); ``denoiser-denoise`` without ``ckpt=`` uses
``release:student``. ``DENOISER_MODELS`` names another folder of the same form (a user's own release,
the tests'). A file is at most :data:`MAX_FILE_BYTES`; weights may be stored as float16 when the
network's outputs stay within :data:`FP16_TOLERANCE` of float32 storage (:func:`fp16_output_error`).
"""

from __future__ import annotations

import os
from pathlib import Path

from denoiser.errors import UserError

#: the prefix of a release network's name (``release:student``)
PREFIX = "release:"
#: the networks a release ships
NAMES = ("teacher", "student")
#: the largest weight file shipped (the wheel and the repository stay small)
MAX_FILE_BYTES = 25 * 2**20
#: float16 storage is used only when outputs move by at most this (relative, see fp16_output_error)
FP16_TOLERANCE = 1e-3
MANIFEST = "release.json"
CARD = "README.md"


def models_dir() -> Path:
    """The folder of the shipped networks: ``$DENOISER_MODELS``, else ``denoiser/models``."""
    env = os.environ.get("DENOISER_MODELS")
    return Path(env) if env else Path(__file__).resolve().parent / "models"


def is_release_name(spec) -> bool:
    return isinstance(spec, (str, os.PathLike)) and str(spec).startswith(PREFIX)


def release_file(spec: str | os.PathLike) -> Path:
    """The weight file of ``release:<name>``. UserError naming it when ``<name>`` is not a release
    network, or when this installation ships none yet (with the command that builds one)."""
    name = str(spec)[len(PREFIX):]
    if name not in NAMES:
        raise UserError(f"{spec}: not a release network; use {' or '.join(PREFIX + n for n in NAMES)}")
    path = models_dir() / f"{name}.pt"
    if not path.is_file():
        raise UserError(f"{spec}: no release {name} is shipped in {models_dir()} yet (make release builds and "
                        "ships one; or give a checkpoint file or a run directory)")
    return path


def fp16_output_error(net, frames: int = 3, size: int = 48, seed: int = 0) -> float:
    """How far float16 storage of ``net``'s weights moves its output: the largest
    ``|y16 - y32| / (1 + |y32|)`` over ``frames`` recurrent steps of a fixed random input
    (``[1, 3, size, size]`` HDR colour, the other buffers alike), computed in float32."""
    import copy

    import torch

    from denoiser.buffers import FRAME_INPUTS
    from denoiser.recurrent import RecurrentRunner

    g = torch.Generator().manual_seed(seed)
    shapes = {"color": 3, "albedo": 3, "normal": 3, "depth": 1, "motion": 2}
    inputs = [{b: torch.rand(1, shapes[b], size, size, generator=g) * (4.0 if b == "color" else 1.0)
               for b in FRAME_INPUTS} for _ in range(frames)]
    half = copy.deepcopy(net)
    with torch.no_grad():
        for p in half.state_dict().values():
            if p.is_floating_point():
                p.copy_(p.to(torch.float16).to(p.dtype))
    outs = []
    with torch.no_grad():
        for model in (net.eval(), half.eval()):
            runner = RecurrentRunner(model.step)
            outs.append(torch.stack([runner(x, reset=t == 0) for t, x in enumerate(inputs)]))
    return float(((outs[1] - outs[0]).abs() / (1 + outs[0].abs())).max())
