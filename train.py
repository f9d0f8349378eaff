"""``python train.py <overrides>`` from a checkout: the same app as ``denoiser-train``
(:mod:`denoiser.commands.train`)."""

from denoiser.commands.train import main

if __name__ == "__main__":
    main()
