"""A small real checkpoint for the tests that load one (:func:`tiny_checkpoint`)."""


def tiny_checkpoint(path, seed: int = 0, **extra):
    """A checkpoint of ``net=tiny kernel=student`` with the weights of ``torch.manual_seed(seed)``,
    written by :func:`denoiser.checkpoint.save_checkpoint` (``extra`` keys go to its top level)."""
    import torch

    from denoiser.checkpoint import save_checkpoint
    from denoiser.configs import build_net, compose_net_config

    cfg = compose_net_config("tiny", "student")
    torch.manual_seed(seed)
    return save_checkpoint(path, build_net(cfg), cfg, **extra)
