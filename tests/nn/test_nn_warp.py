"""warp_to_current / warp_all: backward motion convention, bilinear sampling, zeros outside,
coverage of the bilinear footprint, discarded items."""

import math

import torch
import torch.nn.functional as F

from denoiser.nn.warp import coverage, sample_positions, sampling_grid, warp_all, warp_to_current


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


def _motions():
    torch.manual_seed(0)
    motion = torch.randn(2, 2, 9, 13) * 4  # sub-pixel offsets, many footprints across the border
    motion[0, :, 2:4, 3:6] = torch.tensor([-3.0, 2.0]).view(2, 1, 1)  # whole-pixel offsets
    motion[1, 0, 0, 0] = 1e6  # clamped: far off the image
    motion[1, 1, 5, 5] = float("nan")  # -> 0
    return motion


def test_coverage_against_a_loop_over_pixels():
    """coverage is, pixel by pixel, the summed bilinear weight of the in-image taps of the
    sample position p + motion(p)."""
    motion = _motions()
    h, w = motion.shape[-2:]
    sx, sy = sample_positions(motion)
    cover = coverage(sx, sy)
    for b in range(2):
        for y in range(h):
            for x in range(w):
                px, py = float(sx[b, 0, y, x]), float(sy[b, 0, y, x])
                x0, y0 = math.floor(px), math.floor(py)
                fx, fy = px - x0, py - y0
                ref = sum(wx * wy for i, wx in ((x0, 1 - fx), (x0 + 1, fx)) for j, wy in ((y0, 1 - fy), (y0 + 1, fy))
                          if 0 <= i < w and 0 <= j < h)
                assert abs(float(cover[b, 0, y, x]) - ref) < 1e-5, (b, y, x)


def test_coverage_is_warping_a_constant_image():
    """The same numbers as grid_sample of ones (what the coverage was computed by before)."""
    motion = _motions()
    ones = F.grid_sample(torch.ones(2, 1, 9, 13), sampling_grid(motion), align_corners=False)
    (warped,), cover = warp_all([torch.ones(2, 1, 9, 13)], motion)
    assert torch.allclose(cover, ones, atol=1e-5) and torch.allclose(warped, ones)
    assert cover.min() >= 0 and cover.max() <= 1 + 1e-6 and (cover == 0).any() and (cover == 1).any()


def test_discarded_items_read_nothing():
    """keep=False: that item's buffers are never read (zeros and coverage 0, even where they hold
    NaN and Inf); the kept item is warped as without keep."""
    motion = torch.randn(2, 2, 6, 7)
    prev = torch.rand(2, 3, 6, 7)
    prev[0] = float("nan")
    prev[0, :, ::2] = float("inf")
    keep = torch.tensor([False, True]).view(2, 1, 1, 1)
    (warped,), cover = warp_all([prev], motion, keep)
    assert torch.equal(warped[0], torch.zeros_like(warped[0])) and torch.equal(cover[0], torch.zeros_like(cover[0]))
    (ref,), ref_cover = warp_all([prev[1:]], motion[1:])
    assert torch.equal(warped[1:], ref) and torch.equal(cover[1:], ref_cover)
