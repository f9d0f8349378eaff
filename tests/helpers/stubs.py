"""Stub executables that log how they were called (the pipeline tests run stubs for the commands)."""

from pathlib import Path

# The first lines of every stub executable: it appends its name and arguments as one record
# (NUL-separated, newline-ended) to $STUB_LOG. Pipelines run stubs side by side, so the
# record is written under an exclusive lock: two unlocked writers interleave and lose calls.
STUB_HEADER = """#!/usr/bin/env bash
{ flock 9; printf '%s\\0' "$(basename "$0")" "$@" >&9; printf '\\n' >&9; } 9>> "$STUB_LOG"
"""


def stub_calls(log: Path) -> list[list[str]]:
    """The calls :data:`STUB_HEADER` logged to ``log``, in order: ``[command, *args]`` each."""
    return [line.strip("\0").split("\0") for line in log.read_text().splitlines() if line]
