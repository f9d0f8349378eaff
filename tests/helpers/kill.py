"""Killing a command mid-run (SIGKILL, no chance to clean up), for the crash-safety tests."""

from __future__ import annotations

import os
import signal
import subprocess
import time


def kill_when(argv: list[str], ready, timeout: float = 240.0, env=None) -> bool:
    """Start ``argv``, SIGKILL it as soon as ``ready()`` is true; True if it was still running then."""
    proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, start_new_session=True)
    deadline = time.monotonic() + timeout
    try:
        while not ready():
            if proc.poll() is not None:
                raise AssertionError(f"finished before the kill: {proc.stderr.read().decode()[-2000:]}")
            if time.monotonic() > deadline:
                raise AssertionError("timed out waiting for the first output")
            time.sleep(0.005)
        running = proc.poll() is None
        os.killpg(proc.pid, signal.SIGKILL)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL or not running
    return running
