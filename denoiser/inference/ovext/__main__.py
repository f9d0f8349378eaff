"""``python -m denoiser.inference.ovext`` (``make ovext``): build the OpenVINO extension ahead of
time into its cache (``$DENOISER_CACHE/ovext``, see the package docstring), as a package
maintainer or an image build would, instead of on first use. Prints the library's path (exit 0)
or one line saying why it cannot be built (exit 1)."""

from __future__ import annotations

import sys

from denoiser.inference.ovext import kernel_extension, unavailable_reason


def main() -> int:
    path = kernel_extension()
    if path is None:
        print(f"error: the OpenVINO extension cannot be built: {unavailable_reason()}", file=sys.stderr)
        return 1
    print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
