"""Issue 12: fireflies through the consistent combiner, the firefly guard
(:mod:`ppmrecon.model.guard`) and the scale-free features.

The synthetic buffers are a smooth image (0.1..0.7 per channel) with noise matching
N = 64 passes: ~y has a relative standard error of 1.2 / sqrt(64) = 15% per pixel and
channel, each ~z^j is an independent noisy copy blurred with sigma 1, 1.5, 2, 3 pixels,
and every ``*.V`` layer is that estimate's variance of the mean. A firefly of A x the
image mean is a single-pass event: added to the estimate(s), with V += (A mean)^2.

Tolerance of "no worse than the best input": per pixel and channel,
``|out - clean| <= min_k |X_k - clean| + TOL * clean`` with TOL = 0.25, i.e. 1.7 standard
errors of the noisiest input. On the same images without fireflies the shipped model's
largest excess is 0.13-0.18 x clean (seeds 0-5); the unguarded pipeline with the fireflies
below reaches 0.30-0.63 (measured when these tests were written).
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter

from ppmrecon import buffers as B
from ppmrecon.errors import UsageError
from ppmrecon.metrics import block_means, relmse, relmse_blocks
from ppmrecon.model import checkpoint as C
from ppmrecon.model.cli import main
from ppmrecon.model.combine import combine, term_bounds
from ppmrecon.model.features import FeatureConfig, buffer_scales, from_buffer
from ppmrecon.model.guard import (DEFAULT_ON, GuardConfig, anchor_low_frequencies, find_outliers, finish,
                                  gaussian_lowpass, guard_buffer, guard_estimates, image_scale, local_floor,
                                  median3x3, output_band)
from ppmrecon.model.infer import denoise

SIZE, PASSES = 48, 64
REL_PASS = 1.2                        # relative std of one pass of ~y
SIGMAS = (1.0, 1.5, 2.0, 3.0)         # blur of ~z^1..~z^4 (pixels)
FIREFLIES = [(10, 10), (10, 30), (24, 20), (37, 12), (36, 36)]
TOL = 0.25
WHICH = {"y": [0], "z": [1, 2, 3, 4], "both": [0, 1, 2, 3, 4]}


def synthetic(seed: int = 0, passes: int = PASSES, size: int = SIZE) -> tuple[B.BufferFile, np.ndarray]:
    """(buffer file, clean image (H, W, 3)) as described in the module docstring."""
    rng = np.random.default_rng(seed)
    yy, xx = np.meshgrid(np.linspace(0, 1, size), np.linspace(0, 1, size), indexing="ij")
    clean = (0.4 + 0.3 * np.sin(3 * xx + 1) * np.cos(2 * yy))[..., None] * np.array([1.0, 0.8, 0.6])
    s = REL_PASS / np.sqrt(passes)
    y = clean * (1 + s * rng.standard_normal(clean.shape))
    zs, vs = [], [np.mean((s * clean) ** 2, -1)]
    for sigma in SIGMAS:
        noisy = clean * (1 + s * rng.standard_normal(clean.shape))
        zs.append(np.stack([gaussian_filter(noisy[..., c], sigma, mode="nearest") for c in range(3)], -1))
        vs.append(np.mean((s / (2 * np.sqrt(np.pi) * sigma) * clean) ** 2, -1))   # white noise through the blur
    normal = np.zeros((size, size, 3), np.float32)
    normal[..., 2] = 1
    header = {B.H_VERSION: B.SCHEMA_VERSION, B.H_METHOD: "sppm", B.H_KERNEL: "constant", B.H_PASSES: passes,
              B.H_PHOTONS: 65536, B.H_ALPHA: 2 / 3, B.H_KNN: 20, B.H_SEED: seed, B.H_SCENE: "synthetic",
              B.H_SECONDS: 1.0}
    buf = B.BufferFile(np.clip(np.stack([y] + zs), 0, None).astype(np.float32), np.stack(vs).astype(np.float32),
                       np.full((5, size, size), 0.01, np.float32), np.full((size, size, 3), 0.5, np.float32),
                       normal, np.ones((size, size), np.float32), header)
    return buf, clean.astype(np.float32)


def with_fireflies(buf: B.BufferFile, amp: float, which: str, where=FIREFLIES) -> B.BufferFile:
    """Single-pass fireflies of ``amp`` x the image mean in ~y, in every ~z^j, or in all five."""
    est, var = buf.estimates.copy(), buf.variances.copy()
    f = amp * float(buf.estimates.mean())
    for r, c in where:
        for k in WHICH[which]:
            est[k, r, c] += f
            var[k, r, c] += f * f
    return replace(buf, estimates=est, variances=var)


@pytest.fixture(scope="module")
def shipped():
    """The shipped model, loaded as ``ppmrecon-denoise`` loads it without ``--model``."""
    assert C.DEFAULT_MODEL.is_file(), "the package ships ppmrecon/data/models/default.pt"
    model, _ = C.load_checkpoint(C.DEFAULT_MODEL)
    return model


def excess(out: np.ndarray, buf: B.BufferFile, clean: np.ndarray) -> np.ndarray:
    """How much farther from clean the output is than the best input, per pixel/channel, / clean."""
    best = np.abs(buf.estimates - clean).min(0)
    return (np.abs(out - clean) - best) / clean


# ------------------------------------------------------- the shipped model on fireflies

@pytest.mark.parametrize("mode", ["envelope", "weights", "chooser"])
@pytest.mark.parametrize("amp", [1e3, 1e4, 1e5])
@pytest.mark.parametrize("which", ["y", "z", "both"])
def test_shipped_model_with_guard_is_no_worse_than_the_best_input(shipped, which, amp, mode):
    """In every guide mode: the envelope (the shipped default), Eq. 6 with the network, and
    the envelope with the shipped chooser (opt-in)."""
    buf, clean = synthetic()
    buf = with_fireflies(buf, amp, which)
    out = denoise(buf, shipped, guard=DEFAULT_ON, precision="float32", guide=replace(shipped.guide, mode=mode)).rgb
    ex = excess(out, buf, clean)
    worst = np.unravel_index(np.argmax(ex), ex.shape)
    assert ex.max() <= TOL, f"{ex.max():.3f} x clean farther than the best input at {worst}"
    for r, c in FIREFLIES:        # the firefly itself is gone (in 'both' every input has it)
        assert np.all(np.abs(out[r, c] - clean[r, c]) <= TOL * clean[r, c]), (r, c, out[r, c], clean[r, c])
    # no black dots: nowhere below half of the smallest of its five inputs (or of the
    # truth, where all five carry the firefly); every input is >= 0.1 here
    assert np.all(out >= 0.5 * np.minimum(buf.estimates.min(0), clean))


@pytest.mark.parametrize("which", ["y", "z", "both"])
def test_without_the_guard_the_same_fireflies_do_damage(shipped, which):
    """The failure the guard fixes (so the test above can fail): issue 12. The denoiser
    guide is off too: its spike rule alone already keeps z-only fireflies out."""
    from ppmrecon.model.guide import GuideConfig

    buf, clean = synthetic()
    buf = with_fireflies(buf, 1e4, which)
    out = denoise(buf, shipped, guard=GuardConfig(), guide=GuideConfig(), precision="float32").rgb
    at = np.array([out[r, c].mean() / clean[r, c].mean() for r, c in FIREFLIES])
    if which == "both":                 # present in every term of Eq. 6: passes straight through
        assert np.all(at > 100)         # (no excess over the inputs: they all carry it there)
    else:
        assert excess(out, buf, clean).max() > TOL


def test_the_envelope_without_the_guard_keeps_a_firefly_every_input_has(shipped):
    """The envelope holds the guide between the five estimates: a firefly in all five
    survives it unless the guard replaced it first (so the test above can fail for it)."""
    buf, clean = synthetic()
    buf = with_fireflies(buf, 1e4, "both")
    out = denoise(buf, shipped, guard=GuardConfig(), guide=replace(shipped.guide, mode="envelope")).rgb
    assert all(out[r, c].mean() / clean[r, c].mean() > 100 for r, c in FIREFLIES)


def test_guard_changes_nothing_without_fireflies_but_the_band_and_the_anchor(shipped):
    buf, clean = synthetic(seed=3)
    assert guard_buffer(buf, DEFAULT_ON) is buf
    no_anchor = denoise(buf, shipped, guard=replace(DEFAULT_ON, anchor=0), precision="float32").rgb
    off = denoise(buf, shipped, guard=GuardConfig(), precision="float32").rgb
    assert relmse(no_anchor, clean) <= relmse(off, clean) * 1.01
    # held in the five estimates' range, or (the shipped terms range) in that range widened
    # towards Eq. 6's terms for this render's N (guide.terms_range), of ~y and the ~z^j as the
    # shipped anchor cascade pulled them (infer.buffer_aim)
    from ppmrecon.model.guard import passes_of
    from ppmrecon.model.guide import terms_range, terms_share
    from ppmrecon.model.infer import buffer_aim

    narrow = denoise(buf, shipped, guard=DEFAULT_ON, guide=replace(shipped.guide, terms_passes=0.0, range_sigma=0.0),
                     precision="float32").rgb
    assert np.all(narrow >= buf.estimates.min(0)) and np.all(narrow <= buf.estimates.max(0))
    on = denoise(buf, shipped, guard=DEFAULT_ON, precision="float32").rgb
    assert shipped.guide.terms_passes > 0
    est = torch.from_numpy(buf.estimates).permute(0, 3, 1, 2)[None]
    aim = buffer_aim(buf, shipped.guide, DEFAULT_ON)
    assert aim is not None                                   # the shipped default pulls them
    y, z = est[:, 0], aim.z
    lo, hi = torch.minimum(y, z.amin(1)), torch.maximum(y, z.amax(1))
    assert bool((lo >= est.amin(1)).all() and (hi <= est.amax(1)).all())     # pulled within the range
    # the shipped range also holds each estimate's own noise interval (guide.noise_range)
    assert shipped.guide.range_sigma > 0
    from ppmrecon.model.guard import image_scale
    from ppmrecon.model.guide import noise_range, y_spike_mask
    spikes = y_spike_mask(y, z, shipped.guide, DEFAULT_ON, float(image_scale(est)))
    lo, hi = noise_range(y, z, torch.from_numpy(buf.variances)[None], lo, hi, shipped.guide.range_sigma,
                         rel=shipped.guide.range_sigma_rel, y_out=spikes, width=shipped.guide.range_sigma_width,
                         isolated=shipped.guide.range_sigma_isolated)
    wide_lo, wide_hi = terms_range(y, z, lo, hi, terms_share(passes_of(buf), shipped.guide))
    out = torch.from_numpy(on).permute(2, 0, 1)[None]
    assert bool((out >= wide_lo - 1e-6).all() and (out <= wide_hi + 1e-6).all())
    # The anchor brings ~z^3's low frequencies where they differ from the output's; here every
    # ~z^j is an unbiased blurred copy, so there is no bias for it to remove and it trades
    # the y-mixed guide's low-frequency noise for ~z^3's (relMSE 0.85 -> 0.95 of the best
    # input at seed 3, measured with OIDN(~y) at a fixed quarter of the guide; on real
    # renders it lowers the 8x8-block error, benchmarks/results/guide_y): it may cost, but
    # never past the best input.
    best = min(relmse(x, clean) for x in buf.estimates)
    assert relmse(on, clean) <= best


def test_tiled_equals_untiled_with_the_guard_and_the_new_features():
    from ppmrecon.model.kpn import KPN, Preset

    torch.manual_seed(4)
    cfg = FeatureConfig(scale_free=True, outliers=True)
    model = KPN(Preset("t5", layers=3, filters=8, kernel=3, window=5, final_kernel=1), cfg, DEFAULT_ON).eval()
    buf, _ = synthetic(seed=5, size=40)
    buf = with_fireflies(buf, 1e4, "both", [(12, 13), (12, 26), (0, 39)])      # on tile seams and a corner
    full = denoise(buf, model, tile=10_000, precision="float32")
    for tile in (13, 16):
        tiled = denoise(buf, model, tile=tile, precision="float32")
        np.testing.assert_allclose(tiled.rgb, full.rgb, rtol=1e-5, atol=1e-6)


def test_cli_guard_on_with_the_shipped_model(tmp_path, capsys):
    buf, clean = synthetic()
    src = tmp_path / "fireflies.exr"
    B.write_buffers(src, with_fireflies(buf, 1e4, "both"))
    outs = {}
    for choice in ("on", "model", "off"):
        dst = tmp_path / f"out_{choice}.exr"
        assert main([str(src), "-o", str(dst), "--guard", choice, "--quiet", "--threads", "1"]) == 0
        outs[choice], header = B.read_rgb(dst)
        assert header["ppmrecon.guard"] == ("off" if choice == "off" else "on")   # shipped: trained with it
    np.testing.assert_array_equal(outs["on"], outs["model"])
    for r, c in FIREFLIES:
        assert np.all(np.abs(outs["on"][r, c] - clean[r, c]) <= TOL * clean[r, c])
        assert outs["off"][r, c].mean() > 100 * clean[r, c].mean()
    dst = tmp_path / "out_no_anchor.exr"
    assert main([str(src), "-o", str(dst), "--anchor", "0", "--quiet", "--threads", "1"]) == 0
    no_anchor, header = B.read_rgb(dst)
    assert header["ppmrecon.guard.anchor"] == 0.0 and not np.array_equal(no_anchor, outs["on"])
    assert B.read_rgb(tmp_path / "out_on.exr")[1]["ppmrecon.guard.anchor"] == DEFAULT_ON.anchor
    with pytest.raises(SystemExit):
        main([str(src), "-o", str(dst), "--anchor", "-1"])
    assert main([str(src), "-o", str(dst), "--anchor", "1", "--guard", "off"]) == 2
    assert "--anchor is part of the guard" in capsys.readouterr().err


# ------------------------------------------------------------------ the input guard

def test_fireflies_are_replaced_by_their_median_at_small_n():
    buf, _ = synthetic()
    for which, ks in WHICH.items():
        bad = with_fireflies(buf, 1e3, which)
        est = torch.from_numpy(bad.estimates).permute(0, 3, 1, 2)[None]
        var = torch.from_numpy(bad.variances)[None]
        g = guard_estimates(est, var, torch.tensor([float(PASSES)]), DEFAULT_ON)
        expected = torch.zeros(1, 5, SIZE, SIZE, dtype=torch.bool)
        for r, c in FIREFLIES:
            expected[0, ks, r, c] = True
        assert torch.equal(g.outliers, expected), which
        med, vmed = median3x3(est), median3x3(var)
        for r, c in FIREFLIES:
            for k in ks:
                torch.testing.assert_close(g.estimates[0, k, :, r, c], med[0, k, :, r, c], rtol=0, atol=0)
                assert float(g.variances[0, k, r, c]) == float(vmed[0, k, r, c])
        keep = ~expected[:, :, None].expand_as(est)
        assert torch.equal(g.estimates[keep], est[keep])


def test_a_steady_bright_pixel_is_left_alone(shipped):
    """A small light seen directly: 1e4 x the mean in all five inputs, but 1% standard error."""
    buf, clean = synthetic()
    est, var = buf.estimates.copy(), buf.variances.copy()
    light = 1e4 * float(est.mean())
    est[:, 20, 20] = light
    var[:, 20, 20] = (0.01 * light) ** 2
    steady = replace(buf, estimates=est, variances=var)
    assert guard_buffer(steady, DEFAULT_ON) is steady
    out = denoise(steady, shipped, guard=DEFAULT_ON, precision="float32").rgb
    assert np.all(out[20, 20] >= 0.99 * light)
    # the same value made by one pass (sqrt(V) ~ X) is an outlier
    var[:, 20, 20] = light ** 2
    assert guard_buffer(replace(steady, variances=var), DEFAULT_ON) is not steady


def _random_image(rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
    """Estimates (1, 5, 3, h, w) from 0 to 1e8 (black areas, spikes) and variances (incl. sqrt(V) ~ X)."""
    h, w = (int(v) for v in rng.integers(1, 21, 2))
    est = rng.random((1, 5, 3, h, w)) * 10.0 ** rng.uniform(-4, 4)
    est[rng.random(est.shape) < 0.2] = 0.0
    spikes = rng.random((1, 5, 1, h, w)) < 0.05
    est = np.where(spikes, est * 10.0 ** rng.uniform(2, 4), est).clip(0, 1e8)
    var = (est.mean(2) * rng.uniform(0, 1.5, (1, 5, h, w))) ** 2
    return torch.tensor(est, dtype=torch.float32), torch.tensor(var, dtype=torch.float32)


@pytest.mark.parametrize("seed", range(12))
def test_input_guard_is_the_identity_once_n_is_large(seed):
    """Consistency: for any fixed finite image the guard stops acting at some N0 (and
    stays off beyond it), so guarded inputs converge wherever the raw ones do."""
    est, var = _random_image(np.random.default_rng(seed))
    cfg = DEFAULT_ON
    lum = est.mean(2)
    eps = cfg.floor * float(image_scale(est))
    ratio = float((lum / (median3x3(lum) + eps)).max())
    n0 = max(1.0, (ratio / cfg.threshold) ** (1 / cfg.growth))
    for n in (2 * n0, 1e3 * n0, 1e9 * n0):
        g = guard_estimates(est, var, torch.tensor([n]), cfg)
        assert not g.outliers.any() and g.estimates is est and g.variances is var, n


def test_guard_does_not_depend_on_the_units():
    buf, _ = synthetic(seed=4)
    buf = with_fireflies(buf, 1e3, "z")
    base = guard_buffer(buf, DEFAULT_ON)
    for k in (1e-4, 1e4):
        scaled = guard_buffer(_scaled(buf, k), DEFAULT_ON)
        np.testing.assert_allclose(scaled.estimates, base.estimates * np.float32(k), rtol=1e-5)


def test_robust_statistics():
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(2, 5, 9, 11, generator=gen)
    x[..., ::3, ::2] = 0.5                                            # ties
    pad = torch.nn.functional.pad(x.reshape(-1, 1, 9, 11), (1, 1, 1, 1), mode="replicate")
    exact = torch.nn.functional.unfold(pad, 3).view(10, 9, 9, 11).median(1).values.view_as(x)
    assert torch.equal(median3x3(x), exact)
    assert torch.all(local_floor(x) <= exact)
    spike = torch.full((1, 1, 7, 7), 0.5)
    spike[..., 3, 3] = 1e6
    assert torch.equal(local_floor(spike), torch.full_like(spike, 0.5))   # a lone spike moves no level
    # image scale: a firefly in all five inputs of one pixel in 2304 barely moves it;
    # all black -> 1; a single bright pixel on black -> its mean
    buf, _ = synthetic()
    est = torch.from_numpy(buf.estimates).permute(0, 3, 1, 2)[None]
    fired = torch.from_numpy(with_fireflies(buf, 1e5, "both", [(5, 5)]).estimates).permute(0, 3, 1, 2)[None]
    assert float(image_scale(fired)) == pytest.approx(float(image_scale(est)), rel=1e-3)
    assert float(image_scale(torch.zeros(1, 5, 3, 4, 4))) == 1.0
    one = torch.zeros(1, 5, 3, 40, 40)
    one[..., 7, 7] = 16.0
    assert float(image_scale(one)) == pytest.approx(16.0 / 1600)


def test_guard_acts_at_small_n_on_the_same_kind_of_image():
    """... and the identity above is not vacuous: at N = 64 such images do have outliers."""
    hits = 0
    for seed in range(12):
        est, var = _random_image(np.random.default_rng(seed))
        hits += int(find_outliers(est, var, torch.tensor([64.0]), DEFAULT_ON).sum())
    assert hits > 0


@pytest.mark.parametrize("band", [1.0, 1.5])
@pytest.mark.parametrize("seed", range(4))
def test_banded_output_stays_within_the_appendix_a_bounds(band, seed):
    """The band never leaves [smallest term, largest term] of Eq. 6, so Eq. 10-12 still apply."""
    gen = torch.Generator().manual_seed(seed)
    h, w, k = 13, 17, 5
    y = torch.rand(2, 3, h, w, generator=gen) * 4
    z = torch.rand(2, 4, 3, h, w, generator=gen) * 4
    y[0, :, 3, 4] = 1e5
    z[1, :, :, 6, 6] = 1e5                                            # neighbour fireflies: terms << 0
    logits = torch.randn(2, 4 * k * k, h, w, generator=gen) * 5
    lo, hi = term_bounds(y, z, k)
    out = output_band(combine(y, z, logits), y, z, band)
    slack = 1e-6 * (hi.abs() + lo.abs() + 1)
    assert torch.all(out >= lo - slack) and torch.all(out <= hi + slack)
    assert torch.all(out >= torch.minimum(y, z.amin(1)) / band)       # no black dots
    assert torch.equal(output_band(out, y, z, 0.0), out.clamp(min=0))


def test_guarded_pipeline_converges_to_the_truth():
    """Noise ~ 1/sqrt(N) plus one pass of a fixed huge value E (adds E/N): guard + any
    weights + anchor + band still converge (paper 002 Eq. 7)."""
    _, clean = synthetic(size=24)
    x = torch.from_numpy(clean).permute(2, 0, 1)
    gen = torch.Generator().manual_seed(0)
    logits = torch.randn(1, 4 * 25, 24, 24, generator=gen)
    errors = []
    for n in (16, 256, 4096, 65536, 2 ** 20, 2 ** 24):
        noise = torch.randn(5, 3, 24, 24, generator=gen) * REL_PASS / n ** 0.5
        est = (x * (1 + noise)).clamp(min=0)
        est[:, :, 5, 5] += 3e4 / n
        var = (est.mean(1) * REL_PASS / n ** 0.5) ** 2
        var[:, 5, 5] += (3e4 / n) ** 2
        g = guard_estimates(est[None], var[None], torch.tensor([float(n)]), DEFAULT_ON)
        out = finish(combine(g.estimates[:, 0], g.estimates[:, 1:], logits),
                     g.estimates[:, 0], g.estimates[:, 1:], DEFAULT_ON)
        errors.append(float((out[0] - x).abs().max()))
    # Not monotone: at N = 256 the event (117 at a pixel of ~0.5) is below g(256) = 256 x
    # its neighbourhood, so the guard lets it through; from there on it is averaged in.
    assert errors[-1] < 0.01 and errors[-1] < errors[-2] < errors[-3] < errors[-4], errors


# ------------------------------------------------------------- low-frequency anchor

def test_gaussian_lowpass_keeps_constants_and_has_its_width():
    const = torch.full((1, 3, 9, 11), 0.7)
    assert torch.allclose(gaussian_lowpass(const, 1.5), const, rtol=1e-6)
    delta = torch.zeros(1, 1, 41, 41)
    delta[0, 0, 20, 20] = 1.0
    g = gaussian_lowpass(delta, 2.0)[0, 0].double()
    assert float(g.sum()) == pytest.approx(1.0, rel=1e-6)
    rows = torch.arange(41, dtype=torch.float64) - 20
    assert float((g.sum(1) * rows ** 2).sum()) == pytest.approx(4.0, rel=0.02)     # variance sigma^2


def test_anchor_takes_low_frequencies_from_z4_and_keeps_the_detail():
    """A combination 3% too dark with a fine pattern on top, anchored to an unbiased ~z^4:
    the 3% goes, the pattern (at the Nyquist frequency) stays."""
    _, clean = synthetic(size=64)
    x = torch.from_numpy(clean).permute(2, 0, 1)[None]
    checker = torch.from_numpy((np.indices((64, 64)).sum(0) % 2 * 2 - 1).astype(np.float32))
    image = 0.97 * x + 0.05 * checker
    out = anchor_low_frequencies(image, x, 1.5)
    to_np = lambda t: t[0].permute(1, 2, 0).numpy().astype(np.float64)   # noqa: E731
    assert abs(to_np(out).mean() / clean.mean() - 1) < 2e-3 < abs(to_np(image).mean() / clean.mean() - 1)
    assert relmse_blocks(to_np(out), clean) < 0.01 * relmse_blocks(to_np(image), clean)
    kept = float(((out - x) * checker).mean() / 0.05)
    assert kept > 0.95, kept


def test_anchor_is_part_of_the_guard_and_can_be_switched_off():
    _, clean = synthetic(size=24)
    x = torch.from_numpy(clean).permute(2, 0, 1)[None]
    z = x[:, None].repeat(1, 4, 1, 1, 1)
    dark = 0.9 * x
    assert torch.allclose(finish(dark, x, z, DEFAULT_ON), x, rtol=1e-5)          # band + anchor: the truth
    no_anchor = finish(dark, 0.8 * x, z, replace(DEFAULT_ON, anchor=0.0))
    assert torch.allclose(no_anchor, dark)                                        # within the band: kept
    assert torch.equal(finish(-dark, x, z, GuardConfig()), torch.zeros_like(dark))  # guard off: clamp at 0
    with pytest.raises(ValueError, match="'anchor'"):
        GuardConfig(anchor=-1.0)
    assert GuardConfig.from_dict({"enabled": True}).anchor == DEFAULT_ON.anchor > 0   # older checkpoints


def test_guard_config_validation():
    with pytest.raises(ValueError, match="unknown guard setting"):
        GuardConfig.from_dict({"enabled": True, "gain": 2})
    for bad in ({"growth": 0.0}, {"band": 0.5}, {"threshold": float("inf")}, {"enabled": 1}, {"floor": -1e-3}):
        with pytest.raises(ValueError):
            GuardConfig(**bad)
    assert GuardConfig.from_dict(DEFAULT_ON.to_dict()) == DEFAULT_ON
    for bad in (1.0, 0.5, -4.0, float("nan")):
        with pytest.raises(ValueError, match="confirm"):
            GuardConfig(enabled=True, confirm=bad)
    assert GuardConfig.from_dict({"enabled": True}).confirm == 0
    for bad in (-1.0, 1.5, 25.0, float("inf")):
        with pytest.raises(ValueError, match="peers"):
            GuardConfig(enabled=True, peers=bad)
    assert GuardConfig.from_dict({"enabled": True}).peers == 0


def test_a_sparse_speckle_field_is_no_outlier_with_peers_but_a_lone_firefly_is():
    """``GuardConfig.peers`` (issue 12, the literature cornell-box's glossy floor): on a
    surface that photons reach rarely, ~y is a field of one-photon speckles of comparable
    value over zeros, so each speckle's 3 x 3 median is 0 and the plain guard removes the
    region's energy. With ``peers`` m, a candidate with m unsettled speckles within 4x of it
    in its 5 x 5 window is kept; a lone firefly (far above every neighbour), one next to a
    *settled* bright neighbour (a light seen directly) and one far above its speckled
    neighbours are still caught."""
    rng = np.random.default_rng(3)
    h = w = 40
    est = np.full((5, h, w, 3), 0.2, np.float32)
    var = np.full((5, h, w), (0.01 * 0.2) ** 2, np.float32)
    field = (slice(4, 20), slice(4, 20))                     # ~y: speckles over black
    est[0][field] = 0.0
    var[0][field] = 0.0
    hits = rng.random((16, 16)) < 0.3
    value = rng.uniform(3.0, 6.0, (16, 16)).astype(np.float32)
    est[0][field] = np.where(hits, value, 0.0)[..., None]
    var[0][field] = np.where(hits, value ** 2, 0.0)          # one pass each: sqrt(V) / X = 1
    lone, settled_next, above = (30, 30), (30, 10), (11, 11)
    est[0][lone] = 1e3
    var[0][lone] = 1e6
    est[0][settled_next] = 1e3
    var[0][settled_next] = 1e6
    est[0][30, 11] = 500.0                                  # a bright, steady neighbour
    var[0][30, 11] = (0.01 * 500.0) ** 2
    est[0][above] = 1e3                                     # inside the speckle field, 200x its speckles
    var[0][above] = 1e6
    t = lambda a: torch.from_numpy(a)[None]                 # noqa: E731
    passes = torch.tensor([64.0])
    args = (t(est).permute(0, 1, 4, 2, 3), t(var), passes)
    plain = find_outliers(*args, DEFAULT_ON)[0, 0]
    peers = find_outliers(*args, replace(DEFAULT_ON, peers=2))[0, 0]
    speckles = torch.from_numpy(hits)
    inner = plain[field] & speckles
    assert int(inner.sum()) > 20                            # the plain guard takes most speckles
    assert int((peers[field] & speckles).sum()) < int(inner.sum()) // 4
    for r, c in (lone, settled_next, above):
        assert bool(plain[r, c]) and bool(peers[r, c])
    assert bool((peers <= plain).all())                      # the rule only switches replacements off
    # consistency: with growing N the test is eventually false everywhere, peers or not
    late = find_outliers(args[0], args[1], torch.tensor([1e12]), replace(DEFAULT_ON, peers=2))
    assert not bool(late.any())


def test_a_light_both_hit_points_see_over_several_passes_is_no_outlier_with_mutual():
    """``GuardConfig.mutual`` (issue 12, ``0069_caustic_paths`` N = 16): a small emitter that
    partly covers a pixel flickers at both hit points, so neither ~y nor the ~z^j is settled
    and the plain guard replaced all five by their 3 x 3 medians (the pixel went black). With
    ``mutual`` r1, ~y and a ~z^j within the confirm factor of each other, each below
    sqrt(V)/X = r1, keep the pixel. The issue's shared-photon firefly (one pass in all five,
    sqrt(V)/X = 1), a flickering ~y over a dark ~z^j and a lone ~z^j event are still caught."""
    h = w = 24
    est = np.full((5, h, w, 3), 0.01, np.float32)
    var = np.full((5, h, w), (0.01 * 0.01) ** 2, np.float32)
    light, shared, y_only, z_only = (6, 6), (6, 17), (17, 6), (17, 17)
    est[0][light], var[0][light] = 0.75, (0.69 * 0.75) ** 2       # A: a few passes saw it
    est[1:, light[0], light[1]], var[1:, light[0], light[1]] = 1.12, (0.54 * 1.12) ** 2   # B as well
    est[:, shared[0], shared[1]], var[:, shared[0], shared[1]] = 500.0, 500.0 ** 2        # one pass, all five
    est[0][y_only], var[0][y_only] = 0.75, (0.69 * 0.75) ** 2     # A flickers, B dark
    est[1:, z_only[0], z_only[1]], var[1:, z_only[0], z_only[1]] = 1.12, (0.54 * 1.12) ** 2  # B alone
    t = lambda a: torch.from_numpy(a)[None]                 # noqa: E731
    args = (t(est).permute(0, 1, 4, 2, 3), t(var), torch.tensor([16.0]))
    plain = find_outliers(*args, DEFAULT_ON)[0]
    mutual = find_outliers(*args, replace(DEFAULT_ON, mutual=0.75))[0]
    assert bool(plain[:, light[0], light[1]].all())                  # the plain guard takes the light
    assert not bool(mutual[:, light[0], light[1]].any())             # both hit points: kept
    for r, c in (shared, y_only):
        assert bool(mutual[:, r, c].any()) and torch.equal(mutual[:, r, c], plain[:, r, c])
    assert bool(mutual[1:, z_only[0], z_only[1]].all())
    assert bool((mutual <= plain).all())                              # it only switches replacements off
    late = find_outliers(args[0], args[1], torch.tensor([1e12]), replace(DEFAULT_ON, mutual=0.75))
    assert not bool(late.any())                                       # eventually the identity
    assert GuardConfig.from_dict({"enabled": True}).mutual == 0
    for bad in (-0.1, 1.0, 2.0, float("nan")):
        with pytest.raises(ValueError, match="mutual"):
            GuardConfig(enabled=True, mutual=bad)


def test_a_rare_light_one_chain_saw_once_and_the_other_thrice_is_no_outlier_with_events():
    """``GuardConfig.events`` (issue 12, the literature ``box`` at N = 1024): a glint both hit
    points see in a few of their passes, ~y from one event (sqrt(V)/X ~ 1) and every ~z^j
    from three (0.58). ``mutual`` asks more than one event of each chain and let the ~z^j
    go (the output was 0.17 where the reference is 53.7). With ``events`` K the two chains'
    events together, X^2 / V each, decide: 1 + 3 >= 4 keeps the pixel. A photon both gathers
    shared in one pass (1 + 1), one chain alone, and a ~y far from its ~z^j are still caught."""
    h = w = 24
    n = 1024.0
    est = np.full((5, h, w, 3), 0.16, np.float32)
    var = np.full((5, h, w), (0.02 * 0.16) ** 2, np.float32)
    def events(k: float, value: float) -> tuple[float, float]:
        return value, value * value * (1.0 / k - 1.0 / n)            # k equal events in n passes
    glint, shared, z_only, far = (6, 6), (6, 17), (17, 6), (17, 17)
    est[0][glint], var[0][glint] = events(1, 30.8)
    est[1:, glint[0], glint[1]], var[1:, glint[0], glint[1]] = events(3, 91.8)
    est[:, shared[0], shared[1]], var[:, shared[0], shared[1]] = events(1, 500.0)
    est[1:, z_only[0], z_only[1]], var[1:, z_only[0], z_only[1]] = events(3, 91.8)
    est[0][far], var[0][far] = events(1, 300.0)                    # ~y 1 event, 10x its ~z^j
    est[1:, far[0], far[1]], var[1:, far[0], far[1]] = events(3, 3000.0)
    t = lambda a: torch.from_numpy(a)[None]                 # noqa: E731
    args = (t(est).permute(0, 1, 4, 2, 3), t(var), torch.tensor([n]))
    shipped_before = replace(DEFAULT_ON, confirm=4.0, mutual=0.75, edge=1.0)
    before = find_outliers(*args, shipped_before)[0]
    after = find_outliers(*args, replace(shipped_before, events=4.0))[0]
    assert bool(before[1:, glint[0], glint[1]].all())                 # mutual let the ~z^j go
    assert not bool(after[:, glint[0], glint[1]].any())               # 1 + 3 events: kept
    for r, c in (shared, z_only, far):
        assert bool(after[:, r, c].any()) and torch.equal(after[:, r, c], before[:, r, c])
    assert bool((after <= before).all())                              # it only switches replacements off
    late = find_outliers(args[0], args[1], torch.tensor([1e12]), replace(shipped_before, events=4.0))
    assert not bool(late.any())                                       # eventually the identity
    assert GuardConfig.from_dict({"enabled": True}).events == 0
    for bad in (-1.0, 1.0, 2.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="events"):
            GuardConfig(enabled=True, events=bad)


def test_the_unsettled_edge_of_a_small_light_is_no_outlier_with_edge():
    """``GuardConfig.edge`` (issue 12, ``0108_bright_emitters`` N = 64): a pixel on the edge
    of a small emitter sees it in some passes only, so all five estimates are unsettled and
    far above their mostly dark 3 x 3 median; the plain guard replaced them by it (a black
    dot, 0.0005, where every input was 0.17 and the reference 0.53). With ``edge`` e, a
    candidate beside a settled pixel at least e x its value is kept. The issue's box
    firefly (far above a settled neighbour), a firefly beside an *unsettled* bright pixel
    and a lone firefly are still caught."""
    h = w = 24
    est = np.full((5, h, w, 3), 1e-4, np.float32)                  # a dark room around small lights
    var = np.full((5, h, w), (0.01 * 1e-4) ** 2, np.float32)
    light, edge, above, beside_event, lone = (6, 6), (6, 7), (17, 7), (6, 17), (17, 17)
    est[:, light[0], light[1]], var[:, light[0], light[1]] = 4.13, (0.16 * 4.13) ** 2   # a settled emitter pixel
    est[:, edge[0], edge[1]], var[:, edge[0], edge[1]] = 0.17, 0.17 ** 2                # one event at its edge
    est[:, 17, 6], var[:, 17, 6] = 0.28, (0.05 * 0.28) ** 2                             # the box: a lit wall pixel
    est[:, above[0], above[1]], var[:, above[0], above[1]] = 489.0, 489.0 ** 2          # and a shared-photon firefly
    est[:, 6, 16], var[:, 6, 16] = 4.13, 4.13 ** 2                                      # a one-pass bright pixel
    est[:, beside_event[0], beside_event[1]], var[:, beside_event[0], beside_event[1]] = 0.17, 0.17 ** 2
    est[:, lone[0], lone[1]], var[:, lone[0], lone[1]] = 50.0, 50.0 ** 2
    t = lambda a: torch.from_numpy(a)[None]                 # noqa: E731
    args = (t(est).permute(0, 1, 4, 2, 3), t(var), torch.tensor([64.0]))
    plain = find_outliers(*args, DEFAULT_ON)[0]
    edged = find_outliers(*args, replace(DEFAULT_ON, edge=1.0))[0]
    assert bool(plain[:, edge[0], edge[1]].all())                    # the plain guard blacks the edge out
    assert not bool(edged[:, edge[0], edge[1]].any())                # beside a settled light: kept
    for r, c in (above, beside_event, lone):
        assert bool(edged[:, r, c].all()) and torch.equal(edged[:, r, c], plain[:, r, c])
    assert bool((edged <= plain).all())                               # it only switches replacements off
    # a stricter ratio: the light must be at least 30x the candidate (4.13 < 30 x 0.17)
    assert bool(find_outliers(*args, replace(DEFAULT_ON, edge=30.0))[0][:, edge[0], edge[1]].all())
    late = find_outliers(args[0], args[1], torch.tensor([1e12]), replace(DEFAULT_ON, edge=1.0))
    assert not bool(late.any())                                       # eventually the identity
    assert GuardConfig.from_dict({"enabled": True}).edge == 0
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="edge"):
            GuardConfig(enabled=True, edge=bad)


def test_a_y_value_that_hit_point_b_saw_over_many_passes_is_no_outlier():
    """``GuardConfig.confirm`` (issue 12, ``0021_caustic_paths``): ~y far above its 3 x 3
    median with few passes behind it is an outlier, unless a ~z^j of the same pixel is
    settled (relative error below r0) and within the factor of it: a small emitter both
    hit points see. The issue's shared-photon firefly (one pass, in all five) and a ~y
    spike over an unsettled or dark ~z^j are still caught."""
    buf, _ = synthetic()
    mean = float(buf.estimates.mean())
    est, var = buf.estimates.copy(), buf.variances.copy()
    (r1, c1), (r2, c2), (r3, c3) = FIREFLIES[:3]
    for r, c in FIREFLIES[:3]:                     # ~y: a single-pass spike at three pixels
        est[0, r, c] += 1e3 * mean
        var[0, r, c] += (1e3 * mean) ** 2
    est[1:, r1, c1] = 400 * mean                   # the ~z^j saw it over many passes: settled
    var[1:, r1, c1] = (0.05 * 400 * mean) ** 2
    est[1:, r2, c2] = 400 * mean                   # as bright, but one pass: unsettled
    var[1:, r2, c2] = (400 * mean) ** 2
    # (r3, c3): the ~z^j stay dark
    t = lambda a: torch.from_numpy(a)[None]        # noqa: E731
    passes = torch.tensor([float(PASSES)])
    plain = find_outliers(t(est).permute(0, 1, 4, 2, 3), t(var), passes, DEFAULT_ON)[0, 0]
    confirm = find_outliers(t(est).permute(0, 1, 4, 2, 3), t(var), passes, replace(DEFAULT_ON, confirm=4.0))[0, 0]
    assert bool(plain[r1, c1]) and bool(plain[r2, c2]) and bool(plain[r3, c3])
    assert not bool(confirm[r1, c1]) and bool(confirm[r2, c2]) and bool(confirm[r3, c3])
    assert torch.equal(confirm.sum(), plain.sum() - 1)
    shared = with_fireflies(buf, 1e3, "both")      # one photon in both gathers: every estimate unsettled
    est_s = torch.from_numpy(shared.estimates).permute(0, 3, 1, 2)[None]
    out = find_outliers(est_s, torch.from_numpy(shared.variances)[None], passes, replace(DEFAULT_ON, confirm=4.0))
    for r, c in FIREFLIES:
        assert bool(out[0, :, r, c].all())


# -------------------------------------------------------------------- checkpoints

def test_guard_travels_in_the_checkpoint_and_old_ones_load_with_it_off(tmp_path, shipped):
    path = tmp_path / "guarded.pt"
    C.init_checkpoint(path, "tiny", FeatureConfig(scale_free=True, outliers=True), guard=DEFAULT_ON)
    model, _ = C.load_checkpoint(path)
    assert model.guard == DEFAULT_ON and model.features == FeatureConfig(scale_free=True, outliers=True)
    data = torch.load(path, weights_only=True)
    del data["guard"]
    data["format_version"] = 1                                       # as written before the guard
    torch.save(data, path)
    assert C.load_checkpoint(path).model.guard == GuardConfig()
    data["guard"] = {"enabled": True, "band": 0.5}
    torch.save(data, path)
    with pytest.raises(UsageError, match="guard setting 'band'"):
        C.load_checkpoint(path)
    # the shipped model is issue 12's recipe: trained with the guard and the new features; shipped
    # with the guard's confirmation by hit point B on (a reship setting, benchmarks/results/guide_spike)
    # the mutual confirmation of the two hit points (benchmarks/results/guide_s9_shipped) and the
    # light-edge rule (benchmarks/results/guide_s11_ship)
    # ... and the confirmation by events (benchmarks/results/guide_s15_events*)
    assert shipped.guard == replace(DEFAULT_ON, confirm=4.0, mutual=0.75, edge=1.0, events=4.0)
    assert shipped.features == FeatureConfig(scale_free=True, outliers=True)
    # ... and ships with the guide in the mode the held-out figures picked (bench_guide.py): the
    # envelope; its chooser (better on generated validation scenes, worse on the literature
    # scenes: benchmarks/results/chooser) travels with it, opt-in
    assert shipped.guide.enabled and shipped.guide.mode == "envelope" and shipped.chooser is not None
    # ... with a speckle field's range widened for the anchor (benchmarks/results/guide_s11_final)
    assert shipped.guide.anchor_free == 0.5
    # ... and ~y's share in the guide lowered where ~y caught nothing beside a lit ~z^4
    # (benchmarks/results/guide_s12_yempty and its hold-out set, guide_s12_yempty_holdout)
    assert shipped.guide.y_empty == 3.0 and shipped.guide.y_found == 0.0
    # ... and the range widened by the estimates' own noise where their bare range is narrow, not at an
    # isolated sparkle (benchmarks/results/guide_s27_range_*, guide_s28_iso_*)
    assert (shipped.guide.range_sigma, shipped.guide.range_sigma_rel, shipped.guide.range_sigma_width,
            shipped.guide.range_sigma_isolated) == (1.0, 0.0, 3.0, 3.0)


def test_with_the_guard_off_the_output_is_eq6_clamped_at_zero(shipped):
    """--guard off --guide off: exactly the pipeline before issue 12 (Eq. 6, then the clamp
    at 0); --guard off with the guide: Eq. 6 on the network's logits plus the prior."""
    from ppmrecon.model.infer import buffer_guide
    from ppmrecon.model.guide import GuideConfig, prior_logits

    buf, _ = synthetic(seed=1)
    buf = with_fireflies(buf, 1e3, "z")
    out = denoise(buf, shipped, precision="float32", guard=GuardConfig(), guide=GuideConfig()).rgb
    inp = from_buffer(buf, shipped.features)
    with torch.no_grad():
        logits = shipped(inp.features)
        ref = combine(inp.y, inp.z, logits).clamp(min=0)[0].permute(1, 2, 0).numpy()
        np.testing.assert_allclose(out, ref, rtol=1e-5, atol=1e-6)
        assert shipped.guide.enabled
        weights = replace(shipped.guide, mode="weights")
        guided = denoise(buf, shipped, precision="float32", guard=GuardConfig(), guide=weights).rgb
        prior = prior_logits(inp.y, inp.z, buffer_guide(buf, weights, GuardConfig()), shipped.window)
        ref = combine(inp.y, inp.z, logits + prior).clamp(min=0)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(guided, ref, rtol=1e-4, atol=1e-5)


