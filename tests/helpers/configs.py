"""Entry configs of the commands composed as a test gives them (:func:`compose_command`)."""

from helpers.session import TEST_LEDGER


def compose_command(name: str, overrides, threads: int | None = None):
    """The entry config ``conf/<name>.yaml`` composed with ``overrides`` (plus ``threads=N`` when given).
    ``eval`` gets ``purpose=test-suite`` and the session's :data:`~helpers.session.TEST_LEDGER` unless
    the test gives them."""
    from denoiser.configs import compose_config

    extra = [f"threads={threads}"] if threads else []
    if name == "eval":
        given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
        extra += [o for key, o in (("purpose", "purpose=test-suite"), ("ledger", f"ledger={TEST_LEDGER}"))
                  if key not in given]
    return compose_config([*overrides, *extra], name)
