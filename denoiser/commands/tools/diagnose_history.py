"""Diagnose a recurrent checkpoint's history on one frame of a sequence, a PNG grid and a table:
``python -m denoiser.commands.tools.diagnose_history``.

Usage::

    python -m denoiser.commands.tools.diagnose_history --ckpt S.ckpt --sequence data/blender/val/fast_101 --layout blender
    python -m denoiser.commands.tools.diagnose_history ckpt=S.ckpt sequence=data/demo/val/<seq> frame=5 out=reports/diagnose

Writes ``<out>/<sequence>_f<frame>.png`` (noisy, output, reference, warped history; the history
blend weights a and b, the disocclusion gate and the coverage; the squared tonemapped errors of
the noisy input, the warped history and the output; the motion magnitude) and ``.md`` (region
statistics: :mod:`denoiser.report.history_diagnosis`). Default frame: the one >= 2 with the largest
mean motion. ``key=value`` arguments are accepted for every option as well as ``--key value``.
A bad input (a missing file, a bad value) is one line ``error: ...`` on stderr and exit 2.
"""

from __future__ import annotations

import sys
from pathlib import Path

from denoiser.commands.app import CommandParser, report_user_error
from denoiser.errors import UserError


def parse_args(argv):
    p = CommandParser("denoiser.commands.tools.diagnose_history", __doc__)
    p.add_argument("--ckpt", required=True, type=Path, help="checkpoint of a recurrent Denoiser")
    p.add_argument("--sequence", required=True, type=Path, help="a labeled sequence directory")
    p.add_argument("--layout", default="native", help="native (default) or blender")
    p.add_argument("--frame", type=int, default=None, help="frame index (default: largest motion among frames >= 2)")
    p.add_argument("--out", type=Path, default=Path("reports/diagnose"), help="output folder (default reports/diagnose)")
    p.add_argument("--trust-checkpoint", action="store_true", help="load a checkpoint the safe loader refuses")
    return p.parse_args(argv)


def main(argv=None) -> int:
    args = parse_args(argv)
    from denoiser.report.history_diagnosis import diagnose

    try:
        result = diagnose(args.ckpt, args.sequence, args.layout, args.out, args.frame, trust=args.trust_checkpoint)
    except UserError as e:  # ExrError and ConfigError included
        report_user_error(e)
    print(result["markdown"].read_text(), end="")
    print(f"wrote {result['png']} and {result['markdown']} (frame {result['frame']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