# ----------------------------------------------------------------------- features

def _scaled(buf: B.BufferFile, k: float) -> B.BufferFile:
    return replace(buf, estimates=buf.estimates * np.float32(k), variances=buf.variances * np.float32(k * k))


def test_scale_free_features_do_not_depend_on_the_units():
    clean_buf, _ = synthetic(seed=2)
    buf = with_fireflies(clean_buf, 1e3, "y", FIREFLIES[:2])
    cfg = FeatureConfig(scale_free=True, outliers=True)
    assert cfg.n_channels == 30 and cfg.slices()["outliers"] == slice(27, 30)
    base = from_buffer(buf, cfg).features
    for k in (1e-4, 1e4):
        torch.testing.assert_close(from_buffer(_scaled(buf, k), cfg).features, base, rtol=1e-4, atol=1e-5)
    # the default encoding does depend on them: a 1e-4 scene is all black to the network
    dark = from_buffer(_scaled(clean_buf, 1e-4)).features[0, :15]
    assert float(dark.max()) < 1e-3 < 0.05 < float(from_buffer(clean_buf).features[0, :15].min())


def test_outlier_features_point_at_the_firefly():
    buf, _ = synthetic(seed=2)
    bad = with_fireflies(buf, 1e3, "y", [(20, 30)])
    cfg = FeatureConfig(outliers=True)
    out = from_buffer(bad, cfg).features[0, cfg.slices()["outliers"]]   # y, z1 contrasts + spread
    assert float(out[0, 20, 30]) > np.log(100) and float(out[2, 20, 30]) > np.log(100)
    others = out.clone()
    others[:, 20, 30] = 0
    assert float(others.abs().max()) < 1.0


