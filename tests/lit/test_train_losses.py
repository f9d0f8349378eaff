"""Training losses (denoiser.lit.losses): formulas, masking, warping convention, adversarial objectives."""

from __future__ import annotations

import pytest
import torch

from denoiser.lit.losses import (
    DenoiseLoss,
    HingeAdversarial,
    WassersteinGP,
    feature_loss,
    gradient_loss,
    hdr_loss,
    masked_mean,
    smape,
    temporal_loss,
    warp_previous,
)


def test_smape_formula_and_per_item():
    x = torch.tensor([[[1.0, 3.0]], [[2.0, 2.0]]])  # [B=2, 1, 2]
    y = torch.tensor([[[1.0, 1.0]], [[0.0, 2.0]]])
    expected = torch.tensor([(0 + 2 / 4.01) / 2, (2 / 2.01 + 0) / 2])
    assert torch.allclose(smape(x, y), expected)
    # computed in float32 even for half inputs
    assert smape(x.half(), y.half()).dtype == torch.float32


def test_gradient_loss_zero_for_offset_invariant_edges_and_positive_otherwise():
    img = torch.rand(2, 3, 3, 8, 8)
    assert torch.allclose(gradient_loss(img, img), torch.zeros(2))
    blurred = img.mean(dim=-1, keepdim=True).expand_as(img)
    assert (gradient_loss(blurred, img) > 0).all()


def test_warp_previous_follows_backward_motion():
    prev = torch.arange(8 * 8, dtype=torch.float32).view(1, 1, 8, 8)
    motion = torch.zeros(1, 2, 8, 8)
    motion[:, 0] = 2.0  # the surface at p was 2 pixels to the right in frame t-1
    warped, valid = warp_previous(prev, motion)
    assert torch.allclose(warped[0, 0, :, :6], prev[0, 0, :, 2:])
    assert valid[0, 0, :, :6].eq(1).all() and valid[0, 0, :, 6:].eq(0).all()


def test_temporal_loss_zero_when_output_moves_like_reference_and_ignores_resets():
    b, t, h, w = 1, 3, 8, 8
    base = torch.rand(b, 3, h, w + 4) + 0.1
    motion = torch.zeros(b, t, 2, h, w)
    motion[:, :, 0] = -1.0  # content moves one pixel right per frame
    ref = torch.stack([base[..., 2 - i: 2 - i + w] for i in range(t)], dim=1)
    assert temporal_loss(ref, ref, motion).abs().max() < 1e-6
    flicker = ref.clone()
    flicker[:, 1] *= 1.5
    assert temporal_loss(flicker, ref, motion)[0] > 0.05
    # the flickering frame is a reset (a cut): its difference to frame 0 is not scored,
    # but frame 2 vs frame 1 still is
    reset = torch.tensor([[True, True, False]])
    only_second = temporal_loss(flicker, ref, motion, reset)
    assert only_second[0] > 0.05
    assert torch.allclose(only_second, temporal_loss(flicker[:, 1:], ref[:, 1:], motion[:, 1:]))
    reset_all = torch.tensor([[True, True, True]])
    assert temporal_loss(flicker, ref, motion, reset_all).eq(0).all()
    assert temporal_loss(ref[:, :1], ref[:, :1], motion[:, :1]).eq(0).all()


def test_denoise_loss_weights_and_absent_terms():
    pred, target = torch.rand(2, 2, 3, 8, 8), torch.rand(2, 2, 3, 8, 8)
    motion = torch.zeros(2, 2, 2, 8, 8)
    full = DenoiseLoss(1.0, 0.5, 0.25)(pred, target, motion)
    assert set(full) == {"smape", "gradient", "temporal"}
    assert torch.allclose(full["smape"], smape(pred, target))
    assert torch.allclose(full["gradient"], 0.5 * gradient_loss(pred, target))
    only = DenoiseLoss(2.0, 0.0, 0.0)(pred, target, motion)
    assert set(only) == {"smape"} and torch.allclose(only["smape"], 2 * smape(pred, target))


