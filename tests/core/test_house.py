"""House rules that keep the tree navigable, checked on the source itself:

* the package root holds at most thirteen modules, the shared vocabulary, one job each; everything else lives in
  a wing (``nn``, ``data``, ``render``, ``inference``, ``methods``, ``report``, ``lit``,
  ``pipeline``, ``commands``), and each wing imports only the parts :data:`MAY_IMPORT` lists for it;
* library code never imports a command (``denoiser/commands`` imports the library, not back);
* the buffer vocabulary is written once (:mod:`denoiser.buffers`);
* one recurrent runner (:mod:`denoiser.recurrent`): no module loops over a network's ``step`` by
  itself, and every consumer's steps reach ``Denoiser.step`` through the runner;
* no module of the package reaches itself through imports (late ones inside functions counted);
* checkpoints written by earlier layouts still load, and give the same outputs (the old module
  paths they store: :data:`denoiser.checkpoint.OLD_TARGETS`); no import hook stays on ``sys.meta_path``.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import denoiser
from denoiser.buffers import FRAME_INPUTS, NETWORK_INPUTS, SEQUENCE_BUFFERS
from denoiser.nn.denoiser import Denoiser

PACKAGE = Path(denoiser.__file__).resolve().parent
FIXTURES = Path(__file__).resolve().parents[1] / "fixtures"
RUNNER = (PACKAGE / "recurrent.py").resolve()


def modules(under: Path = PACKAGE, skip: tuple[str, ...] = ()) -> list[Path]:
    return sorted(p for p in under.rglob("*.py") if not any(part in skip for part in p.relative_to(PACKAGE).parts))


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
            names.update(f"{node.module}.{a.name}" for a in node.names)
    return names


def module_name(path: Path, package: Path = PACKAGE) -> str:
    """The dotted name of a module file of ``package`` (a package's ``__init__.py``: the package)."""
    parts = list(path.relative_to(package.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def module_file(name: str, package: Path = PACKAGE) -> Path | None:
    """The file of the dotted module ``name`` of ``package`` (None: not a module of it)."""
    base = package.parent.joinpath(*name.split("."))
    return next((f for f in (base.with_suffix(".py"), base / "__init__.py") if f.is_file()), None)


def import_graph(package: Path = PACKAGE) -> dict[str, set[str]]:
    """``{module: the package's modules it imports}``, every import statement counted, those
    inside functions too (a late import is still an edge): ``from a import b`` is module ``a.b``
    where that is a module, else ``a``; relative imports are resolved."""
    graph = {}
    for path in sorted(package.rglob("*.py")):
        here = module_name(path, package)
        anchor = here if path.name == "__init__.py" else here.rpartition(".")[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = anchor.split(".")[: len(anchor.split(".")) - node.level + 1]
                    base = ".".join([*up, base] if base else up)
                names = [f"{base}.{a.name}" if module_file(f"{base}.{a.name}", package) else base for a in node.names]
            else:
                continue
            found.update(n for n in names if module_file(n, package))
        graph[here] = found - {here}
    return graph


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of ``graph`` with more than one module (Tarjan's)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycle_anywhere_in_the_package():
    """No module of ``denoiser/`` reaches itself through imports, late ones inside functions included."""
    assert not import_cycles(import_graph())


def test_the_cycle_check_sees_a_late_import(tmp_path):
    """The check above is not blind: two modules importing each other, one of them inside a
    function and by a relative import, are one cycle; without the late import, none."""
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("")
    (package / "sub" / "a.py").write_text("from pkg.sub.b import thing\n")
    (package / "sub" / "b.py").write_text("thing = 1\n\ndef late():\n    from . import a\n")
    assert import_cycles(import_graph(package)) == [["pkg.sub.a", "pkg.sub.b"]]
    (package / "sub" / "b.py").write_text("thing = 1\n")
    assert import_cycles(import_graph(package)) == []


#: private modules (a leading underscore: the checkout's conf/ mount) are not part of the root's vocabulary
#: what one job per file needs (tables, machine facts and measurement apart; the release names)
ROOT_MODULES_AT_MOST = 13
#: what each part of the package may import besides itself; ``root`` is the modules at the
#: package root and ``denoiser.conf`` (the shipped configs' folder). ``commands`` may import
#: every part and no part imports it (the test above).
MAY_IMPORT = {
    "root": {"root"},
    "nn": {"root"},
    "data": {"root"},
    "render": {"root", "data"},
    "inference": {"root", "nn"},
    "methods": {"root", "nn", "inference"},
    "report": {"root", "nn", "inference", "methods", "data"},
    "lit": {"root", "nn", "data", "inference", "methods"},  # methods: validation scores OIDN-fast beside the network (val/oidn_fast_psnr)
    "pipeline": {"root"},
}


def part_of(module: str) -> str | None:
    """The part of the package a dotted module name belongs to (None: outside the package)."""
    bits = module.split(".")
    if bits[0] != "denoiser" or len(bits) == 1:
        return None
    return "root" if bits[1] == "conf" or (PACKAGE / f"{bits[1]}.py").is_file() else bits[1]


def test_the_root_holds_at_most_thirteen_modules():
    root = sorted(p.name for p in PACKAGE.glob("*.py") if not p.name.startswith("_"))
    assert len(root) <= ROOT_MODULES_AT_MOST, f"{len(root)} modules at the root, move some into a wing: {root}"


def test_conf_is_at_the_top_level_and_every_package_ships():
    """The configs live in ``conf/`` beside the package (docs/design.md), ``denoiser.conf`` is that
    directory in a checkout, and pyproject's explicit package list (setuptools' find cannot add the
    mapped ``denoiser.conf``) names every package directory, so none is left out of the wheel."""
    import tomllib

    import denoiser.conf

    checkout = PACKAGE.parent
    assert not (PACKAGE / "conf").exists() and (checkout / "conf" / "train.yaml").is_file()
    assert Path(denoiser.conf.CONF_DIR) == checkout / "conf"
    tool = tomllib.loads((checkout / "pyproject.toml").read_text())["tool"]["setuptools"]
    assert tool["package-dir"] == {"denoiser.conf": "conf"}
    # hydra_plugins: the namespace Hydra scans for plugins; an editable install adds this checkout's
    # directory to its __path__ only when it is listed
    found = {"denoiser.conf", "hydra_plugins"} | {
        ".".join(d.relative_to(checkout).parts) for top in ("denoiser", "hydra_plugins")
        for d in [checkout / top, *(checkout / top).rglob("*")]
        if d.is_dir() and d.name != "__pycache__" and any(d.glob("*.py"))}
    assert set(tool["packages"]) == found


def test_every_part_of_the_package_has_an_import_rule():
    parts = {part_of("denoiser." + p.relative_to(PACKAGE).with_suffix("").parts[0]) for p in modules()
             if p.name != "__init__.py" or p.parent != PACKAGE}
    assert parts - {"commands"} == set(MAY_IMPORT)


def test_each_part_imports_only_what_its_rule_allows():
    offenders = {}
    for p in modules(skip=("commands",)):
        here = part_of("denoiser." + p.relative_to(PACKAGE).with_suffix("").parts[0])
        allowed = MAY_IMPORT.get(here, set()) | {here}
        bad = sorted(m for m in imported_modules(p) if part_of(m) not in (None, *allowed))
        if bad:
            offenders[str(p.relative_to(PACKAGE))] = bad
    assert not offenders


def test_the_import_rule_check_is_not_blind(tmp_path):
    """An ``nn`` module importing from ``lit`` or ``inference`` is seen by the check above."""
    bad = tmp_path / "bad.py"
    bad.write_text("from denoiser.lit.losses import DenoiseLoss\nfrom denoiser.inference import ovext\n")
    found = {part_of(m) for m in imported_modules(bad)} - {None}
    assert found == {"lit", "inference"} and not found <= MAY_IMPORT["nn"]


def test_library_never_imports_a_command():
    offenders = {str(p.relative_to(PACKAGE)): sorted(m for m in imported_modules(p) if m.startswith("denoiser.commands"))
                 for p in modules(skip=("commands",))}
    assert not {k: v for k, v in offenders.items() if v}


def test_console_scripts_in_commands_and_python_m_tools_in_tools():
    """``denoiser/commands/`` holds the ``denoiser-*`` console scripts of pyproject's ``[project.scripts]``
    (and ``app.py``, their start-up), each one module there; ``denoiser/commands/tools/`` holds the
    ``python -m`` tools, none of them a console script."""
    import tomllib

    scripts = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())["project"]["scripts"]
    targets = {target.split(":")[0] for target in scripts.values()}
    top = {f"denoiser.commands.{p.stem}" for p in (PACKAGE / "commands").glob("*.py")} - {"denoiser.commands.app"}
    tools = {f"denoiser.commands.tools.{p.stem}" for p in (PACKAGE / "commands" / "tools").glob("*.py")
             if p.name != "__init__.py"}
    assert top == targets, (top - targets, targets - top)
    assert tools and not tools & targets


def test_readme_lists_every_console_script_and_tool():
    """README's "Commands" section has a row for every ``denoiser-*`` console script and every
    ``python -m denoiser.commands.tools`` tool, so a new command cannot ship unlisted."""
    import tomllib

    readme = (PACKAGE.parent / "README.md").read_text()
    commands = readme.split("## Commands", 1)[1]
    scripts = tomllib.loads((PACKAGE.parent / "pyproject.toml").read_text())["project"]["scripts"]
    tools = [p.stem for p in (PACKAGE / "commands" / "tools").glob("*.py") if p.name != "__init__.py"]
    missing = [n for n in [*scripts, *tools] if f"| `{n}` |" not in commands]
    assert not missing, f"README.md's Commands section has no row for {missing}"


def test_commands_do_not_import_each_other():
    """Commands share library modules, never each other's code (``app`` is their shared start-up)."""
    offenders = {}
    for p in modules(PACKAGE / "commands"):
        bad = sorted(m for m in imported_modules(p)
                     if m.startswith("denoiser.commands") and not m.startswith("denoiser.commands.app")
                     and m != "denoiser.commands")
        if bad:
            offenders[p.name] = bad
    assert not offenders


def string_tuples(path: Path):
    """``(line, values)`` of every tuple or list literal made of 4 or more strings."""
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, (ast.Tuple, ast.List)) and len(node.elts) >= 4 and all(
                isinstance(e, ast.Constant) and isinstance(e.value, str) for e in node.elts):
            yield node.lineno, tuple(e.value for e in node.elts)


def test_the_buffer_tuple_is_written_once():
    """No module (tests included) spells out a list of buffer names: they import denoiser.buffers."""
    vocab = set(SEQUENCE_BUFFERS)
    files = modules() + sorted(Path(__file__).resolve().parents[1].rglob("*.py"))
    found = [f"{p.name}:{line} {values}" for p in files if p.name != "buffers.py"
             for line, values in string_tuples(p) if len(vocab.intersection(values)) >= 4]
    assert not found


def loop_step_calls(path: Path):
    """Lines where ``<x>.step(<args>)`` is called inside a loop (optimizer.step() takes no args)."""
    tree = ast.parse(path.read_text())
    for loop in ast.walk(tree):
        if isinstance(loop, (ast.For, ast.While, ast.ListComp, ast.GeneratorExp, ast.DictComp)):
            for node in ast.walk(loop):
                if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) and node.func.attr == "step"
                        and (node.args or node.keywords)):
                    yield node.lineno


def test_only_the_runner_loops_over_step():
    found = [f"{p.relative_to(PACKAGE)}:{line}" for p in modules() if p.resolve() != RUNNER
             for line in loop_step_calls(p)]
    assert not found, f"step the network through denoiser.recurrent instead: {found}"


def test_the_static_check_sees_a_loop(tmp_path):
    """The check above is not blind: a hand-written loop over step is found."""
    bad = tmp_path / "bad.py"
    bad.write_text("def run(net, frames):\n    state = None\n    for f in frames:\n"
                   "        out, state, _ = net.step(f, state)\n")
    assert list(loop_step_calls(bad)) == [4]


@pytest.fixture
def step_callers(monkeypatch):
    """Files from which ``Denoiser.step`` is called while the fixture is active."""
    callers: list[str] = []
    original = Denoiser.step

    def spy(self, *args, **kwargs):
        stack = [str(Path(f.filename).resolve()) for f in inspect.stack(context=0)[1:]]
        callers.append("runner" if str(RUNNER) in stack else stack[0])
        return original(self, *args, **kwargs)

    monkeypatch.setattr(Denoiser, "step", spy)
    return callers


def tiny_net() -> Denoiser:
    from denoiser.checkpoint import load_denoiser

    return load_denoiser(FIXTURES / "student_v0.ckpt")


def frames(count: int = 3, size: int = 16):
    from denoiser.frames import random_frame

    return [random_frame(1, size, size, seed=s, kind="hard") for s in range(count)]


def test_consumers_step_through_the_runner(step_callers, tmp_path):
    """Evaluation's network method, the benchmark's backends and timing, the FLOP count, the
    ONNX export check, and the training/validation unroll all reach Denoiser.step via the runner."""
    from denoiser.inference.backends import TorchBackend
    from denoiser.inference.step_graph import check_export, export_onnx
    from denoiser.measure import count_flops, time_steps
    from denoiser.methods.baselines import NetworkMethod

    net = tiny_net()
    method = NetworkMethod(net, "tiny")
    for i, f in enumerate(frames()):
        method(f, reset=i == 0)
    time_steps(TorchBackend().prepare(net, frames()[0], 1), frames(), warmup=1, repeats=2)
    count_flops(net, 16, 16)
    export_onnx(net, tmp_path / "net.onnx", trace_size=(13, 21))
    calls_before_export_check = len(step_callers)
    check_export(net, tmp_path / "net.onnx", size=(16, 24))
    assert len(step_callers) > calls_before_export_check
    window = {k: torch.stack([f[k] for f in frames()], dim=1) for k in FRAME_INPUTS}
    net(window, reset=torch.tensor([[True, False, False]]))
    assert step_callers
    # tracing for ONNX calls step once through StepGraph: that single step is not a loop
    others = {c for c in step_callers if c != "runner" and not c.endswith("step_graph.py")}
    assert not others, others


def test_network_inputs_extend_the_frame_inputs():
    assert NETWORK_INPUTS[: len(FRAME_INPUTS)] == FRAME_INPUTS and "samples" in NETWORK_INPUTS
    assert set(NETWORK_INPUTS) <= set(SEQUENCE_BUFFERS) and "reference" not in NETWORK_INPUTS


def test_a_checkpoint_of_the_first_layout_still_loads_and_gives_the_same_outputs():
    """``tests/fixtures/student_v0.ckpt`` was written by ``train.py`` at commit d77d64e (before
    the commands moved to ``denoiser/commands``), ``student_v0_io.pt`` holds its outputs on two
    recurrent frames. Rule for later changes: a config key missing from a stored config means
    the behaviour from before that key existed."""
    from denoiser.recurrent import RecurrentRunner

    net = tiny_net()
    io = torch.load(FIXTURES / "student_v0_io.pt", weights_only=True)
    runner = RecurrentRunner(net.step)
    with torch.no_grad():
        for i, (frame, expected) in enumerate(zip(io["frames"], io["outputs"])):
            torch.testing.assert_close(runner(frame, reset=i == 0), expected, rtol=1e-5, atol=1e-6)


# ----------------------------------------------------------------------------- old module paths


def test_importing_the_package_leaves_no_import_hook():
    """``import denoiser`` (and the configs' package) adds nothing to ``sys.meta_path``, and an old
    root module path is no longer importable: stored old paths are mapped where checkpoints load."""
    code = ("import sys\nbefore = list(sys.meta_path)\nimport denoiser, denoiser.conf\n"
            "assert sys.meta_path == before, sys.meta_path\nimport importlib.util\n"
            "assert importlib.util.find_spec('denoiser.losses') is None\nprint(denoiser.conf.CONF_DIR)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False, cwd=PACKAGE.parent)
    assert run.returncode == 0, run.stderr[-3000:]
    assert Path(run.stdout.strip()) == PACKAGE.parent / "conf"


def test_stored_old_targets_map_to_the_current_paths():
    from denoiser.checkpoint import OLD_TARGETS, current_targets

    stored = {"loss": {"_target_": "denoiser.losses.DenoiseLoss", "weights": [1, 2]},
              "transfer": [{"_target_": "denoiser.transfer.L1ChannelTransfer"}], "net": {"_target_": "denoiser.nn.x"}}
    assert current_targets(stored) == {"loss": {"_target_": "denoiser.lit.losses.DenoiseLoss", "weights": [1, 2]},
                                       "transfer": [{"_target_": "denoiser.lit.transfer.L1ChannelTransfer"}],
                                       "net": {"_target_": "denoiser.nn.x"}}
    assert stored["loss"]["_target_"] == "denoiser.losses.DenoiseLoss"  # the stored config is left as it was
    for new in OLD_TARGETS.values():
        importlib.import_module(new.rstrip("."))


def test_the_configs_name_the_current_paths():
    """Every ``_target_`` under conf resolves, and none names an old path of :data:`OLD_TARGETS`."""
    from hydra.utils import get_object

    from denoiser.checkpoint import OLD_TARGETS
    from denoiser.conf import CONF_DIR

    targets = {t for p in Path(CONF_DIR).rglob("*.yaml")
               for t in re.findall(r"_target_:\s*([A-Za-z_][\w.]*)", p.read_text())}
    assert targets
    assert not {t for t in targets if t.startswith(tuple(OLD_TARGETS))}
    for target in sorted(targets):
        get_object(target)


def test_the_first_layout_checkpoint_loads_as_a_training_module():
    """``student_v0.ckpt`` stores ``denoiser.losses.DenoiseLoss`` (the loss's old path): its
    training module is rebuilt from the stored hyper-parameters with the loss at its new path."""
    from denoiser.lit.losses import DenoiseLoss
    from denoiser.lit.supervised import SupervisedModule

    stored = torch.load(FIXTURES / "student_v0.ckpt", map_location="cpu", weights_only=True)["hyper_parameters"]
    assert stored["loss"]["_target_"] == "denoiser.losses.DenoiseLoss"
    module = SupervisedModule.load_from_checkpoint(FIXTURES / "student_v0.ckpt", map_location="cpu",
                                                   weights_only=True)
    assert type(module.loss) is DenoiseLoss


def test_every_path_to_the_checkout_names_the_checkout():
    """A module's ``ROOT``/``CHECKOUT = Path(__file__).resolve().parents[n]`` (the checkout, for the
    scripts, configs and train.py it runs) points at the directory holding pyproject.toml: a module
    moved one package deeper once ran ``denoiser/train.py``, which does not exist."""
    package = Path(denoiser.__file__).resolve().parent
    pattern = re.compile(r"^(ROOT|CHECKOUT) = Path\(__file__\)\.resolve\(\)\.parents\[\d\]", re.MULTILINE)
    found = []
    for path in sorted(package.rglob("*.py")):
        for match in pattern.finditer(path.read_text()):
            module = ".".join(path.relative_to(package.parent).with_suffix("").parts)
            found.append((module, match.group(1)))
            root = getattr(importlib.import_module(module), match.group(1))
            assert (root / "pyproject.toml").is_file() and (root / "denoiser").is_dir(), (module, root)
    assert len(found) >= 4, found  # ledger, cpu_speed, gpu_check, render_blender at least
