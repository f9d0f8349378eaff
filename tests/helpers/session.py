"""The folders a test session makes in the temporary directory, removed when its process exits:
:data:`SESSION_FOLDERS` (a pytest session, and a script a test runs that imports ``conftest``:
tests/inference/test_signal_stack.py's forced sequence), and :data:`TEST_LEDGER`, the session's
test ledger (denoiser/report/ledger.py), never the checkout's committed one."""

import atexit
import shutil
import tempfile
from pathlib import Path

#: the folders this process made in the temporary directory, removed when it exits
SESSION_FOLDERS: list[Path] = []


def _remove_session_folders() -> None:
    for folder in SESSION_FOLDERS:
        shutil.rmtree(folder, ignore_errors=True)


atexit.register(_remove_session_folders)


def session_folder(prefix: str) -> Path:
    """A new folder in the temporary directory, removed when this process exits."""
    folder = Path(tempfile.mkdtemp(prefix=prefix))
    SESSION_FOLDERS.append(folder)
    return folder


#: the test ledger of this test session: every evaluation a test runs appends here
TEST_LEDGER = session_folder("denoiser-test-ledger-") / "test_ledger.csv"
