"""How a checkpoint's output follows the noise level of its input: ``python -m denoiser.commands.tools.noise_response``.

Usage::

    python -m denoiser.commands.tools.noise_response ckpt=S.ckpt sequences=[data/blender/val/fast_101,data/blender/val/fast_102] \\
        layout=blender factors=[0.25,0.5,1,2] grey=true out=reports/noise_response.md plot=reports/noise_response.png

Prints the table (and writes it to ``out`` when given): per sequence and factor f, the PSNR of the
input (the residual against the reference scaled by f) and of the output, on frame 0 and over
frames 2+; with ``grey=true``, the same for the sequence in grey (colour, albedo and reference as
their luminance) (:mod:`denoiser.report.noise_response`). ``key=value`` arguments are accepted for
every option as well as ``--key value``. A bad input (a missing file, a bad value) is one line
``error: ...`` on stderr and exit 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

from denoiser.commands.app import CommandParser, report_user_error
from denoiser.errors import UserError


def _list(text: str) -> list[str]:
    return [t.strip() for t in text.strip().strip("[]").split(",") if t.strip()]


def parse_args(argv):
    p = CommandParser("denoiser.commands.tools.noise_response", __doc__)
    p.add_argument("--ckpt", required=True, type=Path, help="checkpoint of a Denoiser")
    p.add_argument("--sequences", required=True, type=_list, help="[dir,dir,...]: labeled sequence directories")
    p.add_argument("--layout", default="native", help="native (default) or blender")
    p.add_argument("--factors", type=_list, default=["0.25", "0.5", "1", "2"], help="[f,...] (default [0.25,0.5,1,2])")
    p.add_argument("--out", type=Path, default=None, help="also write the table here")
    p.add_argument("--grey", default="false", help="true: the grey version of every sequence too")
    p.add_argument("--plot", type=Path, default=None, help="also write a PNG: output against input PSNR")
    p.add_argument("--trust-checkpoint", action="store_true", help="load a checkpoint the safe loader refuses")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    from denoiser.report.noise_response import run

    try:
        try:
            factors = [float(f) for f in args.factors]
        except ValueError:
            raise UserError(f"factors: not numbers: {args.factors}") from None
        if args.grey.lower() not in ("true", "false"):
            raise UserError(f"grey: true or false, got {args.grey}")
        _, text = run(args.ckpt, args.sequences, args.layout, factors, args.out, trust=args.trust_checkpoint,
                      grey_too=args.grey.lower() == "true", plot=args.plot)
    except UserError as e:  # ExrError and ConfigError included
        report_user_error(e)
    print(text, end="")
    for path in (args.out, args.plot):
        if path is not None:
            print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
