"""What the networks of a source tree compute, as one hash per network config:
``python -m denoiser.commands.tools.nn_fingerprint``. ``scripts/readme_check.py`` compares it between a
README block's commit and ``HEAD`` when only ``denoiser/nn`` code changed, so a refactor that
computes the same numbers leaves the README's measurements current.

Usage::

    python -m denoiser.commands.tools.nn_fingerprint [--nets a,b,...]            # this install's denoiser
    PYTHONPATH=<tree> python denoiser/commands/tools/nn_fingerprint.py --tree <tree> [--nets a,b,...]

prints JSON ``{net: sha256}``. ``<tree>`` is a checkout (or ``git archive``) of a commit:
``denoiser`` is imported from it, this file's code hashes it (``scripts/readme_check.py`` runs this
checkout's file on both trees, by path, so the two hashes are the same computation; the tree of an
older commit need not have this module). So this file imports nothing of the package at its top,
and of the package only what every tree has (``denoiser.configs``, ``denoiser.conf``,
``denoiser.inference.step_graph``); it takes no help from :mod:`denoiser.commands.app` either:
a mistake is one line ``error: ...`` (exit 2). Per
config of ``conf/net`` (``--nets``: a subset), with torch's seed 0 and one thread, bit for bit:

* the training forward pass over a fixed window (batch 2, 3 frames, 24x40, a reset inside: the
  recurrence, its warp and gate), the outputs and every parameter's gradient of a fixed weighting
  of them (what training computes);
* the ONNX graphs the benchmark runs (``export_onnx``: plain and fused operations, 1x1 heads as
  convolutions and as matrix products), canonical: the nodes in order with their operation,
  domain, attributes and inputs by producer (value names left out), the initializers' bytes.

The inputs are drawn here from a generator of their own (nothing of the tree decides them).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import sys
import tempfile
from pathlib import Path


def window(batch: int = 2, frames: int = 3, height: int = 24, width: int = 40) -> dict:
    """A fixed training window ``{buffer: [B, T, C, H, W]}`` with ``reset [B, T]``."""
    import torch

    g = torch.Generator().manual_seed(1234)
    shape = (batch, frames)
    normal = torch.randn(*shape, 3, height, width, generator=g)
    out = {
        "color": torch.rand(*shape, 3, height, width, generator=g) ** 3 * 8.0,
        "albedo": torch.rand(*shape, 3, height, width, generator=g),
        "normal": normal / normal.norm(dim=2, keepdim=True).clamp_min(1e-6),
        "depth": 1.0 + 9.0 * torch.rand(*shape, 1, height, width, generator=g),
        "motion": 3.0 * torch.randn(*shape, 2, height, width, generator=g),
        "reference": torch.rand(*shape, 3, height, width, generator=g),
    }
    out["reset"] = torch.tensor([[True, False, False], [True, False, True]])[:batch, :frames]
    return out


def _tensor_bytes(t) -> bytes:
    return t.detach().contiguous().cpu().numpy().tobytes()


def training_hash(net, h) -> None:
    """Outputs and gradients of the training forward pass over :func:`window` into ``h``."""
    import torch

    w = window()
    net.train()
    net.zero_grad(set_to_none=True)
    outputs, _, _ = net({k: v for k, v in w.items() if k != "reset"}, reset=w["reset"])
    weights = torch.linspace(-1.0, 1.0, outputs.numel()).reshape(outputs.shape)
    (outputs * weights).sum().backward()
    h.update(_tensor_bytes(outputs))
    for name, p in sorted(net.named_parameters()):
        h.update(name.encode())
        h.update(b"none" if p.grad is None else _tensor_bytes(p.grad))


def graph_hash(path: Path, h) -> None:
    """The ONNX graph at ``path``, canonical (see the module docstring), into ``h``."""
    import onnx

    graph = onnx.load(str(path)).graph
    ids: dict[str, int] = {}

    def ref(name: str) -> int:
        return ids.setdefault(name, len(ids)) if name else -1

    for value in graph.input:
        h.update(f"in {value.name} {ref(value.name)}".encode())
    for init in graph.initializer:
        h.update(f"init {ref(init.name)} {list(init.dims)} {init.data_type}".encode())
        h.update(onnx.numpy_helper.to_array(init).tobytes())
    for node in graph.node:
        inputs = [ref(i) for i in node.input]
        outputs = [ref(o) for o in node.output]
        h.update(f"node {node.domain}::{node.op_type} {inputs} -> {outputs}".encode())
        for attr in sorted(node.attribute, key=lambda a: a.name):
            if attr.type == onnx.AttributeProto.GRAPH:  # a subgraph: its canonical form
                raise SystemExit(f"{path}: subgraph attributes are not fingerprinted")
            h.update(attr.name.encode() + b"=" + onnx.helper.get_attribute_value(attr).__repr__().encode())
    for value in graph.output:
        h.update(f"out {value.name} {ref(value.name)}".encode())


def fingerprint(name: str, exports: bool) -> str:
    import torch

    from denoiser.configs import build_net, compose_net_config

    h = hashlib.sha256()
    torch.manual_seed(0)
    net = build_net(compose_net_config(name))
    training_hash(net, h)
    if exports:
        from denoiser.inference.step_graph import export_onnx

        net.eval()
        with tempfile.TemporaryDirectory() as tmp:
            for fused in (False, True):
                for matmul in (False, True):
                    path = Path(tmp) / f"{int(fused)}{int(matmul)}.onnx"
                    export_onnx(net, path, trace_size=(24, 40), fused_kernels=fused, matmul_heads=matmul)
                    graph_hash(path, h)
    return h.hexdigest()


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, as the commands' CommandParser (not imported: see above)
        print(f"error: {message} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


def main(argv=None) -> None:
    parser = _Parser(prog="python -m denoiser.commands.tools.nn_fingerprint", description=__doc__,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--tree", type=Path, help="the tree denoiser must be imported from (an error otherwise)")
    parser.add_argument("--nets", help="comma-separated conf/net names (default: every one)")
    parser.add_argument("--exports", default="demo_student,demo_teacher",
                        help="the nets whose exported graphs count too (the benchmarked ones)")
    args = parser.parse_args(argv)
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    import warnings

    import torch

    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    import denoiser
    from denoiser.conf import CONF_DIR

    if args.tree is not None and args.tree.resolve() not in Path(denoiser.__file__).resolve().parents:
        print(f"error: denoiser was imported from {Path(denoiser.__file__).parent}, not from {args.tree} "
              f"(PYTHONPATH={args.tree})", file=sys.stderr)
        sys.exit(2)

    names = sorted(p.stem for p in (Path(CONF_DIR) / "net").glob("*.yaml"))
    if args.nets:
        names = [n for n in names if n in args.nets.split(",")]
    exports = set(args.exports.split(",")) if args.exports else set()
    json.dump({n: fingerprint(n, n in exports) for n in names}, sys.stdout, indent=1, sort_keys=True)
    print()


if __name__ == "__main__":
    main()