def test_hdr_term_is_off_by_default_and_weighted():
    pred, target = torch.rand(2, 2, 3, 8, 8), torch.rand(2, 2, 3, 8, 8)
    motion = torch.zeros(2, 2, 2, 8, 8)
    assert "hdr" not in DenoiseLoss()(pred, target, motion)
    terms = DenoiseLoss(hdr_weight=0.5)(pred, target, motion)
    assert torch.allclose(terms["hdr"], 0.5 * hdr_loss(pred, target))
    assert hdr_loss(target, target).eq(0).all() and (hdr_loss(pred, target) > 0).all()


def test_hdr_term_bounded_with_fireflies_and_finite_gradient():
    """A 1e6 firefly adds at most 1 / pixels to the term; every gradient stays finite."""
    target = torch.rand(2, 3, 3, 16, 16) * 0.5
    pred = target.clone()
    pred[:, :, :, 8, 8] = 1e6
    pred[1, :, :, 3, 3] = 1e30
    pred.requires_grad_(True)
    loss = hdr_loss(pred, target)
    assert torch.isfinite(loss).all() and (loss >= 0).all() and (loss <= 2 / 256 + 1e-6).all()
    loss.sum().backward()
    assert torch.isfinite(pred.grad).all()
    # exposure invariance (up to the exposure floor HDR_EPS): scaling both together changes ~nothing
    x, y = torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 8)
    torch.testing.assert_close(hdr_loss(x * 1000, y * 1000), hdr_loss(x, y), rtol=5e-3, atol=1e-6)
    # black target: still bounded by 1
    assert hdr_loss(torch.full((1, 3, 4, 4), 1e6), torch.zeros(1, 3, 4, 4)).item() <= 1.0


def test_masked_mean():
    v = torch.tensor([1.0, 3.0, 5.0])
    assert masked_mean(v, torch.tensor([True, False, True])) == 3.0
    assert masked_mean(v, torch.tensor([False, False, False])) == 0.0
    assert masked_mean(v, None) == 3.0


@pytest.mark.parametrize("objective", [HingeAdversarial(), WassersteinGP(gp_weight=10.0)])
def test_adversarial_objectives_train_a_critic(objective):
    torch.manual_seed(0)
    critic = torch.nn.Sequential(torch.nn.Conv2d(3, 8, 3, padding=1), torch.nn.LeakyReLU(0.2),
                                 torch.nn.Conv2d(8, 1, 3, padding=1))
    real = torch.rand(4, 3, 8, 8) + 1.0
    fake = torch.rand(4, 3, 8, 8) * 0.1
    opt = torch.optim.Adam(critic.parameters(), lr=1e-2)
    first = None
    for _ in range(30):
        loss = objective.critic_loss(critic, real, fake)
        first = first if first is not None else float(loss.detach())
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert float(loss) < first
    # after training, the critic scores real higher than fake; the generator loss is -mean D(fake)
    with torch.no_grad():
        assert critic(real).mean() > critic(fake).mean()
        assert torch.isclose(objective.generator_loss(critic, fake), -critic(fake).mean())


def test_feature_loss_scale_invariant():
    t = torch.rand(2, 4, 8, 8)
    s = t + 0.1 * torch.randn_like(t)
    assert torch.isclose(feature_loss(s, t), feature_loss(10 * s, 10 * t), rtol=1e-2)
    assert feature_loss(t, t) == 0


@pytest.mark.parametrize("model, lever", [("student", "hdr_loss"), ("distill", "hdr_loss_distill")])
def test_hdr_loss_levers_turn_the_term_on(model, lever):
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from denoiser.configs import compose_config

    def losses(cfg):
        loss = OmegaConf.to_container(cfg.model.loss, resolve=True)
        return [loss] if model == "student" else [loss["kd"], loss["gt"]]

    base = ["output_dir=/tmp/denoiser-test-hdr", f"model={model}"]
    for cfg_loss in losses(compose_config(base, "train")):
        assert instantiate(cfg_loss).weights["hdr"] == 0.0
    for cfg_loss in losses(compose_config([*base, f"lever={lever}"], "train")):
        assert instantiate(cfg_loss).weights["hdr"] == 0.5
