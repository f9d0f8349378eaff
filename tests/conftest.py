"""Test-session set-up shared by every test module."""

import atexit
import os
import sys
import tempfile
from collections import defaultdict
from pathlib import Path

import pytest

#: the folders this process made in the temporary directory, removed when it exits: a pytest session,
#: and a script a test runs that imports this module (tests/inference/test_signal_stack.py's forced sequence)
SESSION_FOLDERS: list[Path] = []


def _remove_session_folders() -> None:
    import shutil

    for folder in SESSION_FOLDERS:
        shutil.rmtree(folder, ignore_errors=True)


atexit.register(_remove_session_folders)

# built artefacts (the OpenVINO extension, denoiser.inference.ovext) go to a per-session folder, not ~/.cache
if "DENOISER_CACHE" not in os.environ:
    os.environ["DENOISER_CACHE"] = tempfile.mkdtemp(prefix="denoiser-test-cache-")
    SESSION_FOLDERS.append(Path(os.environ["DENOISER_CACHE"]))


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

#: set by .ci/run where ``openvino`` imports and a C++ compiler exists: there the OpenVINO
#: extension's tests must run, and a skip for want of the extension (or of openvino) is a failure
REQUIRE_OVEXT = "DENOISER_REQUIRE_OVEXT"
#: test modules that are all about OpenVINO: under REQUIRE_OVEXT a skip of the whole module fails
OPENVINO_MODULES = ("test_ovext.py", "test_openvino.py")


def skip_or_fail(reason: str):
    """Skip the test for ``reason``, or fail it when ``$DENOISER_REQUIRE_OVEXT`` is 1."""
    if os.environ.get(REQUIRE_OVEXT) == "1":
        pytest.fail(f"{reason} (and {REQUIRE_OVEXT}=1: this test must run here)", pytrace=False)
    pytest.skip(reason)


def extension_or_skip() -> Path:
    """The OpenVINO extension's library (:func:`denoiser.inference.ovext.kernel_extension`, built on first
    use); skips the test naming why it is unavailable (fails it under ``$DENOISER_REQUIRE_OVEXT``)."""
    from denoiser.inference import ovext

    path = ovext.kernel_extension()
    if path is None:
        skip_or_fail(f"the OpenVINO extension is unavailable: {ovext.unavailable_reason()}")
    return path


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


def tiny_checkpoint(path, seed: int = 0, **extra):
    """A checkpoint of ``net=tiny kernel=student`` with the weights of ``torch.manual_seed(seed)``,
    written by :func:`denoiser.checkpoint.save_checkpoint` (``extra`` keys go to its top level)."""
    import torch

    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config

    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(seed)
    return save_checkpoint(path, build_net(cfg), cfg, **extra)


#: the test ledger of this test session (denoiser/report/ledger.py): never the checkout's committed one
TEST_LEDGER = Path(tempfile.mkdtemp(prefix="denoiser-test-ledger-")) / "test_ledger.csv"
SESSION_FOLDERS.append(TEST_LEDGER.parent)


def compose_command(name: str, overrides, threads: int | None = None):
    """The entry config ``conf/<name>.yaml`` composed with ``overrides`` (plus ``threads=N`` when given).
    ``eval`` gets ``purpose=test-suite`` and the session's :data:`TEST_LEDGER` unless the test gives them."""
    from denoiser.configs import compose_config

    extra = [f"threads={threads}"] if threads else []
    if name == "eval":
        given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
        extra += [o for key, o in (("purpose", "purpose=test-suite"), ("ledger", f"ledger={TEST_LEDGER}"))
                  if key not in given]
    return compose_config([*overrides, *extra], name)


# The first lines of every stub executable: it appends its name and arguments as one record
# (NUL-separated, newline-ended) to $STUB_LOG. Pipelines run stubs side by side, so the
# record is written under an exclusive lock: two unlocked writers interleave and lose calls.
STUB_HEADER = """#!/usr/bin/env bash
{ flock 9; printf '%s\\0' "$(basename "$0")" "$@" >&9; printf '\\n' >&9; } 9>> "$STUB_LOG"
"""


def stub_calls(log: Path) -> list[list[str]]:
    """The calls :data:`STUB_HEADER` logged to ``log``, in order: ``[command, *args]`` each."""
    return [line.strip("\0").split("\0") for line in log.read_text().splitlines() if line]
