"""warp_to_current: backward motion convention, bilinear sampling, zeros outside."""

import torch

from denoiser.nn.warp import warp_to_current


def test_backward_motion_convention():
    """An object at (x=3, y=4) in frame t-1 moves 2 right and 1 up: at (5, 3) in frame t,
    where motion = (-2, +1) points back to where it was."""
    prev = torch.zeros(1, 1, 8, 8)
    prev[0, 0, 4, 3] = 7.0
    motion = torch.zeros(1, 2, 8, 8)
    motion[0, 0], motion[0, 1] = -2.0, 1.0
    out = warp_to_current(prev, motion)
    assert out[0, 0, 3, 5].item() == 7.0
    assert out.sum().item() == 7.0


def test_integer_shift_with_zeros_outside():
    prev = torch.rand(2, 3, 5, 6) + 1
    motion = torch.zeros(2, 2, 5, 6)
    motion[:, 0] = 1.0  # every pixel was one pixel to the right
    out = warp_to_current(prev, motion)
    assert torch.allclose(out[..., :-1], prev[..., 1:])
    assert torch.equal(out[..., -1], torch.zeros(2, 3, 5))


def test_half_pixel_motion_is_bilinear():
    prev = torch.tensor([[[[0.0, 2.0, 4.0, 6.0]]]])
    motion = torch.zeros(1, 2, 1, 4)
    motion[:, 0] = 0.5
    out = warp_to_current(prev, motion)
    assert torch.allclose(out[0, 0, 0, :3], torch.tensor([1.0, 3.0, 5.0]))


def test_far_and_nonfinite_motion_gives_zeros():
    prev = torch.rand(1, 3, 6, 7) + 1
    for value in (1e9, -1e9, float("inf")):  # +Inf -> 65504 (denoiser.nonfinite), far off-screen
        out = warp_to_current(prev, torch.full((1, 2, 6, 7), value))
        assert torch.equal(out, torch.zeros_like(out)), value
    for value in (float("nan"), float("-inf")):  # NaN, -Inf -> 0 (denoiser.nonfinite): no motion
        out = warp_to_current(prev, torch.full((1, 2, 6, 7), value))
        assert torch.allclose(out, prev), value


def test_sampling_grid_against_a_loop_over_pixels():
    """The grid (built per axis and transposed, the exported graph's form) is, pixel by pixel,
    ``(p + motion + 0.5) * 2 / size - 1`` with x first, motion clamped to 4 frame sizes."""
    from denoiser.nn.warp import sampling_grid

    torch.manual_seed(0)
    motion = torch.randn(2, 2, 5, 7) * 3
    motion[0, 0, 1, 2] = 1e6  # clamped to 4 * max(H, W)
    grid = sampling_grid(motion)
    assert grid.shape == (2, 5, 7, 2)
    for b in range(2):
        for y in range(5):
            for x in range(7):
                mx, my = (float(v.clamp(-28, 28)) for v in motion[b, :, y, x])
                assert abs(float(grid[b, y, x, 0]) - ((x + mx + 0.5) * 2 / 7 - 1)) < 1e-5
                assert abs(float(grid[b, y, x, 1]) - ((y + my + 0.5) * 2 / 5 - 1)) < 1e-5
