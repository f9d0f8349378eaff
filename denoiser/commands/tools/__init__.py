"""The ``python -m denoiser.commands.tools.<name>`` tools: what the pipelines, studies and checks
run (the summaries, the benchmarks of one part, the diagnoses, the device check, the release's
shipping, the networks' fingerprint), as opposed to the ``denoiser-*`` console scripts of
``pyproject.toml``'s ``[project.scripts]``, which are the modules of ``denoiser/commands/`` itself.
A tool is a Hydra app over ``conf/<name>.yaml`` or an argparse command
(:class:`denoiser.commands.app.CommandParser`); like every command it imports the library, never
another command.
"""