def test_scale_free_features_need_the_radiance_scale_for_crops():
    buf, _ = synthetic(size=16)
    cfg = FeatureConfig(scale_free=True)
    with pytest.raises(ValueError, match="radiance scale"):
        from_buffer(buf, cfg, (slice(0, 8), slice(0, 8)), buffer_scales(buf))
    part = from_buffer(buf, cfg, (slice(3, 11), slice(5, 16)), buffer_scales(buf, cfg))
    torch.testing.assert_close(part.features, from_buffer(buf, cfg).features[..., 3:11, 5:16], rtol=0, atol=0)


# ------------------------------------------------------------------------ training

@pytest.mark.parametrize("name", ["cpu", "cpu_small", "cpu_paper", "cpu_v2", "cpu_v2_guide"])
def test_shipped_training_configs_train_with_the_guard(name):
    from ppmrecon.data import CONFIGS
    from ppmrecon.train.loop import TrainConfig

    cfg = TrainConfig.load(CONFIGS / "train" / f"{name}.json")
    assert GuardConfig.from_dict(cfg.guard) == DEFAULT_ON
    assert FeatureConfig.from_dict(cfg.features) == FeatureConfig(scale_free=True, outliers=True)


def test_training_sees_guarded_inputs_and_stores_the_guard(tmp_path):
    from ppmrecon.train.dataset import load_split
    from ppmrecon.train.datagen import REFERENCE, input_name
    from ppmrecon.train.loop import TrainConfig, train

    root = tmp_path / "data"
    scenes = []
    for i, split in enumerate(("train", "val")):
        buf, clean = synthetic(seed=i, size=32)
        buf = with_fireflies(buf, 1e4, "both", [(8, 8)])
        folder = root / f"s{i}"
        folder.mkdir(parents=True)
        B.write_buffers(folder / input_name(PASSES, 0), buf)
        B.write_rgb(folder / REFERENCE, clean)
        scenes.append({"id": f"s{i}", "split": split, "inputs": [{"file": input_name(PASSES, 0), "passes": PASSES}]})
    (root / "manifest.json").write_text(json.dumps(
        {"version": 1, "config": {"input_passes": [PASSES], "seeds": [0]}, "scenes": scenes}))
    raw = load_split(root, "train")[0]
    guarded = load_split(root, "train", guard=DEFAULT_ON)[0]
    assert float(raw.y[:, 8, 8].min()) > 100 and float(guarded.y[:, 8, 8].max()) < 2
    assert float(guarded.z[:, :, 8, 8].max()) < 2
    cfg = TrainConfig(preset="tiny", guard={"enabled": True}, features={"scale_free": True, "outliers": True},
                      epochs=1, steps_per_epoch=2, batch=2, patch=16)
    history = train(root, tmp_path / "run", cfg, quiet=True)
    model, _ = C.load_checkpoint(tmp_path / "run" / "model.pt")
    assert model.guard == DEFAULT_ON and model.features.outliers and np.isfinite(history[-1]["loss"])


# ------------------------------------------------------------------------- metrics

def test_block_relmse_sees_bias_but_not_noise_that_averages_out():
    ref = np.full((16, 16, 3), 0.5, np.float32)
    checker = (np.indices((16, 16)).sum(0) % 2 * 2 - 1)[..., None] * 0.2       # zero mean per 8x8 block
    assert relmse_blocks(ref + checker, ref) < 1e-12 < relmse(ref + checker, ref)
    assert relmse_blocks(ref + 0.1, ref) == pytest.approx(relmse(ref + 0.1, ref))
    assert block_means(np.ones((17, 9, 3)), 8).shape == (2, 1, 3)
    with pytest.raises(ValueError, match="smaller than one"):
        block_means(np.ones((7, 9, 3)), 8)
