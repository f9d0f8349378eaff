"""Test-session set-up shared by every test module: the session's temporary folders, the built
artefacts' cache, the OpenVINO modules' skips under ``$DENOISER_REQUIRE_OVEXT``, skips listed by
reason. The code test files share is in ``tests/helpers/`` (``from helpers.<module> import ...``)."""

import os
import sys
from collections import defaultdict

import pytest
from helpers.ovext import REQUIRE_OVEXT
from helpers.session import session_folder

# built artefacts (the OpenVINO extension, denoiser.inference.ovext) go to a per-session folder, not ~/.cache
if "DENOISER_CACHE" not in os.environ:
    os.environ["DENOISER_CACHE"] = str(session_folder("denoiser-test-cache-"))

# make test runs one pytest-xdist worker per core (the Makefile's PYTEST_ISOLATION): each worker's torch
# takes its share of the cores, so that the workers' thread pools do not oversubscribe them
if (_workers := int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "1"))) > 1:
    import torch

    torch.set_num_threads(max(1, (os.cpu_count() or 1) // _workers))


def _absl_handler_on_the_real_stderr() -> None:
    """``import openvino`` imports ``absl.logging`` (through ``openvino.tools.ovc``), whose handler
    keeps the ``sys.stderr`` of that moment: inside pytest, the capture's file. Its ``close()``
    closes any stream that is not the current ``sys.stderr``/``stdout``, so the next
    ``logging.config.dictConfig`` (Hydra's, e.g. in tests/commands/test_help.py) closed pytest's capture
    file and the session died with "I/O operation on closed file". Point it at the real stderr."""
    try:
        import absl.logging
    except ImportError:
        return
    absl.logging.get_absl_handler().python_handler.stream = sys.__stderr__


_absl_handler_on_the_real_stderr()

#: test modules that are all about OpenVINO: under REQUIRE_OVEXT a skip of the whole module fails
OPENVINO_MODULES = ("test_ovext.py", "test_openvino.py")


@pytest.hookimpl(wrapper=True)
def pytest_make_collect_report(collector):
    """Under ``$DENOISER_REQUIRE_OVEXT``, a module-level skip of :data:`OPENVINO_MODULES`
    (``pytest.importorskip("openvino")``) is a collection error."""
    report = yield
    if (report.skipped and os.environ.get(REQUIRE_OVEXT) == "1" and isinstance(collector, pytest.Module)
            and collector.path.name in OPENVINO_MODULES):
        report.outcome = "failed"
        report.longrepr = f"{collector.path.name}: skipped ({skip_reason(report)}), and {REQUIRE_OVEXT}=1"
    return report


def skip_reason(report) -> str:
    """A skipped report's reason, without pytest's ``Skipped: `` prefix."""
    text = report.longrepr[2] if isinstance(report.longrepr, tuple) else str(report.longrepr)
    return text.removeprefix("Skipped: ")


def compact_ids(nodeids: list[str]) -> str:
    """``tests/a.py: test_x (3 cases), test_y; tests/b.py: (module)``: node ids by file, one
    function once with its number of parametrized cases."""
    files: dict[str, dict[str, int]] = defaultdict(dict)
    for nodeid in nodeids:
        path, _, name = nodeid.partition("::")
        name = name.split("[", 1)[0] or "(module)"
        files[path][name] = files[path].get(name, 0) + 1
    return "; ".join(f"{path}: " + ", ".join(name + (f" ({n} cases)" if n > 1 else "") for name, n in names.items())
                     for path, names in files.items())


def pytest_terminal_summary(terminalreporter):
    """A "skipped, by reason" section: each reason once, with how many tests it skipped and
    which (pyproject's ``-r`` leaves skips out, so they are not listed twice)."""
    by_reason: dict[str, list[str]] = defaultdict(list)
    for report in terminalreporter.stats.get("skipped", []):
        by_reason[skip_reason(report)].append(report.nodeid)
    if not by_reason:
        return
    terminalreporter.section("skipped, by reason", sep="-")
    for reason, nodeids in sorted(by_reason.items(), key=lambda item: (-len(item[1]), item[0])):
        terminalreporter.write_line(f"{len(nodeids):4d}  {reason}")
        terminalreporter.write_line(f"      {compact_ids(nodeids)}")
