"""The consistent combiner (paper 002 Eq. 6, Appendix A).

References are computed here independently, in numpy: explicit edge padding and an
explicit loop over window offsets, float64 softmax and terms.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from ppmrecon.model.combine import (
    UNFOLD_BUDGET_BYTES, combine, combine_with_weights, logit_channels, term_bounds, window_size,
)

SCALES = [0.0, 1e-6, 1.0, 1e3, 1e8]




def reference(y: np.ndarray, z: np.ndarray, logits: np.ndarray, k: int):
    """Eq. 6 by brute force for one image: y (3,H,W), z (4,3,H,W), logits (4K^2,H,W).

    Returns the float64 combination, the float64 terms, the terms evaluated in float32
    as ``(y_i - z_i) + z_c`` (the combiner's stated evaluation) and, per pixel, the
    largest input magnitude in the window (for rounding tolerances).
    """
    _, h, w = y.shape
    r = k // 2
    y64, z64 = y.astype(np.float64), z.astype(np.float64)
    yp = np.pad(y, ((0, 0), (r, r), (r, r)), mode="edge")
    zp = np.pad(z, ((0, 0), (0, 0), (r, r), (r, r)), mode="edge")
    t64 = np.empty((k * k, 4, 3, h, w))
    t32 = np.empty((k * k, 4, 3, h, w), dtype=np.float32)
    mag = np.abs(z64).max(0)
    for a in range(k):
        for b in range(k):
            o = a * k + b
            ys, zs = yp[:, a:a + h, b:b + w], zp[:, :, a:a + h, b:b + w]
            t64[o] = ys.astype(np.float64)[None] + z64 - zs.astype(np.float64)
            t32[o] = (ys[None] - zs).astype(np.float32) + z
            mag = np.maximum(mag, np.maximum(np.abs(ys), np.abs(zs).max(0)))
    lg = logits.astype(np.float64).reshape(k * k, 4, 1, h, w)
    wts = np.exp(lg - lg.max(axis=(0, 1), keepdims=True))
    wts /= wts.sum(axis=(0, 1), keepdims=True)
    return (wts * t64).sum((0, 1)), t64, t32, mag


def random_case(rng: np.random.Generator, h: int, w: int, k: int, scale: float, logit_scale: float,
                extreme: bool = False):
    y = (rng.random((3, h, w)) * scale).astype(np.float32)
    z = (rng.random((4, 3, h, w)) * scale).astype(np.float32)
    if scale > 0 and rng.random() < 0.5:  # fireflies next to dark pixels
        y.reshape(-1)[rng.integers(0, y.size, max(1, y.size // 10))] = 1e8
        z.reshape(-1)[rng.integers(0, z.size, max(1, z.size // 20))] = 1e8
    if extreme:
        logits = rng.choice([-1e4, 1e4], size=(4 * k * k, h, w)).astype(np.float32)
    else:
        logits = (rng.standard_normal((4 * k * k, h, w)) * logit_scale).astype(np.float32)
    return y, z, logits


def run(y, z, logits, method="auto"):
    out = combine_with_weights(torch.from_numpy(y)[None], torch.from_numpy(z)[None],
                               torch.from_numpy(logits)[None], method=method)
    return out.image[0].numpy(), out.weights_per_z[0].numpy()


@settings(max_examples=200, deadline=None)
@given(k=st.sampled_from([1, 3, 5, 7, 11, 19]), h=st.integers(1, 11), w=st.integers(1, 11),
       scale=st.sampled_from(SCALES), logit_scale=st.sampled_from([0.0, 1.0, 30.0, 1e4]),
       extreme=st.booleans(), method=st.sampled_from(["loop", "unfold"]), seed=st.integers(0, 2**31))
def test_output_lies_between_smallest_and_largest_term(k, h, w, scale, logit_scale, extreme, method, seed):
    rng = np.random.default_rng(seed)
    y, z, logits = random_case(rng, h, w, k, scale, logit_scale, extreme)
    out, weights = run(y, z, logits, method)
    ref, t64, t32, mag = reference(y, z, logits, k)
    assert np.isfinite(out).all()
    # exactly inside the terms as evaluated in float32 (no tolerance)
    assert (out >= t32.min((0, 1))).all() and (out <= t32.max((0, 1))).all()
    # and equal to Eq. 6 up to float32 rounding of the window's magnitudes
    np.testing.assert_array_less(np.abs(out - ref), 2e-5 * mag + 1e-30)
    np.testing.assert_allclose(weights.sum(0), 1.0, rtol=1e-5)
    assert (weights >= 0).all()


@pytest.mark.parametrize("scale", SCALES)
@pytest.mark.parametrize("method", ["loop", "unfold"])
def test_identical_inputs_come_out_unchanged(scale, method):
    rng = np.random.default_rng(3)
    k = 7
    t = (rng.random((3, 9, 6)) * scale).astype(np.float32)
    z = np.broadcast_to(t, (4, 3, 9, 6)).copy()
    logits = (rng.standard_normal((4 * k * k, 9, 6)) * 50).astype(np.float32)
    out, _ = run(t, z, logits, method)
    np.testing.assert_array_equal(out, t)


@pytest.mark.parametrize("method", ["loop", "unfold"])
def test_offset_correlated_inputs_return_the_centre(method):
    """~y = t, ~z^j = t + c_j: every term is t_c + c_j - c_j = t_c, whatever the weights."""
    rng = np.random.default_rng(4)
    k = 5
    t = (rng.random((3, 8, 10)) * 100).astype(np.float32)
    z = (t[None] + np.array([0.5, 3.0, 20.0, 1e3], dtype=np.float32).reshape(4, 1, 1, 1)).astype(np.float32)
    logits = (rng.standard_normal((4 * k * k, 8, 10)) * 5).astype(np.float32)
    out, _ = run(t, z, logits, method)
    np.testing.assert_allclose(out, t, rtol=0, atol=1e3 * 4 * np.finfo(np.float32).eps)


@pytest.mark.parametrize("k,h,w", [(1, 4, 4), (5, 6, 9), (19, 3, 2), (19, 1, 1), (3, 1, 7)])
def test_constant_logits_give_the_uniform_average_of_the_terms(k, h, w):
    rng = np.random.default_rng(5)
    y, z, _ = random_case(rng, h, w, k, 10.0, 0.0)
    logits = np.full((4 * k * k, h, w), 7.25, dtype=np.float32)
    out, weights = run(y, z, logits, "loop")
    _, t64, _, mag = reference(y, z, logits, k)
    np.testing.assert_array_less(np.abs(out - t64.mean((0, 1))), 2e-5 * mag + 1e-30)
    np.testing.assert_allclose(weights, 0.25, rtol=1e-6)


def test_border_uses_replicate_padding_not_zeros():
    """A bright image with weight only on the top-left offset: the corner pixel sees itself."""
    k = 3
    y = np.full((3, 2, 2), 5.0, dtype=np.float32)
    y[:, 1, 1] = 9.0
    z = np.zeros((4, 3, 2, 2), dtype=np.float32)
    logits = np.full((4 * k * k, 2, 2), -1e4, dtype=np.float32)
    logits[0] = 0.0                                  # offset (-1, -1) of ~z^1
    out, _ = run(y, z, logits)
    np.testing.assert_array_equal(out[:, 0, 0], [5.0] * 3)    # clamped to itself, not to 0
    np.testing.assert_array_equal(out[:, 1, 1], [5.0] * 3)    # its upper-left neighbour


@pytest.mark.parametrize("k", [1, 3, 9])
def test_loop_and_unfold_paths_agree(k):
    torch.manual_seed(6)
    y = torch.rand(2, 3, 13, 17) * 50
    z = torch.rand(2, 4, 3, 13, 17) * 50
    logits = torch.randn(2, logit_channels(k), 13, 17) * 4
    a = combine_with_weights(y, z, logits, method="loop")
    b = combine_with_weights(y, z, logits, method="unfold")
    torch.testing.assert_close(a.image, b.image, rtol=1e-5, atol=1e-5 * 50)
    torch.testing.assert_close(a.weights_per_z, b.weights_per_z, rtol=1e-5, atol=1e-7)
    ga = torch.autograd.grad(combine(y, z, logits.requires_grad_(), "loop").sum(), logits)[0]
    gb = torch.autograd.grad(combine(y, z, logits, "unfold").sum(), logits)[0]
    torch.testing.assert_close(ga, gb, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("method", ["loop", "unfold"])
def test_consume_overwrites_only_when_asked_and_changes_no_result(method):
    torch.manual_seed(8)
    y, z = torch.rand(1, 3, 9, 11) * 5, torch.rand(1, 4, 3, 9, 11) * 5
    logits = torch.randn(1, logit_channels(3), 9, 11) * 30
    kept = logits.clone()
    plain = combine_with_weights(y, z, logits, method=method)
    assert torch.equal(logits, kept)                          # the caller's logits untouched
    consumed = combine_with_weights(y, z, logits, method=method, consume=True)
    assert torch.equal(consumed.image, plain.image) and torch.equal(consumed.weights_per_z, plain.weights_per_z)
    assert not torch.equal(logits, kept)                      # the weights were formed in place
    grad_in = kept.clone().requires_grad_()                   # autograd: never in place
    combine_with_weights(y, z, grad_in, method=method, consume=True).image.sum().backward()
    assert torch.equal(grad_in.detach(), kept) and grad_in.grad is not None


@pytest.mark.parametrize("method", ["loop", "unfold"])
def test_gradient_in_logits_matches_finite_differences(method):
    torch.manual_seed(7)
    k = 3
    y = torch.rand(1, 3, 4, 5, dtype=torch.float64)
    z = torch.rand(1, 4, 3, 4, 5, dtype=torch.float64)
    logits = torch.randn(1, logit_channels(k), 4, 5, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda lg: combine(y, z, lg, method), (logits,), eps=1e-6, atol=1e-6,
                                    fast_mode=True)


def test_term_bounds_match_brute_force():
    rng = np.random.default_rng(8)
    k = 5
    y, z, logits = random_case(rng, 7, 6, k, 1e3, 1.0)
    lo, hi = term_bounds(torch.from_numpy(y)[None], torch.from_numpy(z)[None], k)
    _, _, t32, _ = reference(y, z, logits, k)
    np.testing.assert_array_equal(lo[0].numpy(), t32.min((0, 1)))
    np.testing.assert_array_equal(hi[0].numpy(), t32.max((0, 1)))


def test_auto_uses_the_offset_loop_for_large_images(monkeypatch):
    import ppmrecon.model.combine as C

    used = []
    real = C._numerator_loop
    monkeypatch.setattr(C, "_numerator_loop", lambda *a: used.append("loop") or real(*a))
    k = 19
    side = int((UNFOLD_BUDGET_BYTES / (12 * k * k * 4)) ** 0.5) + 2   # just over the unfold budget
    y = torch.zeros(1, 3, side, side)
    z = torch.zeros(1, 4, 3, side, side)
    logits = torch.zeros(1, logit_channels(k), side, side)
    combine(y, z, logits)
    assert used == ["loop"]


def test_window_size_validation():
    assert window_size(4 * 19 * 19) == 19
    for bad in (4 * 4, 4 * 36, 5, 0):
        with pytest.raises(ValueError):
            window_size(bad)
    with pytest.raises(ValueError, match="logits"):
        combine(torch.zeros(1, 3, 4, 4), torch.zeros(1, 4, 3, 4, 4), torch.zeros(1, 4 * 9, 4, 5))
