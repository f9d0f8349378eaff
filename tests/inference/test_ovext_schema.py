"""The OpenVINO extension's operations are said once (:data:`denoiser.nn.graph_ops.OPERATIONS`):
what :mod:`denoiser.nn` exports and what the C++ source registers (one header per operation,
named after it in snake case, and extension.cpp) must both match it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from denoiser.inference import ovext
from denoiser.nn.graph_ops import DOMAIN, OPERATIONS

OVEXT = Path(ovext.__file__).parent
#: the C++ type an ONNX conversion reads each attribute type with (ctx.get_attribute<T>)
CPP_TYPES = {"float": "FLOAT", "int64_t": "INT", "std::vector<int64_t>": "INTS", "std::string": "STRING"}


def cpp_operations() -> dict[str, dict]:
    """From the C++ source: per operation, its header (OPENVINO_OP), the attributes it visits, and
    from extension.cpp's ONNX conversion the attributes read (with their types) and the inputs."""
    found: dict[str, dict] = {}
    for header in sorted(OVEXT.glob("*.hpp")):
        text = header.read_text()
        for name, domain in re.findall(r'OPENVINO_OP\("(\w+)", "(\w+)"\)', text):
            assert domain == DOMAIN, (header.name, name, domain)
            found[name] = {"header": header.name, "visited": set(re.findall(r'on_attribute\("(\w+)"', text))}
    registration = (OVEXT / "extension.cpp").read_text()
    for name in re.findall(r"OpExtension<denoiser::(\w+)>", registration):
        found[name]["registered"] = True
    blocks = re.split(r"ConversionExtension>\(", registration)[1:]
    for block in blocks:
        name, domain = re.match(r'\s*"(\w+)", "(\w+)"', block).groups()
        assert domain == DOMAIN, (name, domain)
        attrs = {a: CPP_TYPES[t.strip()] for t, a in re.findall(r'get_attribute<([\w:<> ]+)>\("(\w+)"', block)}
        indices = [int(i) for i in re.findall(r"get_input\((\d+)\)", block)]
        inputs = None if "all_inputs(ctx)" in block else max(indices) + 1  # all_inputs: any number
        found[name].update(attributes=attrs, inputs=inputs)
    return found


def header_of(name: str) -> str:
    """``KernelApply`` -> ``kernel_apply.hpp``."""
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower() + ".hpp"


def test_the_cpp_source_registers_the_schema():
    cpp = cpp_operations()
    assert set(cpp) == set(OPERATIONS)
    for name, op in OPERATIONS.items():
        got = cpp[name]
        assert got["header"] == header_of(name), name
        assert got.get("registered"), f"{name}: no OpExtension in extension.cpp"
        assert got["attributes"] == op.attributes, name           # what the ONNX conversion reads
        assert got["visited"] == set(op.attributes), name         # what the operation serialises
        assert got["inputs"] == op.inputs, name


def exported_operations(tmp_path: Path) -> dict[str, list[tuple[int, dict[str, str]]]]:
    """Every ``denoiser`` node of graphs exported with the fused operations: the pyramid student,
    the single-kernel ablation (KernelApply), the matmul heads (FactoredHead, the f32 graph's input operations) and the history
    clamp with the disocclusion gate (ClampBlend, GuideGate: demo_student's temporal options)."""
    onnx = pytest.importorskip("onnx")
    from denoiser.configs import build_net, compose_net_config
    from denoiser.inference.step_graph import export_onnx

    nodes: dict[str, list] = {}
    temporal = ["+net.temporal.history_clamp=1.0", "+net.temporal.reject_threshold=0.1"]
    for k, (ablation, matmul, overrides) in enumerate([("none", False, []), ("no_pyramid", False, []),
                                                       ("none", True, []), ("none", False, temporal)]):
        net = build_net(compose_net_config("tiny", ablation=ablation, overrides=overrides)).eval()
        path = export_onnx(net, tmp_path / f"{k}.onnx", trace_size=(32, 32), fused_kernels=True, matmul_heads=matmul)
        for node in onnx.load(str(path)).graph.node:
            if node.domain == DOMAIN:
                attrs = {a.name: onnx.AttributeProto.AttributeType.Name(a.type) for a in node.attribute}
                nodes.setdefault(node.op_type, []).append((len(node.input), attrs))
    return nodes


def test_the_networks_export_the_schema(tmp_path):
    exported = exported_operations(tmp_path)
    assert set(exported) == set(OPERATIONS)   # every operation is exported by some network, none other
    for name, uses in exported.items():
        op = OPERATIONS[name]
        for inputs, attrs in uses:
            assert attrs == op.attributes, name
            assert op.inputs is None or inputs == op.inputs, name


def _main(tmp_path: Path, **env: str):
    import os
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-m", "denoiser.inference.ovext"], capture_output=True, text=True,
                          check=False, timeout=600, cwd=tmp_path,
                          env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]),
                               "DENOISER_CACHE": str(tmp_path / "cache"), **env})


def test_make_ovext_builds_ahead_of_time_or_says_why(tmp_path):
    """``python -m denoiser.inference.ovext`` (make ovext): the library's path, or one line and exit 1."""
    failed = _main(tmp_path, CXX="/bin/false")
    if ovext.missing_requirement() is None:
        assert failed.returncode == 1 and failed.stdout == ""
        errors = [line for line in failed.stderr.splitlines() if not line.startswith("building the OpenVINO")]
        assert errors == [("error: the OpenVINO extension cannot be built: building extension.cpp failed: "
                           "/bin/false exited with status 1 and printed nothing")]
        (tmp_path / "again").mkdir()
        built = _main(tmp_path / "again")
        assert built.returncode == 0, built.stderr
        library = Path(built.stdout.strip())
        assert library.is_file() and (tmp_path / "again" / "cache" / "ovext") in library.parents
    else:   # no openvino or no compiler here: the reason, one line
        assert failed.returncode == 1 and ovext.missing_requirement() in failed.stderr
