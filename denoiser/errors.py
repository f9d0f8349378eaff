"""User-facing errors: one clear line naming the file or key and the problem.

Commands catch :class:`UserError` at the top (see :mod:`denoiser.commands.app`) and print
``error: <message>`` on stderr with a non-zero exit instead of a traceback. Set
``DENOISER_DEBUG=1`` to get the full traceback.
"""


class UserError(Exception):
    """A mistake in the user's input (file, config, checkpoint), not a bug."""


class ExrError(UserError):
    """An EXR file is missing, unreadable, or lacks what the caller needs."""

    def __init__(self, path, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


class ConfigError(UserError):
    """A configuration value is invalid (names the key or file)."""


def first_line(exc: BaseException, limit: int = 200) -> str:
    """The first line of an exception's message (at most ``limit`` characters), else its type name."""
    text = str(exc).strip()
    return text.splitlines()[0][:limit] if text else type(exc).__name__
