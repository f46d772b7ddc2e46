"""relMSE (SPEC 7) and the Eq. 8 loss of paper 002 on hand-computed examples."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from ppmrecon.metrics import relmse, relmse_map, relmse_scaled, relmse_trimmed
from ppmrecon.train.loss import block_log_l1, relative_log_l1, relative_log_l1_map


def test_relmse_one_pixel_by_hand():
    est = np.array([[[1.0, 2.0, 3.0]]])
    ref = np.array([[[1.0, 1.0, 1.0]]])
    # mean_l (0, 1, 4) = 5/3 over (mean_l ref)^2 + 0.01 = 1.01
    assert relmse(est, ref) == pytest.approx((5 / 3) / 1.01, rel=1e-12)


def test_relmse_averages_pixels_not_channels():
    ref = np.array([[[0.0, 0.0, 0.0], [2.0, 2.0, 2.0]]])           # (1, 2, 3)
    est = np.array([[[0.1, 0.1, 0.1], [2.0, 2.0, 5.0]]])
    first = 0.01 / 0.01                                              # 1.0
    second = (9 / 3) / (4 + 0.01)
    assert relmse(est, ref) == pytest.approx((first + second) / 2, rel=1e-12)
    np.testing.assert_allclose(relmse_map(est, ref), [[first, second]], rtol=1e-12)


def test_relmse_zero_for_identical_and_positive_otherwise():
    rng = np.random.default_rng(1)
    ref = rng.random((5, 6, 3))
    assert relmse(ref, ref) == 0.0
    assert relmse(ref + 1e-3, ref) > 0.0


def test_relmse_numpy_and_torch_agree_with_channel_axis():
    rng = np.random.default_rng(2)
    ref = rng.random((4, 5, 3)).astype(np.float32) * 10
    est = ref + rng.standard_normal((4, 5, 3)).astype(np.float32)
    expected = relmse(est, ref)
    as_tensor = relmse(torch.from_numpy(est).permute(2, 0, 1)[None], torch.from_numpy(ref).permute(2, 0, 1)[None],
                       channel_axis=1)
    assert isinstance(as_tensor, torch.Tensor)
    assert float(as_tensor) == pytest.approx(expected, rel=1e-5)


def test_relmse_is_differentiable_in_torch():
    ref = torch.rand(1, 3, 4, 4)
    est = (ref + 0.5).requires_grad_()
    relmse(est, ref, channel_axis=1).backward()
    assert est.grad is not None and float(est.grad.abs().sum()) > 0


def test_relmse_rejects_shape_mismatch():
    with pytest.raises(ValueError, match="shapes differ"):
        relmse(np.zeros((2, 2, 3)), np.zeros((2, 3, 3)))


def _pixel(values) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64).view(1, 3, 1, 1)


def test_loss_by_hand_black_target():
    e = math.e
    pred, target = _pixel([e - 1, e * e - 1, 0.0]), _pixel([0.0, 0.0, 0.0])
    # |1 - 0|, |2 - 0|, 0 over (0 + 0.01): mean of 100, 200, 0
    assert float(relative_log_l1(pred, target)) == pytest.approx(100.0, rel=1e-12)


def test_loss_by_hand_lit_target():
    e = math.e
    pred, target = _pixel([0.0, e - 1, e ** 3 - 1]), _pixel([e - 1] * 3)
    # log targets are 1, mean 1; |0 - 1|, 0, |3 - 1| over 1.01
    assert float(relative_log_l1(pred, target)) == pytest.approx((1 + 0 + 2) / 3 / 1.01, rel=1e-12)


def test_loss_per_pixel_normaliser_uses_that_pixels_target():
    e = math.e
    target = torch.tensor([[[[0.0, e - 1]]] * 3], dtype=torch.float64)  # (1, 3, 1, 2): pixel 0 black, pixel 1 lit
    pred = target + torch.tensor([[[[e - 1, 0.0]]] * 3], dtype=torch.float64)  # only pixel 0 is off
    per = relative_log_l1_map(pred, target)
    np.testing.assert_allclose(per[0, :, 0, 0].numpy(), [1 / 0.01] * 3, rtol=1e-12)
    np.testing.assert_allclose(per[0, :, 0, 1].numpy(), [0.0] * 3, atol=1e-15)


def test_loss_clips_negative_prediction_at_zero():
    target = torch.rand(1, 3, 3, 3) + 0.5
    neg = torch.full_like(target, -5.0, requires_grad=True)
    assert float(relative_log_l1(neg.detach(), target)) == pytest.approx(float(relative_log_l1(torch.zeros_like(target), target)))
    relative_log_l1(neg, target).backward()
    assert float(neg.grad.abs().max()) == 0.0          # below zero the clipped loss is flat


def test_loss_zero_for_exact_and_gradient_sign():
    target = torch.rand(2, 3, 4, 4) * 3
    assert float(relative_log_l1(target.clone(), target)) == 0.0
    pred = (target + 0.1).requires_grad_()
    relative_log_l1(pred, target).backward()
    assert bool((pred.grad > 0).all())                  # over-estimates are pushed down


def test_trimmed_relmse_drops_only_the_worst_pixels():
    ref = np.full((100, 100, 3), 0.5)
    est = ref + 0.1
    est[3, 7] = 1e4                                   # one firefly among 10^4 pixels
    plain, trimmed = relmse(est, ref), relmse_trimmed(est, ref, discard=1e-4)
    assert plain > 1e3
    assert trimmed == pytest.approx(0.01 / 0.26, rel=1e-12)
    assert relmse_trimmed(est, ref, discard=0.0) == pytest.approx(plain, rel=1e-12)


def test_block_loss_sees_a_smooth_bias_and_not_zero_mean_noise():
    """The 8x8 block-mean term of the training loss: 0 for a perfect prediction, close
    to 0 for +-10% checkerboard noise around the target (averages out in a block) while
    Eq. 8 charges it, and as large as Eq. 8 for a uniform 2% darkening."""
    target = torch.full((2, 3, 16, 24), 0.8)
    assert float(block_log_l1(target.clone(), target)) == 0.0
    checker = (torch.arange(16)[:, None] + torch.arange(24)[None, :]) % 2 * 2 - 1
    noisy = target * (1 + 0.1 * checker)
    assert float(block_log_l1(noisy, target)) < 0.01 * float(relative_log_l1(noisy, target))
    dark = target * 0.98
    assert float(block_log_l1(dark, target)) == pytest.approx(float(relative_log_l1(dark, target)), rel=1e-4)
    with pytest.raises(ValueError, match="smaller than one 8x8 block"):
        block_log_l1(target[..., :4, :4], target[..., :4, :4])


def test_scaled_relmse_does_not_depend_on_the_units_and_plain_relmse_does():
    """Issue 12's data span radiance 1e-4 to 1e4: a dark scene's plain relMSE scores only
    its few pixels above 0.1, so the same noisy render scaled by 1e4 scores differently;
    the scaled figure is the same, and it equals plain relMSE on an image of mean 1."""
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.0, 2.0, (16, 16, 3))
    ref[0, 0] = 50.0                                     # one bright pixel
    est = ref * rng.uniform(0.5, 1.5, ref.shape)
    plain = [relmse(est * s, ref * s) for s in (1e-4, 1.0, 1e4)]
    scaled = [relmse_scaled(est * s, ref * s) for s in (1e-4, 1.0, 1e4)]
    assert max(plain) > 10 * min(plain)
    assert scaled == pytest.approx([scaled[1]] * 3, rel=1e-9)
    m = ref.mean()
    assert relmse_scaled(est, ref) == pytest.approx(relmse(est / m, ref / m))
    black = np.zeros_like(ref)
    assert relmse_scaled(est, black) == pytest.approx(relmse(est, black))


def test_deciding_pixels_counts_the_fewest_pixels_whose_excess_makes_an_image_worse():
    """0 where ours is no worse; 1 where one pixel's excess outweighs everything else; the
    count grows with a spread-out (systematic) excess."""
    from ppmrecon.metrics import deciding_pixels

    excess = np.full((16, 16), -0.01)
    assert deciding_pixels(excess) == 0                    # better everywhere
    excess[3, 4] = 1.0                                      # one pixel: 1.0 against 2.55 gained... not enough
    assert deciding_pixels(excess) == 0
    excess[3, 4] = 10.0                                     # ... now it decides alone
    assert deciding_pixels(excess) == 1
    spread = np.full((16, 16), 0.01)                        # worse everywhere, by a little
    assert deciding_pixels(spread) == 256
    spread[0, 0] = 0.5                                      # a large pixel first, then the rest
    assert deciding_pixels(spread) == 1 + 255
