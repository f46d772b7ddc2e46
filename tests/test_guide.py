"""The denoiser guide (ppmrecon/model/guide.py): prior logits, consistency, checkpoint, CLI."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from ppmrecon import buffers as B
from ppmrecon.errors import UsageError
from ppmrecon.model import checkpoint as C
from ppmrecon.model.cli import main as denoise_main
from ppmrecon.model.combine import combine, term_bounds
from ppmrecon.model.features import FeatureConfig
from ppmrecon.model.guard import DEFAULT_ON, settled_mask
from ppmrecon.model.guide import DEFAULT_GUIDE, GuideConfig, guide_planes, oidn_image, prior_logits, y_share
from ppmrecon.model.infer import buffer_guide, denoise
from ppmrecon.model.kpn import build
from tests.conftest import make_buffer


def _terms(y: torch.Tensor, z: torch.Tensor, k: int) -> torch.Tensor:
    """Every term t^j_{c,i} of Eq. 6 in the logit layout, (B, 4 K^2, 3, H, W), by brute force."""
    b, _, h, w = y.shape
    r = k // 2
    yp = torch.nn.functional.pad(y, (r, r, r, r), mode="replicate")
    zp = torch.nn.functional.pad(z.reshape(b, 12, h, w), (r, r, r, r), mode="replicate").view(b, 4, 3, h + 2 * r, w + 2 * r)
    out = []
    for a in range(k):
        for c in range(k):
            for j in range(4):
                out.append(yp[..., a:a + h, c:c + w] + z[:, j] - zp[:, j, :, a:a + h, c:c + w])
    return torch.stack(out, 1)


def test_prior_logits_are_the_gaussian_log_likelihood_of_each_term():
    torch.manual_seed(0)
    y, z = torch.rand(2, 3, 6, 7), torch.rand(2, 4, 3, 6, 7)
    g = torch.rand(2, 3, 6, 7)
    sigma = 0.1 + torch.rand(2, 1, 6, 7)
    logits = prior_logits(y, z, torch.cat([g, sigma], 1), 3)
    t = _terms(y, z, 3)
    expected = -(t - g.unsqueeze(1)).square().mean(2) / (2 * sigma.square())
    torch.testing.assert_close(logits, expected, rtol=1e-5, atol=1e-6)


def test_a_sharp_guide_selects_the_term_closest_to_it():
    torch.manual_seed(1)
    y, z = torch.rand(1, 3, 5, 5), torch.rand(1, 4, 3, 5, 5)
    t = _terms(y, z, 3)
    g = t[:, 17]                                 # one of the terms at every pixel
    planes = torch.cat([g, torch.full((1, 1, 5, 5), 1e-4)], 1)
    out = combine(y, z, prior_logits(y, z, planes, 3))
    torch.testing.assert_close(out, g, rtol=1e-5, atol=1e-5)


def test_any_guide_stays_within_the_terms_and_converged_inputs_ignore_it():
    torch.manual_seed(2)
    y, z = torch.rand(1, 3, 8, 9), torch.rand(1, 4, 3, 8, 9)
    wild = torch.cat([torch.rand(1, 3, 8, 9) * 1e4, torch.full((1, 1, 8, 9), 0.01)], 1)   # a guide far off
    out = combine(y, z, prior_logits(y, z, wild, 5))
    lo, hi = term_bounds(y, z, 5)
    assert bool((out >= lo).all() and (out <= hi).all())
    x = torch.rand(1, 3, 8, 9)                   # converged inputs: every term is x, whatever the guide
    same = combine(x, x.unsqueeze(1).expand(1, 4, 3, 8, 9).contiguous(), prior_logits(x, x.unsqueeze(1).expand(1, 4, 3, 8, 9), wild, 5))
    torch.testing.assert_close(same, x, rtol=1e-6, atol=1e-6)


def test_guide_planes_are_oidn_of_the_source_with_a_relative_tolerance():
    buf = make_buffer(16, 20, seed=4)
    planes = guide_planes(buf.estimates, buf.albedo, buf.normal, GuideConfig(enabled=True), scale=2.0, floor=1e-3)
    g = oidn_image(buf.estimates[4], buf.albedo, buf.normal, DEFAULT_GUIDE.quality)
    assert planes.shape == (1, 4, 16, 20)
    np.testing.assert_allclose(planes[0, :3].permute(1, 2, 0).numpy(), g)
    np.testing.assert_allclose(planes[0, 3].numpy(), 0.03 * g.mean(-1) + 2e-3, rtol=1e-5)
    assert (g >= 0).all() and np.isfinite(g).all()


def test_the_guide_is_scale_free():
    buf = make_buffer(16, 16, seed=5)
    bright = replace(buf, estimates=buf.estimates * 1000.0, variances=buf.variances * 1e6)
    model = build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON, DEFAULT_GUIDE)
    a = denoise(buf, model, tile=None).rgb
    b = denoise(bright, model, tile=None).rgb
    np.testing.assert_allclose(b / 1000.0, a, rtol=2e-2, atol=1e-4)   # OIDN itself is only ~scale-equivariant


def test_an_untrained_guided_model_is_the_guide_alone_and_tiles_agree():
    buf = make_buffer(40, 36, seed=6)
    model = build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON, DEFAULT_GUIDE)
    assert float(model.head.weight.detach().abs().sum()) == 0.0
    whole = denoise(buf, model, tile=64).rgb
    tiled = denoise(buf, model, tile=16).rgb
    np.testing.assert_allclose(tiled, whole, rtol=1e-5, atol=1e-5)
    off = denoise(buf, model, guide=GuideConfig()).rgb
    assert not np.allclose(off, whole)           # the guide changes the weights


def test_guide_settings_are_validated():
    with pytest.raises(ValueError, match="beta"):
        GuideConfig(enabled=True, beta=0)
    with pytest.raises(ValueError, match="source"):
        GuideConfig(source=5)
    with pytest.raises(ValueError, match="unknown guide"):
        GuideConfig.from_dict({"sharpness": 1})
    for bad in (1.0, 0.5, -2.0, float("inf"), float("nan"), True):
        with pytest.raises(ValueError, match="y_spike"):
            GuideConfig(y_spike=bad)
    assert GuideConfig(y_spike=16).y_spike == 16 and GuideConfig.from_dict({}).y_spike == 0
    for bad in (-1.0, float("nan"), float("inf"), False):
        with pytest.raises(ValueError, match="anchor_window"):
            GuideConfig(anchor_window=bad)
    assert GuideConfig.from_dict({}).anchor_window == 0
    for bad in (-0.5, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="anchor_settled"):
            GuideConfig(anchor_settled=bad)
    assert GuideConfig.from_dict({}).anchor_settled == 0
    for bad in (-1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="anchor_select"):
            GuideConfig(anchor_select=bad)
    assert GuideConfig.from_dict({}).anchor_select == 0
    for bad in (-1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="terms_passes"):
            GuideConfig(terms_passes=bad)
    assert GuideConfig.from_dict({}).terms_passes == 0
    for bad in (1.0, 0.5, -1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="anchor_spikes"):
            GuideConfig(anchor_spikes=bad)
    assert GuideConfig.from_dict({}).anchor_spikes == 0 and GuideConfig(anchor_spikes=8).anchor_spikes == 8


def test_checkpoints_carry_the_guide_and_older_ones_read_as_off(tmp_path):
    model = build("tiny", FeatureConfig(), DEFAULT_ON, replace(DEFAULT_GUIDE, beta=0.05))
    C.save_checkpoint(tmp_path / "m.pt", model)
    assert C.load_checkpoint(tmp_path / "m.pt").model.guide == replace(DEFAULT_GUIDE, beta=0.05)
    payload = torch.load(tmp_path / "m.pt", weights_only=True)
    del payload["guide"]
    payload["format_version"] = 2
    torch.save(payload, tmp_path / "old.pt")
    assert C.load_checkpoint(tmp_path / "old.pt").model.guide == GuideConfig()


def test_cli_guide_switch_and_header(tmp_path):
    buf = make_buffer(24, 24, seed=7)
    B.write_buffers(tmp_path / "in.exr", buf)
    C.init_checkpoint(tmp_path / "m.pt", "tiny", FeatureConfig())
    assert denoise_main([str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q",
                         "-o", str(tmp_path / "on.exr")]) == 0
    assert denoise_main([str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q", "--guide", "off",
                         "-o", str(tmp_path / "off.exr")]) == 0
    on, h_on = B.read_rgb(tmp_path / "on.exr")
    off, h_off = B.read_rgb(tmp_path / "off.exr")
    assert h_on["ppmrecon.guide"] == "oidn(z4, fast) weights beta=0.03 cross=2 y=0" and h_off["ppmrecon.guide"] == "off"
    assert not np.allclose(on, off)
    planes = buffer_guide(buf, DEFAULT_GUIDE, DEFAULT_ON)
    assert planes.shape == (1, 4, 24, 24) and bool(torch.isfinite(planes).all())


def test_guide_quality_option(tmp_path, capsys):
    """--guide-quality picks OIDN's mode (header says which; 'high' and 'fast' give
    different guides, hence different images); a checkpoint without the setting reads as
    'fast'; a bad mode or the option with the guide off is one clear error."""
    import ppmrecon
    from ppmrecon.errors import UsageError

    buf = make_buffer(24, 24, seed=8)
    B.write_buffers(tmp_path / "in.exr", buf)
    C.init_checkpoint(tmp_path / "m.pt", "tiny", FeatureConfig())
    assert C.load_checkpoint(tmp_path / "m.pt").model.guide.quality == "fast"
    assert GuideConfig.from_dict({"enabled": True, "beta": 0.03, "source": 4, "cross": 2.0}).quality == "fast"
    with pytest.raises(ValueError, match="quality"):
        GuideConfig(enabled=True, quality="slow")
    images = {}
    for q in ("high", "fast"):
        out = tmp_path / f"{q}.exr"
        assert denoise_main([str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q",
                             "--guide-quality", q, "-o", str(out)]) == 0
        images[q], header = B.read_rgb(out)
        assert header["ppmrecon.guide"] == f"oidn(z4, {q}) weights beta=0.03 cross=2 y=0"
    assert not np.array_equal(images["high"], images["fast"])
    np.testing.assert_array_equal(ppmrecon.denoise(buf, tmp_path / "m.pt", guide_quality="high"), images["high"])
    assert denoise_main([str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q", "--guide", "off",
                         "--guide-quality", "high"]) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--guide-quality" in err[0] and "--guide on" in err[0]
    with pytest.raises(UsageError, match="guide_quality"):
        ppmrecon.denoise(buf, tmp_path / "m.pt", guide_quality="slow")


def test_a_wrong_guide_cannot_stop_convergence():
    """Noise ~ 1/sqrt(N) on all five inputs, a guide that is wrong by 2x and sharp: the
    guided combination, anchor and band still converge to the truth (Appendix A)."""
    from ppmrecon.model.guard import finish

    gen = torch.Generator().manual_seed(0)
    x = 0.2 + torch.rand(3, 20, 20, generator=gen)
    wrong = torch.cat([2.0 * x, torch.full((1, 20, 20), 1e-3)], 0)[None]
    errors = []
    for n in (16, 256, 4096, 65536, 2 ** 20):
        est = (x * (1 + torch.randn(5, 3, 20, 20, generator=gen) * 1.2 / n ** 0.5)).clamp(min=0)
        y, z = est[:1], est[1:][None]
        out = finish(combine(y, z, prior_logits(y, z, wrong, 5)), y, z, DEFAULT_ON)
        errors.append(float((out[0] - x).abs().max()))
    assert errors[-1] < 0.01 and errors[-1] < errors[-2] < errors[-3] < errors[-4], errors


def test_where_the_two_hit_points_disagree_the_guide_is_their_geometric_mean():
    buf = make_buffer(16, 16, seed=8)
    est = buf.estimates.copy()
    est[0] = 1.0 + 0.0 * est[0]                  # ~y flat at 1, ~z^4 flat at 1 with a patch at 10
    est[4] = 1.0 + 0.0 * est[4]
    est[4, 4:12, 4:12] = 10.0
    buf = replace(buf, estimates=est)
    cross = guide_planes(buf.estimates, buf.albedo, buf.normal, DEFAULT_GUIDE, scale=1.0, floor=1e-3)[0, :3]
    plain = guide_planes(buf.estimates, buf.albedo, buf.normal, GuideConfig(enabled=True), scale=1.0, floor=1e-3)[0, :3]
    gy = torch.from_numpy(oidn_image(buf.estimates[0], buf.albedo, buf.normal, DEFAULT_GUIDE.quality)).permute(2, 0, 1)
    inside = (slice(None), slice(6, 10), slice(6, 10))
    torch.testing.assert_close(cross[inside], (plain[inside] * gy[inside]).sqrt(), rtol=1e-5, atol=1e-5)
    assert float(cross[inside].mean()) < 0.5 * float(plain[inside].mean())
    torch.testing.assert_close(cross[:, :2, :2], plain[:, :2, :2])   # where they agree: OIDN of ~z^4


def test_y_weight_mixes_oidn_of_y_into_the_guide_by_inverse_local_variance():
    buf = make_buffer(16, 16, seed=9)
    var = np.ones_like(buf.variances)
    var[4, :, :8] = 3.0                          # left half: ~z^4 3x as noisy as ~y
    var[0, :, 8:] = 7.0                          # right half: ~y 7x as noisy as ~z^4
    args = (buf.estimates, buf.albedo, buf.normal)
    gy = torch.from_numpy(oidn_image(buf.estimates[0], buf.albedo, buf.normal, DEFAULT_GUIDE.quality)).permute(2, 0, 1)
    for cross in (0.0, 2.0):
        base = replace(DEFAULT_GUIDE, cross=cross)
        g = guide_planes(*args, base, scale=1.0, floor=1e-3)[0]
        mixed = guide_planes(*args, replace(base, y_weight=2.0), scale=1.0, floor=1e-3, variances=var)[0]
        w = y_share(var, 4, 2.0)
        torch.testing.assert_close(mixed[:3], g[:3] + w * (gy - g[:3]), rtol=1e-5, atol=1e-6)
        # the tolerance follows the guide it is the tolerance of
        torch.testing.assert_close(mixed[3], 0.03 * mixed[:3].mean(0) + 1e-3, rtol=1e-5, atol=1e-7)
    # w = f V_z / (V_y + f V_z) far from the halves' seam (the variances are blurred)
    torch.testing.assert_close(w[0, :, :2], torch.full((16, 2), 6.0 / 7.0))
    torch.testing.assert_close(w[0, :, -2:], torch.full((16, 2), 2.0 / 9.0))
    assert float(y_share(np.zeros_like(var), 4, 2.0).abs().max()) == 0.0     # nothing noisy: ~z^4's image
    with pytest.raises(ValueError, match="variances"):
        guide_planes(*args, replace(DEFAULT_GUIDE, y_weight=1.0), scale=1.0, floor=1e-3)
    assert GuideConfig.from_dict({k: v for k, v in DEFAULT_GUIDE.to_dict().items() if k != "y_weight"}).y_weight == 0
    for bad in (-0.1, True, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="y_weight"):
            GuideConfig(enabled=True, y_weight=bad)


def test_y_found_keeps_a_photon_starved_y_out_of_the_guide():
    """y_found S: ~y's share is scaled by the local share of pixels where ~y is not sparser than
    the source (effective events mean^2 / V below 1 where the source's are not). Where ~y's disc
    caught nothing (V_y = 0, ~y = 0) next to a well-lit source the share falls to 0; where ~y
    has its photons, where the source is as sparse, or at an emitter seen directly (lit, V_y = 0)
    it is the plain share (the rule leaves many passes alone)."""
    h, w = 24, 48
    est = np.ones((5, h, w, 3), np.float32)
    var = np.full((5, h, w), 0.01, np.float32)          # 100 events everywhere ...
    est[0, :, :12], var[0, :, :12] = 0.0, 0.0           # ... but ~y caught nothing on the left
    est[0, :, 24:36], var[0, :, 24:36] = 0.0, 0.0       # nor here, where the source is as sparse:
    var[4, :, 24:36] = 4.0                              # 1 / 4 of an event
    var[0, :, 36:] = 0.0                                # an emitter: lit, variance 0
    plain = y_share(var, 4, 2.0)
    found = y_share(var, 4, 2.0, found=2.0, estimates=est)
    assert float(plain[0, :, :4].min()) == pytest.approx(1.0)       # V_y = 0 reads as infinitely sure
    assert float(found[0, :, :4].abs().max()) == 0.0                # starved: OIDN(~z^4) alone
    for cols in (slice(19, 23), slice(28, 32), slice(42, 48)):      # ~y lit, equally sparse, emitter
        torch.testing.assert_close(found[0, :, cols], plain[0, :, cols])
    assert bool((found <= plain + 1e-7).all())                      # it only ever lowers the share
    lit = est.copy()
    lit[0] = 1.0
    lit_var = np.full_like(var, 0.01)
    torch.testing.assert_close(y_share(lit_var, 4, 2.0, found=2.0, estimates=lit), y_share(lit_var, 4, 2.0))
    torch.testing.assert_close(y_share(var, 4, 2.0, found=2.0), plain)   # no estimates: off
    # more than one event: nothing seen is none, an emitter seen directly (variance 0) is plenty
    events = settled_mask(torch.tensor([0.0, 2.0, 2.0, 3.0]), torch.tensor([0.0, 4.0, 3.0, 0.0]), 1.0)
    assert events.tolist() == [False, False, True, True]
    assert GuideConfig.from_dict({}).y_found == 0 and GuideConfig(y_found=2).y_found == 2
    for bad in (-1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="y_found"):
            GuideConfig(y_found=bad)


def test_y_empty_keeps_only_a_y_that_caught_nothing_out_of_the_guide():
    """y_empty S: ~y's share is scaled by the local share of pixels where ~y did not read 0
    while the source rests on more than one event. A ~y that caught nothing next to a well-lit
    source loses its share (its V = 0 reads as certainty, the plain share is 1); a ~y of less
    than one event keeps it (y_found takes that one out too), and so do a ~y beside an equally
    sparse source and an emitter seen directly."""
    h, w = 24, 60
    est = np.ones((5, h, w, 3), np.float32)
    var = np.full((5, h, w), 0.01, np.float32)          # 100 events everywhere ...
    est[0, :, :12], var[0, :, :12] = 0.0, 0.0           # ... but ~y caught nothing on the left
    var[0, :, 24:36] = 4.0                              # ~y of a quarter event: sparse, not empty
    est[0, :, 36:48], var[0, :, 36:48] = 0.0, 0.0       # nothing, where the source is as sparse
    var[4, :, 36:48] = 4.0
    var[0, :, 48:] = 0.0                                # an emitter: lit, variance 0
    plain = y_share(var, 4, 2.0)
    empty = y_share(var, 4, 2.0, estimates=est, empty=2.0)
    found = y_share(var, 4, 2.0, found=2.0, estimates=est)
    assert float(plain[0, :, :4].min()) == pytest.approx(1.0)       # V_y = 0 reads as certainty
    assert float(empty[0, :, :4].abs().max()) == 0.0                # caught nothing: OIDN(~z^4) alone
    for cols in (slice(28, 32), slice(40, 44), slice(54, 60)):      # a quarter event, equally sparse, emitter
        torch.testing.assert_close(empty[0, :, cols], plain[0, :, cols])
    assert float(found[0, :, 29:31].abs().max()) < 1e-3             # y_found: the quarter event is starved
    assert bool((empty <= plain + 1e-7).all())
    torch.testing.assert_close(y_share(var, 4, 2.0, empty=2.0), plain)   # no estimates: off
    both = y_share(var, 4, 2.0, found=2.0, estimates=est, empty=2.0)
    torch.testing.assert_close(both, found * empty / plain.clamp(min=1e-12), atol=1e-6, rtol=1e-5)
    assert GuideConfig.from_dict({}).y_empty == 0 and GuideConfig(y_empty=3).y_empty == 3
    for bad in (-1.0, float("nan"), float("inf"), True):
        with pytest.raises(ValueError, match="y_empty"):
            GuideConfig(y_empty=bad)


def test_a_spike_only_hit_point_b_saw_is_kept_out_of_the_guide():
    from ppmrecon.model.guide import despike

    y = torch.full((3, 9, 9), 0.5)
    z = torch.full((3, 9, 9), 0.5)
    z[:, 4, 4] = 20.0                            # in ~z^4 only: removed
    z[:, 1, 1] = 20.0                            # ~y sees it too, next door: kept
    y[:, 1, 2] = 20.0
    out = despike(z, y, eps=1e-3)
    assert float(out[:, 4, 4].max()) == 0.5 and float(out[:, 1, 1].min()) == 20.0


@pytest.mark.parametrize("fraction", [0.005, 0.2])
def test_despike_at_the_candidates_equals_the_whole_image_median(monkeypatch, fraction):
    """The medians computed at the candidate pixels only (few spikes) or on the whole
    image (many) give the same guide input, borders and corners included."""
    import ppmrecon.model.guide as guide_module
    from ppmrecon.model.guard import median3x3

    gen = torch.Generator().manual_seed(3)
    z = torch.rand(3, 23, 31, generator=gen) ** 4
    y = torch.rand(3, 23, 31, generator=gen) ** 2 * 0.2
    hot = torch.randperm(23 * 31, generator=gen)[:max(3, int(fraction * 23 * 31))]
    z.view(3, -1)[:, hot] *= 1e3
    z[:, 0, 0] = z[:, -1, -1] = 1e3                  # corners: replicate padding
    lum, med = z.mean(0), median3x3(z)
    ymax = torch.nn.functional.max_pool2d(y.mean(0)[None, None], 3, 1, 1)[0, 0]
    spike = (lum > 4 * (med.mean(0) + 1e-3)) & (lum > 4 * (ymax + 1e-3))
    expected = torch.where(spike, med, z)
    assert bool(spike.any())
    for dense in (0.05, 0.0, 1.0):                   # the default, always dense, never dense
        monkeypatch.setattr(guide_module, "DENSE_SPIKES", dense)
        assert torch.equal(guide_module.despike(z, y, eps=1e-3), expected)


# ------------------------------------------------------------------- envelope mode

ENVELOPE = replace(DEFAULT_GUIDE, mode="envelope")


def test_envelope_stays_within_each_pixels_five_estimates_and_runs_no_network(tmp_path):
    """The guide's envelope: every output value lies between the smallest and largest of
    the pixel's five (guarded) estimates, per channel; the network is never called (a
    model whose weights are NaN gives the same image); no weights come back."""
    from ppmrecon.model.guard import guard_buffer

    buf = make_buffer(32, 32, seed=11)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, ENVELOPE)
    out = denoise(buf, model)
    assert out.weights_per_z is None and out.rgb.shape == (32, 32, 3)
    est = guard_buffer(buf, DEFAULT_ON).estimates                    # (5, H, W, 3)
    lo, hi = est.min(0), est.max(0)
    assert bool(((out.rgb >= lo - 1e-6 * np.abs(lo)) & (out.rgb <= hi + 1e-6 * np.abs(hi))).all())
    with torch.no_grad():
        for p in model.parameters():
            p.fill_(float("nan"))
    np.testing.assert_array_equal(denoise(buf, model).rgb, out.rgb)


def test_envelope_returns_the_estimates_when_they_agree():
    """Converged inputs (all five estimates equal) give back exactly that image, whatever
    OIDN makes of it: the envelope is consistent by construction."""
    buf = make_buffer(24, 24, seed=12)
    same = np.repeat(buf.estimates[4:5], 5, axis=0)
    buf = replace(buf, estimates=same)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, ENVELOPE)
    np.testing.assert_array_equal(denoise(buf, model).rgb, same[0])


def test_anchor_target_takes_the_wider_estimate_where_the_low_passes_agree():
    """anchor_select: the aim is ~z^(m+1) (and its variance) where its low-pass agrees with
    ~z^m's, ~z^m where they differ far beyond ~z^m's noise, between the two elsewhere; off,
    it is ~z^m; the envelope with it returns converged inputs exactly."""
    from ppmrecon.model.guide import anchor_target

    z = torch.full((1, 4, 3, 16, 16), 1.0)
    v3, v4 = torch.full((1, 1, 16, 16), 1e-2), torch.full((1, 1, 16, 16), 1e-3)
    z[:, 3, :, :, 10:] = 3.0                               # ~z^4's bandwidth bias on the right, 2 >> sqrt(1e-2)
    on = replace(ENVELOPE, anchor_source=3, anchor_select=1.0)
    t, v = anchor_target(z, v3, v4, on, 1.5)
    assert torch.equal(t[..., :4], z[:, 3, :, :, :4]) and torch.equal(v[..., :4], v4[..., :4])
    assert torch.allclose(t[..., 14:], z[:, 2, :, :, 14:], rtol=0, atol=1e-2)
    assert torch.allclose(v[..., 14:], v3[..., 14:], rtol=0, atol=1e-4)
    assert bool(((t >= 1.0) & (t <= 3.0)).all())              # a convex combination of the two
    t0, v0 = anchor_target(z, v3, None, replace(on, anchor_select=0.0), 1.5)
    assert torch.equal(t0, z[:, 2]) and v0 is v3
    t4, v4_ = anchor_target(z, v4, None, replace(on, anchor_source=4), 1.5)     # no wider estimate: ~z^4 itself
    assert torch.equal(t4, z[:, 3]) and v4_ is v4
    with pytest.raises(ValueError, match="wider estimate's variance"):
        anchor_target(z, v3, None, on, 1.5)
    buf = make_buffer(24, 24, seed=12)
    same = np.repeat(buf.estimates[4:5], 5, axis=0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    np.testing.assert_array_equal(denoise(replace(buf, estimates=same), model).rgb, same[0])


def _biased_wide(h: int = 16, w: int = 16) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """z (1, 4, 3, H, W) at 1 with ~z^3 and ~z^4 at 3 on the right half (a wide kernel's
    bandwidth bias far beyond the noise), the five variances (1e-3) and radii (r, sqrt(2) r, ...)."""
    z = torch.full((1, 4, 3, h, w), 1.0)
    z[:, 2:, :, :, w // 2:] = 3.0
    var = torch.full((1, 5, h, w), 1e-3)
    radii = torch.stack([torch.full((h, w), 0.01 * 2 ** (k / 2)) for k in range(5)])[None]
    return z, var, radii


def _biased_buffer(seed: int) -> B.BufferFile:
    """A 24 x 24 buffer file whose ~z^j are :func:`_biased_wide`'s (with its variances and
    radii); ~y as :func:`make_buffer` drew it."""
    z, var, radii = _biased_wide(24, 24)
    buf = make_buffer(24, 24, seed=seed)
    est = buf.estimates.copy()
    est[1:] = z[0].permute(0, 2, 3, 1).numpy()
    return replace(buf, estimates=est, variances=var[0].numpy(), radii=radii[0].numpy())


def test_cascade_aim_steps_down_where_the_wide_estimates_are_biased():
    """cascade: where ~z^3/~z^4 depart from ~z^2/~z^1 far beyond their noise the aim is the
    narrow estimates' level and the wide ~z^j are pulled to it; where all agree (or the gap is
    within k x the noise, or the narrow estimate's variance reads 0 beside noisy wider ones)
    the aim is anchor_target's and no ~z^j moves; off or converged: nothing changes."""
    from ppmrecon.model.guide import anchor_target, cascade_aim

    z, var, radii = _biased_wide()
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, cascade=4.0, anchor_window=3.0)
    aim = cascade_aim(z, var, radii, on, 1.5, None)
    t34, v34 = anchor_target(z, var[:, 3:4], var[:, 4:5], on, 1.5)
    assert torch.equal(aim.t[..., :4], t34[..., :4]) and torch.equal(aim.z[..., :4], z[..., :4])
    assert torch.equal(aim.variance[..., :4], v34[..., :4])
    assert torch.allclose(aim.t[..., 13:], torch.ones(1, 3, 16, 3), rtol=0, atol=2e-2)   # w = 1 - k noise / |D|^2
    assert torch.allclose(aim.z[..., 13:], torch.ones(1, 4, 3, 16, 3), rtol=0, atol=2e-2)
    assert bool(((aim.z >= 1.0) & (aim.z <= 3.0)).all())          # convex combinations of the estimates
    # a gap within k x the noise: no step, no pull
    small = z.clone()
    small[:, 2:, :, :, 8:] = 1.05                                 # 0.05 against sqrt(Var(G * ~z^j)) ~ 0.03
    calm = cascade_aim(small, var, radii, on, 1.5, None)
    assert torch.equal(calm.z, small)
    # ~z^2 and ~z^1 read variance 0 (their passes missed the bright photons) beside noisy wider
    # ones: the floor V_i (r_i / r_j)^2 keeps the step from reading that gap as bias
    lucky = var.clone()
    lucky[:, 1:3] = 0.0
    lucky[:, 3:] = 10.0
    assert torch.equal(cascade_aim(z, lucky, radii, on, 1.5, None).z, z)
    # a speckle field: no step
    free = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    assert torch.equal(cascade_aim(z, var, radii, on, 1.5, free).z, z)
    same = torch.ones_like(z)
    converged = cascade_aim(same, var, radii, on, 1.5, None)
    assert torch.equal(converged.t, same[:, 0]) and torch.equal(converged.z, same)


def _trend(h: int = 16, w: int = 16) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """y (1, 3, H, W) at 1 and :func:`_biased_wide`'s ~z^j with a bandwidth trend on the right
    half (~z^1 1.5, ~z^2 2, ~z^3 and ~z^4 3: every kernel gathers a bright neighbour's photons,
    the wider the more), its variances and radii."""
    z, var, radii = _biased_wide(h, w)
    z[:, 0, :, :, w // 2:] = 1.5
    z[:, 1, :, :, w // 2:] = 2.0
    return torch.ones(1, 3, h, w), z, var, radii


def test_y_step_takes_the_aim_to_y_where_the_z_trend_shows():
    """cascade_y: where ~z^1 departs from the wide estimates beyond its noise and ~y lies
    further the same way, the aim steps on to ~y (the range's ~z^j are not pulled by it);
    a ~y on the far side of the wide estimates, a ~y departing from ~z^j that agree among
    themselves, or a speckle field: no step; a ~y of variance 0 is not taken as certain (the
    ~z^j's prediction of its variance floors the test); off: the aim of the ~z^j alone."""
    from ppmrecon.model.guide import cascade_aim

    y, z, var, radii = _trend()
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, cascade=4.0, anchor_window=3.0, cascade_y=4.0)
    off = replace(on, cascade_y=0.0)
    stepped, plain = cascade_aim(z, var, radii, on, 1.5, None, y), cascade_aim(z, var, radii, off, 1.5, None)
    assert torch.allclose(plain.t[..., 13:], torch.full((1, 3, 16, 3), 1.5), rtol=0, atol=6e-2)   # ~z^1's level
    assert torch.allclose(stepped.t[..., 13:], torch.ones(1, 3, 16, 3), rtol=0, atol=5e-2)
    assert torch.equal(stepped.z, plain.z)                         # the step pulls no ~z^j
    assert torch.equal(stepped.t[..., :4], plain.t[..., :4])       # no trend on the left: no step
    assert bool(((stepped.t >= 1.0 - 1e-6) & (stepped.t <= 3.0)).all())    # convex combinations
    far = torch.where(torch.arange(16) >= 8, 3.5, 1.0).expand(1, 3, 16, 16)     # beyond ~z^4
    assert torch.equal(cascade_aim(z, var, radii, on, 1.5, None, far).t, plain.t)
    flat = torch.ones_like(z)                                      # the ~z^j agree; ~y alone departs
    assert torch.equal(cascade_aim(flat, var, radii, on, 1.5, None, 0.5 * y).t,
                       cascade_aim(flat, var, radii, off, 1.5, None).t)
    free = torch.ones(1, 1, 16, 16, dtype=torch.bool)
    assert torch.equal(cascade_aim(z, var, radii, on, 1.5, free, y).t, cascade_aim(z, var, radii, off, 1.5, free).t)
    starved = var.clone()
    starved[:, 0] = 0.0
    near = torch.where(torch.arange(16) >= 8, 1.49, 1.0).expand(1, 3, 16, 16)   # 0.01 below ~z^1
    assert bool((cascade_aim(z, starved, radii, on, 1.5, None, near).t[..., 13:] > 1.495).all())
    with pytest.raises(ValueError, match="needs ~y"):
        cascade_aim(z, var, radii, on, 1.5, None)


def test_y_step_down_only_steps_no_aim_up():
    """cascade_aim(y_up=False): a trend up (~y above ~z^1 above the wide estimates, as a photon
    beside the hit points makes) steps the aim up to ~y with y_up and not at all without it,
    where the aim is the ~z^j's alone; a step down is the same either way."""
    from ppmrecon.model.guide import cascade_aim

    y, z, var, radii = _trend()
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, cascade=4.0, anchor_window=3.0, cascade_y=4.0)
    assert torch.equal(cascade_aim(z, var, radii, on, 1.5, None, y).t,
                       cascade_aim(z, var, radii, on, 1.5, None, y, y_up=False).t)
    peak_y, peak_z = 4.0 - y, 4.0 - z                   # mirrored: ~y 3 > ~z^1 2.5 > ~z^2 2 > wide 1
    plain = cascade_aim(peak_z, var, radii, replace(on, cascade_y=0.0), 1.5, None).t
    up = cascade_aim(peak_z, var, radii, on, 1.5, None, peak_y).t
    assert bool((up[..., 13:] > plain[..., 13:] + 0.3).all())          # stepped on up towards ~y's 3
    assert torch.equal(cascade_aim(peak_z, var, radii, on, 1.5, None, peak_y, y_up=False).t, plain)


def test_cascade_in_the_envelope_and_the_guide():
    """The envelope with the cascade on holds the biased wide ends out of the range and the
    anchor at the narrow level (the image near 1, not 3, on the right); converged inputs are
    returned exactly; the setting is checked and refuses what it cannot step from."""
    from ppmrecon.model.infer import buffer_aim

    buf = _biased_buffer(31)
    est = buf.estimates.copy()
    est[0] = 1.0
    buf = replace(buf, estimates=est)
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, anchor_window=3.0, cascade=4.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    cascaded = denoise(buf, model).rgb
    plain = denoise(buf, model, guide=replace(on, cascade=0.0)).rgb
    assert np.abs(cascaded[:, 16:] - 1.0).max() < 0.05
    assert plain[:, 16:].mean() > cascaded[:, 16:].mean() + 0.5
    assert buffer_aim(buf, replace(on, cascade=0.0), DEFAULT_ON) is None
    assert buffer_aim(buf, on, replace(DEFAULT_ON, enabled=False)) is None
    same = np.repeat(est[1:2], 5, axis=0)
    np.testing.assert_array_equal(denoise(replace(buf, estimates=same), model).rgb, same[0])
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match="cascade"):
            replace(on, cascade=bad)
    with pytest.raises(ValueError, match="anchor_source >= 2"):
        replace(on, anchor_source=1)
    with pytest.raises(ValueError, match="source >= 1"):
        replace(on, source=0)


def test_rgb_mean_is_bit_identical_to_mean():
    """rgb_mean: torch's mean over a dimension of 3, to the bit, on pixel-major (strided)
    and channels-first memory, with and without keepdim; other channel counts refused."""
    from ppmrecon.model.guard import rgb_mean

    torch.manual_seed(4)
    hwc = torch.rand(5, 7, 9, 3) * torch.logspace(-6, 6, 3)         # radiance over 12 decades
    for x, dim in ((hwc.permute(0, 3, 1, 2)[None], 2), (hwc, -1), (hwc.permute(3, 0, 1, 2).contiguous(), 0)):
        for keepdim in (False, True):
            assert torch.equal(rgb_mean(x, dim, keepdim), x.mean(dim, keepdim=keepdim))
    with pytest.raises(ValueError, match="4 channels"):
        rgb_mean(torch.zeros(4, 2, 2), 0)


def test_window_max_is_the_replicate_padded_max_pool():
    """window_max / window_max(op=min): the extremes over each pixel's K x K window, the
    window cut at the edges, as max_pool2d on a replicate-padded image."""
    from ppmrecon.model.guide import window_max

    torch.manual_seed(21)
    for h, w in ((9, 11), (1, 6), (5, 1), (2, 3)):          # images narrower than the window too
        x = torch.randn(2, 4, 3, h, w)
        for size in (1, 3, 5, 7):
            r = size // 2
            padded = torch.nn.functional.pad(x.view(2, 12, h, w), (r, r, r, r), mode="replicate")
            pooled = torch.nn.functional.max_pool2d(padded, size, stride=1).view_as(x)
            assert torch.equal(window_max(x, size=size), pooled)
            neg = torch.nn.functional.max_pool2d(-padded, size, stride=1).view_as(x)
            assert torch.equal(window_max(x, torch.minimum, size), -neg)
            assert not window_max(x, size=size).data_ptr() == x.data_ptr()   # a new tensor, x untouched


def test_terms_range_widens_towards_eq6_terms_by_a_share_capped_at_the_width():
    """terms_range: each end moves towards the extreme of Eq. 6's terms over the 3 x 3 window
    (brute force) by the share s, never inwards, by at most s x the range's width, the low
    end never below 0; s = 0 is the range itself; terms_share falls with N."""
    from ppmrecon.model.guide import terms_range, terms_share

    torch.manual_seed(22)
    y, z = torch.rand(1, 3, 10, 12) * 4, torch.rand(1, 4, 3, 10, 12)
    lo, hi = torch.minimum(y, z.amin(1)), torch.maximum(y, z.amax(1))
    t = _terms(y, z, 3)                                     # (1, 36, 3, H, W)
    width = hi - lo
    lo_full = torch.maximum(torch.minimum(lo, t.amin(1)), lo - width).clamp(min=0.0)
    hi_full = torch.minimum(torch.maximum(hi, t.amax(1)), hi + width)
    for share in (0.0, 0.3, 1.0):
        a, b = terms_range(y, z, lo, hi, share)
        torch.testing.assert_close(a, lo + share * (lo_full - lo), rtol=1e-6, atol=1e-6)
        torch.testing.assert_close(b, hi + share * (hi_full - hi), rtol=1e-6, atol=1e-6)
        assert bool((a <= lo).all() and (b >= hi).all() and (a >= 0).all())
        assert bool((lo - a <= share * width + 1e-6).all() and (b - hi <= share * width + 1e-6).all())
    assert bool((terms_range(y, z, lo, hi, 1.0)[1] > hi).any())     # it does widen somewhere
    cfg = replace(ENVELOPE, terms_passes=16.0)
    assert terms_share(16, cfg) == 0.5 and terms_share(4, cfg) == 0.8
    shares = [terms_share(n, cfg) for n in (1, 4, 16, 64, 256, 1024, 1 << 20)]
    assert shares == sorted(shares, reverse=True) and shares[-1] < 1e-4
    assert terms_share(4, ENVELOPE) == 0.0


def test_envelope_with_the_terms_range_is_consistent_and_needs_the_pass_count():
    """With terms_passes the envelope still returns converged inputs exactly (every term is
    the image, the range's width 0), changes the image of a noisy render, and refuses to run
    without the render's pass count."""
    from ppmrecon.model.guide import envelope

    buf = make_buffer(24, 24, seed=12)
    on = replace(ENVELOPE, terms_passes=16.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    same = np.repeat(buf.estimates[4:5], 5, axis=0)
    np.testing.assert_array_equal(denoise(replace(buf, estimates=same), model).rgb, same[0])
    few = replace(buf, header=dict(buf.header, **{B.H_PASSES: 4}))
    plain = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, ENVELOPE)
    assert not np.array_equal(denoise(few, model).rgb, denoise(few, plain).rgb)
    y, z = torch.rand(1, 3, 8, 8), torch.rand(1, 4, 3, 8, 8)
    with pytest.raises(ValueError, match="pass count"):
        envelope(torch.rand(1, 4, 8, 8), y, z, torch.rand(1, 1, 8, 8), DEFAULT_ON, on)
    # the widened room is the guide's: the anchor keeps within [min(lo, e), max(hi, e)],
    # e the guide held in the widened range, while the guide itself uses the room
    from ppmrecon.model.guide import terms_range, terms_share
    torch.manual_seed(23)
    y, z = torch.rand(1, 3, 20, 20), torch.rand(1, 4, 3, 20, 20)
    z[:, 2, :, 10, 10] = 50.0                              # a light in the anchor's aim
    guide = torch.rand(1, 4, 20, 20) * 2.0
    out = envelope(guide, y, z, torch.full((1, 1, 20, 20), 1e-8), DEFAULT_ON, on, passes=1)
    lo, hi = torch.minimum(y, z.amin(1)), torch.maximum(y, z.amax(1))
    wide_lo, wide_hi = terms_range(y, z, lo, hi, terms_share(1, on))
    e = torch.minimum(torch.maximum(guide[:, :3], wide_lo), wide_hi)
    assert bool((e > hi).any() and (e < lo).any())           # the guide did use the widened room
    assert bool((out <= torch.maximum(hi, e)).all() and (out >= torch.minimum(lo, e)).all())


def test_noise_range_holds_each_estimates_noise_interval_and_gates_sparkles():
    """noise_range: each end moves out to the estimates' X_k -+ kappa sqrt(V_k) (brute force),
    never inwards, the low end never below 0; an estimate whose sqrt(V) exceeds rel x its
    level is not widened; a lone ~y spike takes no part; zero variances or kappa 0 leave the
    range as it was (the consistency argument: the widening vanishes with the noise)."""
    from ppmrecon.model.guide import noise_range

    torch.manual_seed(27)
    y, z = torch.rand(1, 3, 6, 7) + 0.5, torch.rand(1, 4, 3, 6, 7) + 0.5
    v = torch.rand(1, 5, 6, 7) * 0.04
    lo, hi = torch.minimum(y, z.amin(1)), torch.maximum(y, z.amax(1))
    x = torch.cat([y[:, None], z], 1)
    sd = v.sqrt()[:, :, None]
    a, b = noise_range(y, z, v, lo, hi, 1.5)
    torch.testing.assert_close(a, torch.minimum(lo, (x - 1.5 * sd).amin(1)).clamp(min=0.0))
    torch.testing.assert_close(b, torch.maximum(hi, (x + 1.5 * sd).amax(1)))
    assert bool((a <= lo).all() and (b >= hi).all() and (a >= 0).all() and (b > hi).any())
    for zero in (noise_range(y, z, torch.zeros_like(v), lo, hi, 1.5), noise_range(y, z, v, lo, hi, 0.0)):
        assert torch.equal(zero[0], lo) and torch.equal(zero[1], hi)
    # the sparkle gate: ~z^2 at pixel (2, 3) has sd 0.5 x its level, above rel = 0.3
    z2 = z.clone()
    z2[:, 1, :, 2, 3] = 10.0
    v2 = torch.zeros_like(v)
    v2[:, 2, 2, 3] = 25.0
    lo2, hi2 = torch.minimum(y, z2.amin(1)), torch.maximum(y, z2.amax(1))
    gated = noise_range(y, z2, v2, lo2, hi2, 1.0, rel=0.3)
    assert torch.equal(gated[1], hi2) and torch.equal(gated[0], lo2)
    assert bool(noise_range(y, z2, v2, lo2, hi2, 1.0, rel=0.6)[1][..., 2, 3].ge(15.0 - 1e-5).all())
    # a lone ~y spike (left out of the range) does not widen it by its own noise
    y3 = y.clone()
    y3[..., 4, 4] = 100.0
    v3 = torch.zeros_like(v)
    v3[:, 0, 4, 4] = 1.0
    out = torch.zeros(1, 1, 6, 7, dtype=torch.bool)
    out[..., 4, 4] = True
    zlo, zhi = z.amin(1), z.amax(1)
    wide = noise_range(y3, z, v3, zlo, zhi, 2.0, y_out=out)
    assert torch.equal(wide[1][..., 4, 4], zhi[..., 4, 4]) and torch.equal(wide[0][..., 4, 4], zlo[..., 4, 4])
    assert bool((noise_range(y3, z, v3, zlo, zhi, 2.0)[1][..., 4, 4] >= 102.0).all())
    # the width test: only pixels whose bare range is within W x ~z^4's sd are widened
    w_only = noise_range(y, z, v, lo, hi, 1.5, width=2.0)
    narrow = (hi - lo).mean(1, keepdim=True) <= 2.0 * v[:, 4:].sqrt()
    assert bool(narrow.any() and (~narrow).any())
    torch.testing.assert_close(w_only[0], torch.where(narrow, a, lo))
    torch.testing.assert_close(w_only[1], torch.where(narrow, b, hi))
    # the isolation test: a pixel whose ~z^4 is above F x its 3 x 3 median keeps its bare range,
    # every other pixel is widened as without the test (a flat image: no pixel is isolated)
    z5 = z.clone()
    z5[:, 3, :, 1, 5] = 20.0                      # ~z^4 alone: 20 against neighbours of 0.5..1.5
    lo5, hi5 = torch.minimum(y, z5.amin(1)), torch.maximum(y, z5.amax(1))
    free = noise_range(y, z5, v, lo5, hi5, 1.5)
    held = noise_range(y, z5, v, lo5, hi5, 1.5, isolated=3.0)
    alone = torch.zeros(1, 1, 6, 7, dtype=torch.bool)
    alone[..., 1, 5] = True
    assert bool((free[1][..., 1, 5] > hi5[..., 1, 5]).all())
    torch.testing.assert_close(held[0], torch.where(alone, lo5, free[0]))
    torch.testing.assert_close(held[1], torch.where(alone, hi5, free[1]))
    for same in zip(noise_range(y, z, v, lo, hi, 1.5, isolated=3.0), (a, b)):
        assert torch.equal(*same)


def test_envelope_with_the_noise_range_lets_the_guide_leave_a_narrow_range():
    """With range_sigma the envelope needs the variances, returns converged inputs exactly,
    and keeps a guide that lies within the estimates' noise of a range narrower than it."""
    from ppmrecon.model.guide import envelope

    on = replace(ENVELOPE, range_sigma=1.0, range_sigma_rel=0.3)
    y = torch.full((1, 3, 8, 8), 1.0)
    z = torch.full((1, 4, 3, 8, 8), 1.02)                 # five estimates that err together
    guide = torch.full((1, 4, 8, 8), 0.95)                # the guide averaged that error away
    v = torch.full((1, 5, 8, 8), 0.1 ** 2)
    with pytest.raises(ValueError, match="variances"):
        envelope(guide, y, z, v[:, 4:], DEFAULT_ON, on)
    still = replace(DEFAULT_ON, anchor=0.0)                # the clamp alone
    bare = envelope(guide, y, z, v[:, 4:], still, replace(on, range_sigma=0.0))
    wide = envelope(guide, y, z, v[:, 4:], still, on, variances=v)
    torch.testing.assert_close(bare, torch.ones_like(bare))
    torch.testing.assert_close(wide, torch.full_like(wide, 0.95))
    buf = make_buffer(24, 24, seed=13)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    same = np.repeat(buf.estimates[4:5], 5, axis=0)
    np.testing.assert_array_equal(denoise(replace(buf, estimates=same, variances=np.zeros_like(buf.variances)),
                                          model).rgb, same[0])


def test_aim_spikes_are_lone_bright_pixels_and_spike_estimate_weighs_by_variance():
    """aim_spikes: a light of one or two pixels far above its other neighbours is one; a
    bright patch (its corners too), a thin bright line (but its two ends) or a pixel less
    than R x above its neighbours is not; spike_estimate is the inverse-variance mean of ~y and ~z (their plain
    mean where both variances are 0)."""
    from ppmrecon.model.guide import aim_spikes, spike_estimate

    t = torch.ones(1, 3, 16, 16)
    t[..., 3, 3] = 100.0                                  # a lone light
    t[..., 3, 7:9] = 100.0                                # a light of two pixels
    t[..., 7:10, 7:10] = 100.0                            # a bright patch
    t[..., 13, 2:12] = 100.0                              # a thin bright line
    t[..., 3, 12] = 5.0                                   # 5x its neighbours: below R = 8
    s = aim_spikes(t, 1e-3, 8.0)
    expected = torch.zeros(1, 1, 16, 16, dtype=torch.bool)
    expected[..., 3, 3] = expected[..., 3, 7] = expected[..., 3, 8] = True
    expected[..., 13, 2] = expected[..., 13, 11] = True    # a line's ends have one bright neighbour
    assert torch.equal(s, expected)
    assert aim_spikes(t, 1e-3, 4.0).sum() == 6
    y, z = torch.full((1, 3, 2, 2), 10.0), torch.full((1, 3, 2, 2), 40.0)
    vy = torch.tensor([[[[1.0, 3.0], [0.0, 0.0]]]])
    vz = torch.tensor([[[[1.0, 1.0], [0.0, 2.0]]]])
    est = spike_estimate(y, z, vy, vz)[0, 0]
    torch.testing.assert_close(est, torch.tensor([[25.0, 32.5], [25.0, 10.0]]))


def test_envelope_anchor_spikes_keeps_a_lone_light_out_of_its_neighbours():
    """The anchor spreads the gap between a lone bright pixel of its aim and the (flattened)
    guide into a ring of neighbours, lifting them to the top of their range; with
    anchor_spikes the neighbours keep the guide and the light takes the inverse-variance
    mean of ~y and ~z^4; converged inputs come back exactly either way."""
    from ppmrecon.model.guide import envelope

    h = w = 15
    y = torch.full((1, 3, h, w), 1.5)                    # room above the guide in every pixel
    z = torch.full((1, 4, 3, h, w), 1.0)
    y[..., 7, 7], z[..., 7, 7] = 50.0, 150.0             # a small light seen from both hit points
    guide = torch.ones(1, 4, h, w)                        # OIDN took the light for a firefly
    small = torch.full((1, 1, h, w), 1e-8)
    vy, v4 = torch.full((1, 1, h, w), 1.0), torch.full((1, 1, h, w), 1.0)
    vy[..., 7, 7], v4[..., 7, 7] = 100.0, 300.0
    plain = replace(ENVELOPE, anchor_source=3)
    on = replace(plain, anchor_spikes=8.0)
    halo = envelope(guide, y, z, small, DEFAULT_ON, plain)
    kept = envelope(guide, y, z, small, DEFAULT_ON, on, spike_variances=(vy, v4))
    ring = torch.zeros(h, w, dtype=torch.bool)
    ring[5:10, 5:10] = True
    ring[7, 7] = False
    assert float(halo[0, :, ring].mean()) > 1.2           # the ring lifted towards ~y
    assert torch.equal(kept[0, :, ring], torch.ones_like(kept[0, :, ring]))
    torch.testing.assert_close(kept[0, :, 7, 7], torch.full((3,), 0.75 * 50.0 + 0.25 * 150.0))
    with pytest.raises(ValueError, match="anchor_spikes"):
        envelope(guide, y, z, small, DEFAULT_ON, on)
    buf = make_buffer(24, 24, seed=12)
    same = np.repeat(buf.estimates[4:5], 5, axis=0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    np.testing.assert_array_equal(denoise(replace(buf, estimates=same), model).rgb, same[0])


def test_lone_y_spikes_are_above_every_z_and_their_own_neighbourhood(monkeypatch):
    """A ~y pixel far above the ~z^j of its pixel and its own 3 x 3 median is a lone spike;
    one the ~z^j share (a real bright feature), or one in a bright ~y neighbourhood (a
    caustic only the narrowest gather resolves) is not; the test is per pixel, not per N."""
    from ppmrecon.model.guide import lone_y_spikes

    y = torch.full((1, 3, 9, 9), 1.0)
    z = torch.full((1, 4, 3, 9, 9), 1.0)
    y[..., 2, 2] = 500.0                                   # alone: a spike
    y[..., 6, 6] = 500.0                                   # the ~z^j see it too (one of them is enough)
    z[:, 3, :, 6, 6] = 100.0
    y[..., 5:8, 1:4] = 200.0                               # a bright ~y patch of 3 x 3
    y[..., 6, 2] = 2000.0                                  # 10x its neighbours: below 16x
    spikes = lone_y_spikes(y, z, 1e-3, 16.0)[0, 0]
    assert bool(spikes[2, 2]) and not bool(spikes[6, 6]) and not bool(spikes[6, 2])
    assert int(spikes[:4].sum()) == 1                      # nothing else near the lone spike
    assert not lone_y_spikes(y, z, 1e-3, 1e3)[0, 0].any()   # 500x is below a factor of 1000
    import ppmrecon.model.guide as guide_module

    for dense in (0.0, 1.0):                               # the whole image's medians, or the candidates' only
        monkeypatch.setattr(guide_module, "DENSE_SPIKES", dense)
        assert torch.equal(lone_y_spikes(y, z, 1e-3, 16.0)[0, 0], spikes)


def test_envelope_keeps_a_lone_y_spike_out_of_the_output():
    """issue 12, ``0036_bright_emitters``: a ~y firefly that the guard keeps (many passes)
    and OIDN spreads into the guide; with ``y_spike`` the pixel's range is that of its
    ~z^j, so the output stays there; without it the output follows the guide towards the
    spike. Pixels without a spike are unchanged."""
    buf = make_buffer(32, 32, seed=21)
    est = buf.estimates.copy()
    est[0, 16:18, 16:18] = 3e4                             # ~y alone, 1e4 x the image: a 2 x 2 cluster
    header = dict(buf.header, **{B.H_PASSES: 1 << 20})     # the guard's threshold grows with N: kept
    buf = replace(buf, estimates=est, header=header)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, replace(ENVELOPE, y_weight=2.0))
    zmin, zmax = est[1:, 16:18, 16:18].min(0), est[1:, 16:18, 16:18].max(0)
    off = denoise(buf, model, guide=replace(model.guide, y_spike=0.0)).rgb
    on = denoise(buf, model, guide=replace(model.guide, y_spike=16.0)).rgb
    assert float(off[16:18, 16:18].mean()) > 10 * float(zmax.mean())
    assert bool((on[16:18, 16:18] <= zmax + 1e-6).all()) and bool((on[16:18, 16:18] >= zmin - 1e-6).all())
    far = np.ones((32, 32), bool)
    far[8:25, 8:25] = False                                # beyond the guide's reach of the spike
    np.testing.assert_allclose(on[far], off[far], rtol=1e-5, atol=1e-6)


def test_lone_z_spikes_are_unsettled_z_over_a_settled_y():
    """The mirror of a lone ~y spike: every ~z^j far above a settled ~y and none of them
    settled (light hit point B's eye path alone saw once). Not where ~y is unsettled too (a coin toss
    between two events), nor where a ~z^j is settled (a light B sees over many passes), nor
    where one ~z^j is within the factor, nor where ~y is 0 (no event: not settled)."""
    from ppmrecon.model.guide import lone_z_spikes

    y = torch.full((1, 3, 8, 8), 0.01)
    z = torch.full((1, 4, 3, 8, 8), 0.012)
    var = torch.full((1, 5, 8, 8), 1e-8)                   # sqrt(V)/mean 0.01: settled everywhere
    for r, c in ((2, 2), (5, 5), (2, 5), (5, 2)):
        z[..., r, c], var[:, 1:, r, c] = 1.0, 1.0          # every ~z^j one event of 1.0
    var[:, 0, 5, 5] = 1e-4                                 # ~y one event too
    var[:, 4, 2, 5] = 1e-3                                 # ~z^4 settled
    z[:, 0, :, 5, 2] = 0.05                                # ~z^1 5x ~y only
    spikes = lone_z_spikes(y, z, var, 1e-3, 8.0, 0.5)[0, 0]
    assert bool(spikes[2, 2]) and int(spikes.sum()) == 1
    assert not lone_z_spikes(y, z, var, 1e-3, 200.0, 0.5).any()     # 100x is below a factor of 200
    y[..., 2, 2] = 0.0
    assert not lone_z_spikes(y, z, var, 1e-3, 8.0, 0.5).any()


def test_envelope_holds_a_lone_z_spike_at_y():
    """issue 12, ``0148_bright_emitters``: light that hit point B's eye path alone saw lifts all
    four ~z^j of a pixel (the guard keeps it beside a light, here: after many passes) and the
    guide follows it; with ``z_spike`` the pixel's range is ~y's alone, so the output is ~y
    there. Pixels beyond the anchor's reach are unchanged."""
    buf = make_buffer(32, 32, seed=22)
    est, var = buf.estimates.copy(), buf.variances.copy()
    est[1:, 16, 16], var[1:, 16, 16] = 3e3, 9e6            # every ~z^j: one event (sqrt(V)/mean 1)
    buf = replace(buf, estimates=est, variances=var, header=dict(buf.header, **{B.H_PASSES: 1 << 20}))
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, replace(ENVELOPE, y_weight=2.0))
    off = denoise(buf, model, guide=replace(model.guide, z_spike=0.0)).rgb
    on = denoise(buf, model, guide=replace(model.guide, z_spike=8.0)).rgb
    assert float(off[16, 16].mean()) > 10 * float(est[0, 16, 16].mean())
    np.testing.assert_allclose(on[16, 16], est[0, 16, 16], rtol=1e-6)
    far = np.ones((32, 32), bool)
    far[8:25, 8:25] = False
    np.testing.assert_allclose(on[far], off[far], rtol=1e-5, atol=1e-6)


def test_speckle_field_is_where_every_estimate_is_unsettled():
    """All five unsettled (one event, or ~y without one) is a speckle pixel; one settled
    estimate, ~y or any ~z^j, is not, nor a pixel whose widest gather ~z^4 stayed empty (a
    dark pixel); r = 0 is off."""
    from ppmrecon.model.guide import speckle_field

    y = torch.full((1, 3, 4, 4), 1.0)
    z = torch.full((1, 4, 3, 4, 4), 1.0)
    var = torch.full((1, 5, 4, 4), 1.0)                     # sqrt(V)/mean 1: one event everywhere
    y[..., 0, 0], z[..., 0, 0], var[..., 0, 0] = 0.0, 0.0, 0.0   # no photon at all: dark
    y[..., 3, 3], var[:, 0, 3, 3] = 0.0, 0.0                 # ~y caught nothing, ~z^4 one event: a speckle
    var[:, 0, 1, 1] = 0.01                                   # ~y settled
    var[:, 3, 2, 2] = 0.01                                   # ~z^3 settled
    field = speckle_field(y, z, var, 0.5)[0, 0]
    assert bool(field[3, 3]) and int(field.sum()) == 13
    assert not bool(field[0, 0]) and not bool(field[1, 1]) and not bool(field[2, 2])
    assert speckle_field(y, z, var, 0.0) is None


def test_envelope_anchor_free_leaves_the_range_only_in_a_speckle_field():
    """A field of one-event speckles (the glossy floor of the literature cornell-box): the
    widest gather ~z^4 catches a photon of very uneven value at every pixel, the others
    rarely. The guide's smooth level clamped into each pixel's range loses much of its
    energy (most pixels' range ends below it), and the anchor cannot bring it back through
    the clamp; with ``anchor_free`` the range there reaches the 5 x 5 medians of its ends,
    so the field keeps more of its mean. Where the estimates are settled the output is
    the clamped one, bit for bit, and a settled light beside the field does not widen it."""
    from ppmrecon.model.guide import envelope

    gen = torch.Generator().manual_seed(3)
    h = w = 32
    z4 = 4.0 * torch.rand(1, 1, h, w, generator=gen) ** 3                   # mean 1, mostly small
    y = torch.zeros(1, 3, h, w)
    z = torch.zeros(1, 4, 3, h, w)
    z[:, 3] = z4.expand(1, 3, h, w)
    var = torch.zeros(1, 5, h, w)
    var[:, 4] = z4[:, 0] ** 2                                                # sqrt(V)/mean 1: one event
    y[..., :, 24:], z[..., :, 24:], var[..., :, 24:] = 1.0, 1.0, 1e-4       # a settled strip on the right
    z[..., 0, 20], var[:, 1:, 0, 20] = 1e4, 1.0                              # a settled light in the field
    guide = torch.cat([torch.full((1, 3, h, w), 1.0), torch.full((1, 1, h, w), 0.5)], 1)
    plain = replace(ENVELOPE, anchor_source=4)
    clamped = envelope(guide, y, z, var[:, 4:], DEFAULT_ON, plain, variances=var)
    free = envelope(guide, y, z, var[:, 4:], DEFAULT_ON, replace(plain, anchor_free=0.5), variances=var)
    field = (slice(8, 32), slice(0, 16))
    kept, lost = float(free[..., field[0], field[1]].mean()), float(clamped[..., field[0], field[1]].mean())
    assert lost < 0.7 and kept > lost + 0.1                                  # the field's mean is 0.95
    assert torch.equal(free[..., :, 24:], clamped[..., :, 24:]) and bool((free >= 0).all())
    beside = free[..., :3, 18:23].clone()
    beside[..., 0, 2] = 0.0                                                  # the light itself
    assert float(beside.max()) <= 4.0                                        # its neighbours: the field's range
    with pytest.raises(ValueError, match="anchor_free"):
        envelope(guide, y, z, var[:, 4:], DEFAULT_ON, replace(plain, anchor_free=0.5))


def test_anchor_free_dark_keeps_a_negligible_photon_out_of_the_speckle_field():
    """``anchor_free_dark`` D: a pixel whose ~z^4 caught a photon of negligible value (at most
    D x the guard's floor x the image's scale) beside a bright region is dark, not a speckle:
    its range is its own and the anchor cannot lift it towards the light (``holdout_n1024_s16``
    ``0000_bright_emitters`` N = 16: all five estimates below 1e-8, reference 1.0, output 161
    with D = 0). A real one-event speckle of the field stays free; D = 0 is the old rule."""
    from ppmrecon.model.guide import envelope, speckle_field

    h = w = 16
    y = torch.zeros(1, 3, h, w)
    z = torch.zeros(1, 4, 3, h, w)
    var = torch.zeros(1, 5, h, w)
    y[...], z[...], var[...] = 100.0, 300.0, 1e6                # a bright field, unsettled (one event)
    y[..., 8, 7], z[..., 8, 7], var[..., 8, 7] = 0.0, 0.0, 0.0   # in it: a dark pixel whose ~z^4
    z[:, 3, :, 8, 7], var[:, 4, 8, 7] = 1e-8, 1e-16             # caught a negligible photon
    y[..., 4, 4], z[..., 4, 4], var[..., 4, 4] = 0.0, 0.0, 0.0   # and a real one-event speckle
    z[:, 3, :, 4, 4], var[:, 4, 4, 4] = 5.0, 25.0
    scale = 150.0
    old = speckle_field(y, z, var, 0.5)[0, 0]
    new = speckle_field(y, z, var, 0.5, 0.1 * 1e-3 * scale)[0, 0]
    assert bool(old[8, 7]) and not bool(new[8, 7]) and bool(new[4, 4]) and bool(old[4, 4])
    guide = torch.cat([torch.full((1, 3, h, w), 150.0), torch.full((1, 1, h, w), 1.0)], 1)
    plain = replace(ENVELOPE, anchor_source=4, anchor_free=0.5)
    lifted = envelope(guide, y, z, var[:, 4:], DEFAULT_ON, plain, scale, variances=var)
    kept = envelope(guide, y, z, var[:, 4:], DEFAULT_ON, replace(plain, anchor_free_dark=0.1), scale, variances=var)
    assert float(lifted[0, :, 8, 7].max()) > 1.0                 # the light's median let it up
    assert float(kept[0, :, 8, 7].max()) <= 1e-8
    assert torch.equal(kept[0, :, 4, 4], lifted[0, :, 4, 4]) and float(kept[0, :, 4, 4].max()) > 5.0
    for bad in (-1.0, float("nan")):
        with pytest.raises(ValueError, match="anchor_free_dark"):
            replace(plain, anchor_free_dark=bad)


def _nlm_source_flags_agree(tmp_path, capsys, buf, settings: dict[str, str], header_part: str,
                            refused: tuple[str, ...] = ()) -> None:
    """``ppmrecon-denoise --guide-denoiser nlm_source --guide-y-weight 2`` with the NL-means
    ``settings`` (flag -> value) writes what ``ppmrecon.denoise`` returns with the same keywords,
    its guide header holds ``header_part``; each setting's flag, and each of ``refused``,
    refuses negative and NaN values (:func:`_refuses_negative_and_nan`)."""
    import ppmrecon

    args = _envelope_cli(tmp_path, buf) + ["--guide-denoiser", "nlm_source", "--guide-y-weight", "2"]
    chosen = [item for pair in settings.items() for item in pair]
    assert denoise_main(args + chosen + ["-o", str(tmp_path / "cli.exr")]) == 0
    image, header = B.read_rgb(tmp_path / "cli.exr")
    assert header_part in header["ppmrecon.guide"]
    keywords = {flag[2:].replace("-", "_"): float(value) for flag, value in settings.items()}
    np.testing.assert_array_equal(ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope",
                                                   guide_denoiser="nlm_source", guide_y_weight=2.0, **keywords), image)
    for flag in (*settings, *refused):
        _refuses_negative_and_nan(tmp_path, capsys, buf, args, flag)


def test_nlm_y_passes_gates_nl_means_for_y_by_passes(tmp_path, capsys):
    """GuideConfig.nlm_y_passes M with denoiser nlm_source: a render of M passes or more has
    ~y denoised by NL-means too (exactly as denoiser nlm), one of fewer by OIDN (exactly as
    nlm_source alone); ``nlm_y_k`` sets NL-means' k for ~y (0 = nlm_k). The flags agree with
    the API, the header names them; negative or not a number: one clear line, exit 2."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=43)
    # variances about the pixels' spread (std 1.2), so that NL-means' k matters
    buf = replace(buf, variances=np.ones_like(buf.variances), header=dict(buf.header, **{B.H_PASSES: 32}))
    on = replace(ENVELOPE, denoiser="nlm_source", y_weight=2.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    source_only = denoise(buf, model).rgb
    both = denoise(buf, model, guide=replace(on, denoiser="nlm")).rgb
    assert not np.array_equal(source_only, both)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, nlm_y_passes=32.0)).rgb, both)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, nlm_y_passes=33.0)).rgb, source_only)
    y_k = denoise(buf, model, guide=replace(on, nlm_y_passes=32.0, nlm_y_k=1.0)).rgb
    assert not np.array_equal(y_k, both)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, denoiser="nlm", nlm_y_k=1.0)).rgb, y_k)
    _nlm_source_flags_agree(tmp_path, capsys, buf, {"--guide-nlm-y-passes": "16", "--guide-nlm-y-k": "1"},
                            "oidn(y, fast) nlm(y from N=16) k(y)=1 ", ("--guide-anchor-free-dark",))


def test_nlm_image_of_several_images_shares_one_set_of_weights():
    """nlm_image of G stacked images: one image alone is what it was; two copies of one image
    (each with its own variance) give that image twice, with the weights of the mean distance
    (the same as one image whose normalised distance is that mean: here, equal variances);
    where a second image carries an edge the first one's noise hides, the joint filter keeps
    the first image's edge too."""
    from ppmrecon.model.guide import nlm_image

    gen = torch.Generator().manual_seed(11)
    a = torch.rand(3, 20, 20, generator=gen)
    va = torch.full((20, 20), 0.02)
    alone = nlm_image(a, va, 0.7)
    both = nlm_image(torch.cat([a, a]), torch.stack([va, va]), 0.7)
    torch.testing.assert_close(both[:3], alone, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(both[3:], alone, rtol=1e-5, atol=1e-6)
    step = torch.zeros(3, 20, 20)
    step[..., 10:] = 1.0
    noisy = step + 0.5 * torch.randn(3, 20, 20, generator=gen)       # the edge lies within its noise
    clean = step + 0.01 * torch.randn(3, 20, 20, generator=gen)
    own = nlm_image(noisy, torch.full((20, 20), 0.25), 0.7)
    joint = nlm_image(torch.cat([noisy, clean]), torch.stack([torch.full((20, 20), 0.25),
                                                              torch.full((20, 20), 1e-4)]), 0.7)[:3]
    def contrast(x):
        return float(x[..., 12:].mean() - x[..., :8].mean())
    assert contrast(joint) > 0.9 and contrast(own) < contrast(joint)


def _nlm_by_offsets(colour: torch.Tensor, variance: torch.Tensor, k: float, radius: int, patch: int) -> torch.Tensor:
    """nlm_image's formula evaluated one offset at a time, the patch mean by avg_pool2d: the
    reference the mirrored-offset loop must match."""
    import math

    from ppmrecon.model.guide import NLM_CUT

    groups = 1 if variance.dim() == 2 else variance.shape[0]
    u, v = colour[None], variance.reshape(1, groups, *variance.shape[-2:])
    h, w = u.shape[-2:]
    pu = torch.nn.functional.pad(u, (radius,) * 4, mode="replicate")
    pv = torch.nn.functional.pad(v, (radius,) * 4, mode="replicate")
    num, den = torch.zeros_like(u), torch.zeros(1, 1, h, w)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            uq, vq = pu[..., dy:dy + h, dx:dx + w], pv[..., dy:dy + h, dx:dx + w]
            d = ((u - uq) ** 2).view(1, groups, 3, h, w).mean(2) - (v + torch.minimum(v, vq))
            d = (d / (k * k * (v + vq) + torch.finfo(torch.float32).tiny)).mean(1, keepdim=True)
            d = torch.nn.functional.avg_pool2d(d, 2 * patch + 1, stride=1, padding=patch, count_include_pad=False)
            wt = torch.exp(-d.clamp(0.0, NLM_CUT)) - math.exp(-NLM_CUT)
            num += wt * uq
            den += wt
    return (num / den)[0]


def test_nlm_image_matches_its_formula_offset_by_offset():
    """The mirrored-offset loop with its separable box (nlm_image) is the formula of its
    docstring: the same as one pass per offset with avg_pool2d, for one and two images, window
    half widths 1..3 and patches 1..2, on images of uneven size."""
    from ppmrecon.model.guide import nlm_image

    gen = torch.Generator().manual_seed(61)
    colour = 2.0 * torch.rand(6, 13, 17, generator=gen)
    variance = 0.2 * torch.rand(2, 13, 17, generator=gen)
    for c, v in ((colour[:3], variance[0]), (colour, variance)):
        for radius, patch in ((1, 1), (2, 1), (3, 1), (3, 2)):
            torch.testing.assert_close(nlm_image(c, v, 0.7, radius, patch), _nlm_by_offsets(c, v, 0.7, radius, patch),
                                       rtol=1e-5, atol=1e-6)


def test_nlm_image_with_albedo_averages_across_texture_and_keeps_what_it_does_not_explain():
    """nlm_image's ``albedo``: on a textured diffuse surface (radiance = albedo x a smooth
    irradiance, noise of the mean proportional to it) the albedo-aware filter lands closer to
    the clean image than the plain one, which stops at every texture edge; where the albedo is
    flat it is the plain filter; a highlight independent of the texture (radiance not the
    albedo's) does not get the texture printed into it."""
    from ppmrecon.model.guide import nlm_image

    gen = torch.Generator().manual_seed(29)
    size = 32
    texture = torch.where((torch.arange(size)[:, None] // 2 + torch.arange(size)[None] // 2) % 2 == 0, 0.8, 0.2)
    irradiance = 1.0 + 0.3 * torch.linspace(0, 1, size)[None].expand(size, size)
    clean = (texture * irradiance).expand(3, size, size)
    variance = (0.25 * clean[0]) ** 2
    noisy = clean + variance.sqrt() * torch.randn(3, size, size, generator=gen)
    albedo = texture + 0.05

    def error(x: torch.Tensor, truth: torch.Tensor) -> float:
        return float(((x - truth) ** 2 / (truth ** 2 + 1e-2)).mean())

    plain = nlm_image(noisy, variance, 0.7)
    aware = nlm_image(noisy, variance, 0.7, albedo=albedo, albedo_penalty=2.0)
    assert error(aware, clean) < 0.6 * error(plain, clean)
    flat = torch.full((size, size), 0.55)
    torch.testing.assert_close(nlm_image(noisy, variance, 0.7, albedo=flat), plain, rtol=1e-5, atol=1e-6)
    # a highlight over the texture: the radiance is the same on both albedos
    glossy = torch.full((3, size, size), 2.0)
    g_var = torch.full((size, size), 0.01)
    g_noisy = glossy + 0.1 * torch.randn(3, size, size, generator=gen)
    g_aware = nlm_image(g_noisy, g_var, 0.7, albedo=albedo, albedo_penalty=2.0)
    assert error(g_aware, glossy) <= 1.05 * error(nlm_image(g_noisy, g_var, 0.7), glossy)
    # no texture pattern imprinted: the two albedos' pixels end at the same level
    assert abs(float(g_aware[:, texture > 0.5].mean() - g_aware[:, texture < 0.5].mean())) < 5e-4


def test_nlm_image_with_rgb_albedo_divides_out_a_texture_of_two_hues():
    """nlm_image's ``albedo`` (3, H, W): a checker of two hues of one brightness (green and
    pink, the same RGB mean) is no texture to the scalar demodulation, which stops at every
    edge as the plain filter does; divided per channel it is, and the filter lands much closer
    to the clean image. Where the albedo is the same at both pixels of a pair the distance is
    the plain one: a flat saturated albedo leaves the image exactly as the plain filter does."""
    from ppmrecon.model.guide import nlm_image

    gen = torch.Generator().manual_seed(31)
    size = 32
    cells = (torch.arange(size)[:, None] // 2 + torch.arange(size)[None] // 2) % 2 == 0
    green, pink = torch.tensor([0.2, 0.7, 0.3]), torch.tensor([0.7, 0.2, 0.5])
    texture = torch.where(cells[None], green[:, None, None], pink[:, None, None])
    irradiance = 1.0 + 0.3 * torch.linspace(0, 1, size)[None].expand(size, size)
    clean = texture * irradiance
    # photon noise: each channel's the same share of its own value; V the channels' mean
    noisy = clean + 0.25 * clean * torch.randn(3, size, size, generator=gen)
    variance = ((0.25 * clean) ** 2).mean(0)

    def error(x: torch.Tensor) -> float:
        return float(((x - clean) ** 2 / (clean ** 2 + 1e-2)).mean())

    plain = nlm_image(noisy, variance, 0.7)
    by_mean = nlm_image(noisy, variance, 0.7, albedo=texture.mean(0) + 0.05, albedo_penalty=1.0)
    by_channel = nlm_image(noisy, variance, 0.7, albedo=texture + 0.05, albedo_penalty=1.0)
    assert error(by_mean) > 0.9 * error(plain)
    assert error(by_channel) < 0.75 * error(plain)
    blue = torch.tensor([0.01, 0.01, 0.89])[:, None, None].expand(3, size, size) + 0.05
    torch.testing.assert_close(nlm_image(noisy, variance, 0.7, albedo=blue, albedo_penalty=1.0), plain,
                               rtol=1e-5, atol=1e-6)


def test_nlm_albedo_setting_reaches_the_guide_flags_and_api(tmp_path, capsys):
    """GuideConfig.nlm_albedo F > 0 gives the guide's NL-means the albedo (changes the image of
    a textured buffer), 0 leaves it exactly as it was; ``--guide-nlm-albedo`` /
    ``--guide-nlm-albedo-eps`` agree with the API and the header names them; negative or not
    a number: one clear line, exit 2; an eps of 0 is refused by the config. Per channel
    (``nlm_albedo_channels`` "rgb", ``--guide-nlm-albedo-channels``): the same image for a grey
    albedo, another for a hued one; a name not in the list is refused."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=53)
    rng = np.random.default_rng(53)
    albedo = np.repeat(rng.choice([0.1, 0.8], size=(24, 24, 1)), 3, -1).astype(np.float32)
    buf = replace(buf, albedo=albedo, variances=np.ones_like(buf.variances),
                  header=dict(buf.header, **{B.H_PASSES: 32}))
    on = replace(ENVELOPE, denoiser="nlm_source", y_weight=2.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    plain = denoise(buf, model).rgb
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, nlm_albedo=0.0, nlm_albedo_eps=0.2)).rgb,
                                  plain)
    aware = denoise(buf, model, guide=replace(on, nlm_albedo=2.0)).rgb
    assert not np.array_equal(aware, plain)
    _nlm_source_flags_agree(tmp_path, capsys, buf, {"--guide-nlm-albedo": "2", "--guide-nlm-albedo-eps": "0.1"},
                            "r=3 albedo=2(+0.1)")
    for bad in (0.0, -1.0, float("nan")):
        with pytest.raises(ValueError, match="nlm_albedo_eps"):
            replace(on, nlm_albedo_eps=bad)
    hued = replace(buf, albedo=(albedo * np.array([1.0, 0.4, 0.7], np.float32)))
    by_mean = denoise(hued, model, guide=replace(on, nlm_albedo=2.0)).rgb
    by_channel = denoise(hued, model, guide=replace(on, nlm_albedo=2.0, nlm_albedo_channels="rgb")).rgb
    assert not np.array_equal(by_mean, by_channel)
    args = _envelope_cli(tmp_path, hued) + ["--guide-denoiser", "nlm_source", "--guide-y-weight", "2",
                                            "--guide-nlm-albedo", "2", "--guide-nlm-albedo-channels", "rgb"]
    assert denoise_main(args + ["-o", str(tmp_path / "rgb.exr")]) == 0
    image, header = B.read_rgb(tmp_path / "rgb.exr")
    assert "albedo=2(+0.05, rgb)" in header["ppmrecon.guide"]
    np.testing.assert_array_equal(ppmrecon.denoise(hued, tmp_path / "m.pt", guide_mode="envelope",
                                                   guide_denoiser="nlm_source", guide_y_weight=2.0,
                                                   guide_nlm_albedo=2.0, guide_nlm_albedo_channels="rgb"), image)
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        denoise_main(args[:-1] + ["hsv", "-o", str(tmp_path / "bad.exr")])
    assert exc.value.code == 2 and "--guide-nlm-albedo-channels" in capsys.readouterr().err
    with pytest.raises(ValueError, match="nlm_albedo_channels"):
        replace(on, nlm_albedo_channels="hsv")


def test_range_sigma_setting_reaches_the_envelope_flags_and_api(tmp_path, capsys):
    """GuideConfig.range_sigma K > 0 changes the envelope of a noisy buffer, 0 leaves it exactly
    as it was whatever range_sigma_rel says; ``--guide-range-sigma`` / ``--guide-range-sigma-rel`` /
    ``--guide-range-sigma-width`` / ``--guide-range-sigma-isolated`` agree with the API and the
    header names them; negative or not a number: one clear line, exit 2."""
    buf = make_buffer(24, 24, seed=57)
    buf = replace(buf, variances=np.full_like(buf.variances, 0.05), header=dict(buf.header, **{B.H_PASSES: 64}))
    on = replace(ENVELOPE, denoiser="nlm_source", y_weight=2.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    plain = denoise(buf, model).rgb
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, range_sigma_rel=0.3)).rgb, plain)
    wide = denoise(buf, model, guide=replace(on, range_sigma=1.0)).rgb
    assert not np.array_equal(wide, plain)
    _nlm_source_flags_agree(tmp_path, capsys, buf, {"--guide-range-sigma": "1", "--guide-range-sigma-rel": "0.3",
                                                    "--guide-range-sigma-width": "3"}, "range=1sd(<=0.3)(width<=3sd)")
    _nlm_source_flags_agree(tmp_path, capsys, buf, {"--guide-range-sigma": "1", "--guide-range-sigma-isolated": "3"},
                            "range=1sd(isolated>3x)")


def test_nlm_joint_passes_denoises_source_and_y_together(tmp_path, capsys):
    """GuideConfig.nlm_joint_passes M: a render of M passes or more (and fewer than
    nlm_y_passes, from where each image has its own NL-means) has the source and ~y denoised by
    one joint NL-means (k = nlm_joint_k), one of fewer as without it; the flags agree with the API and the header names them; negative or not a
    number: one clear line, exit 2."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=47)
    buf = replace(buf, variances=np.ones_like(buf.variances), header=dict(buf.header, **{B.H_PASSES: 32}))
    on = replace(ENVELOPE, denoiser="nlm_source", y_weight=2.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    plain = denoise(buf, model).rgb
    joint = denoise(buf, model, guide=replace(on, nlm_joint_passes=32.0, nlm_joint_k=0.7)).rgb
    assert not np.array_equal(plain, joint)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, nlm_joint_passes=33.0, nlm_joint_k=0.7)).rgb,
                                  plain)
    many = denoise(buf, model, guide=replace(on, nlm_joint_passes=16.0, nlm_joint_k=0.7, nlm_y_passes=32.0,
                                             nlm_y_k=1.0)).rgb            # from nlm_y_passes: each its own
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, denoiser="nlm", nlm_y_k=1.0)).rgb, many)
    assert not np.array_equal(many, joint)
    _nlm_source_flags_agree(tmp_path, capsys, buf, {"--guide-nlm-joint-passes": "16", "--guide-nlm-joint-k": "0.7"},
                            " oidn(y, fast) below N=16, joint(z4 + y) from N=16 k=0.7 ")


def test_redistribute_gives_back_the_clamps_loss_within_each_pixels_range():
    """A smooth level clamped into a speckle field's ranges loses energy; ``redistribute``
    gives part of it back to the pixels with room, never outside their own ``[lo, hi]``,
    and changes nothing where the clamp took nothing."""
    from ppmrecon.model.guide import redistribute

    gen = torch.Generator().manual_seed(5)
    lo = torch.zeros(1, 3, 32, 32)
    hi = (4.0 * torch.rand(1, 1, 32, 32, generator=gen) ** 3).expand(1, 3, 32, 32).contiguous()
    anchored = torch.ones(1, 3, 32, 32)
    held = torch.minimum(torch.maximum(anchored, lo), hi)
    out = redistribute(anchored, held, lo, hi, 1.5)
    assert bool((out >= lo).all()) and bool((out <= hi).all())
    lost, kept = float((anchored - held).mean()), float((out - held).mean())
    assert lost > 0.2 and kept > 0.2 * lost                  # the room is capped at the local level
    inside = torch.full_like(anchored, 0.5)
    assert torch.equal(redistribute(inside, inside, lo, hi + 1.0, 1.5), inside)
    with pytest.raises(ValueError, match="redistribute"):
        GuideConfig(redistribute=-1.0)


def test_noise_correlation_and_the_variance_of_a_low_pass_of_correlated_noise():
    """White noise blurred by a Gaussian of s0 px has a Gaussian autocorrelation of width
    s0: the neighbour correlation estimated from the image alone is exp(-1 / (4 s0^2)), and
    the predicted variance of its sigma-low-pass matches the measured one (the independent
    formula underestimates it several times); white noise reads as uncorrelated."""
    from ppmrecon.model.guard import (correlated_lowpass_variance, gaussian_lowpass, lowpass_variance,
                                      noise_correlation)

    gen = torch.Generator().manual_seed(5)
    white = torch.randn(1, 3, 160, 160, generator=gen, dtype=torch.float64)
    s0, sigma = 2.0, 1.5
    for noise, rho_true in ((white, 0.0), (gaussian_lowpass(white, s0), math.exp(-1 / (4 * s0 * s0)))):
        inner = noise[..., 20:-20, 20:-20]                         # away from the replicate border
        v = torch.full((1, 1, 160, 160), float(inner.var()), dtype=torch.float64)
        rho = noise_correlation(noise, v, 8.0)[..., 20:-20, 20:-20]
        assert abs(float(rho.mean()) - rho_true) < 0.05
        measured = float(gaussian_lowpass(noise, sigma)[..., 20:-20, 20:-20].var())
        predicted = float(correlated_lowpass_variance(v, noise_correlation(noise, v, 8.0), sigma)[..., 20:-20, 20:-20].mean())
        assert predicted == pytest.approx(measured, rel=0.2)
        if rho_true:
            assert float(lowpass_variance(v, sigma).mean()) < 0.3 * measured
    # no variance: no noise to correlate; a flat image with variance: fully correlated (clamped)
    flat = torch.ones(1, 3, 8, 8)
    assert float(noise_correlation(flat, torch.zeros(1, 1, 8, 8), 2.0).max()) == 0.0
    assert float(noise_correlation(flat, torch.ones(1, 1, 8, 8), 2.0).min()) == pytest.approx(0.999)
    rho0 = torch.zeros(1, 1, 8, 8)
    v = torch.rand(1, 1, 8, 8, generator=gen)
    assert torch.equal(correlated_lowpass_variance(v, rho0, sigma), lowpass_variance(v, sigma))


def test_the_anchor_trusts_a_single_photons_plateau_less_with_the_correlation():
    """issue 12, ``texture_leaks``: one photon paints a plateau over every pixel within its
    radius, so the anchor's noise is correlated and its low-pass keeps all of it; with the
    correlation window the anchor moves the image less towards such a plateau."""
    from ppmrecon.model.guard import anchor_where_biased

    h = w = 32
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    plateau = (((yy - 16) ** 2 + (xx - 16) ** 2) <= 36).float()      # a disk of radius 6 px
    anchor = (1e-4 + 1e-2 * plateau).expand(1, 3, h, w).contiguous()
    var = (1e-4 * plateau + 1e-10)[None, None]                       # the variance of one photon's estimate
    image = torch.full((1, 3, h, w), 1e-4)
    plain = anchor_where_biased(image, anchor, var, 1.5, 1.0)
    shared = anchor_where_biased(image, anchor, var, 1.5, 1.0, window=3.0)
    centre = (slice(None), slice(None), slice(13, 20), slice(13, 20))
    assert float(shared[centre].mean()) < 0.8 * float(plain[centre].mean())
    assert bool((shared >= image - 1e-12).all())


def test_the_settled_anchor_ignores_one_photon_plateaus_and_still_corrects_a_settled_bias():
    """issue 12: a wide kernel's single photon paints a plateau (relative error ~1, shared by
    its neighbours) into the anchor; the plain anchor's noise test lets much of that gap
    through, the settled anchor (its low-pass's standard deviation, with the neighbour
    correlation, below r0 times its level) does not act there. A smooth bias against a
    settled anchor is corrected either way. Where the pixels look independent (no window)
    the plateau's low-pass looks settled too: the rule needs the correlation."""
    from ppmrecon.model.guard import anchor_where_biased, settled_mask

    image = torch.ones(1, 3, 40, 40)
    anchor = torch.ones(1, 3, 40, 40)
    var = torch.full((1, 1, 40, 40), 1e-6)
    anchor[..., 5:10, 5:10] = 50.0                              # one photon event: sqrt(V) = mean
    var[..., 5:10, 5:10] = 2500.0
    anchor[..., 22:38, 22:38] = 1.2                             # a settled 20% gap
    plain = anchor_where_biased(image, anchor, var, 1.5, 1.0, 3.0)
    kept = anchor_where_biased(image, anchor, var, 1.5, 1.0, 3.0, settled=0.5)
    assert float(plain[..., 7, 7].mean()) > 20.0                # the plateau leaks into the image
    torch.testing.assert_close(kept[..., 7, 7], image[..., 7, 7])
    for out in (plain, kept):
        torch.testing.assert_close(out[..., 30, 30], torch.full((1, 3), 1.2), rtol=1e-3, atol=0)
    torch.testing.assert_close(anchor_where_biased(image, anchor, var, 1.5, 1.0, 0.0, settled=0.5),
                               anchor_where_biased(image, anchor, var, 1.5, 1.0, 0.0))
    assert settled_mask(torch.zeros(1), torch.zeros(1), 0.5).item() is False   # 0 / 0: no photon, not settled


def test_anchor_where_biased_acts_only_beyond_the_anchors_noise():
    """a -> 1 (the plain anchor) where the anchor's low-pass is exact, a -> 0 where its
    variance dwarfs the gap; lowpass_variance of a constant V is V (sum g^2)^2."""
    from ppmrecon.model.guard import anchor_low_frequencies, anchor_where_biased, lowpass_variance

    gen = torch.Generator().manual_seed(0)
    image = torch.rand(1, 3, 20, 20, generator=gen)
    anchor = image + 0.3 * torch.rand(1, 3, 20, 20, generator=gen)
    plain = anchor_low_frequencies(image, anchor, 1.5)
    exact = anchor_where_biased(image, anchor, torch.zeros(1, 1, 20, 20), 1.5, 1.0)
    np.testing.assert_allclose(exact.numpy(), plain.numpy(), rtol=1e-5, atol=1e-6)
    noisy = anchor_where_biased(image, anchor, torch.full((1, 1, 20, 20), 1e6), 1.5, 1.0)
    np.testing.assert_allclose(noisy.numpy(), image.numpy(), atol=1e-5)
    assert torch.equal(anchor_where_biased(image, image, torch.ones(1, 1, 20, 20), 1.5, 1.0), image)
    v = lowpass_variance(torch.full((1, 1, 16, 16), 2.0), 1.5)
    assert v.shape == (1, 1, 16, 16)
    # inside (beyond the radius of 5 px from every edge): the 1-D taps squared and summed,
    # squared again for the two axes
    t = torch.exp(-0.5 * (torch.arange(-5, 6, dtype=torch.float32) / 1.5) ** 2)
    t = t / t.sum()
    np.testing.assert_allclose(v[..., 5:11, 5:11].numpy(), 2.0 * float(t.square().sum()) ** 2, rtol=1e-5)


@pytest.mark.parametrize("shape", [(9, 11), (1, 7), (6, 1), (1, 1), (2, 3), (3, 25)])
@pytest.mark.parametrize("sigma", [0.8, 1.5, 3.0])
def test_lowpass_variance_is_exact_at_the_edges(shape, sigma):
    """lowpass_variance is Var(G_sigma * X) for independent pixels, edges and corners
    included: sum_m a_{c,m}^2 V_m with a the replicate-padded blur's weight on pixel m (built
    here tap by tap), on images narrower than the blur too. The old form (sum_k g_k^2 V_{c-k})
    is 2.4x too low at an edge and 6x at a corner for sigma 1.5."""
    from ppmrecon.model.guard import _gaussian_taps, _separable, lowpass_variance

    h, w = shape
    var = torch.rand(2, 3, h, w, generator=torch.Generator().manual_seed(h * 31 + w), dtype=torch.float64)
    taps = _gaussian_taps(sigma, var)
    r = len(taps) // 2

    def weights(n: int) -> torch.Tensor:
        a = torch.zeros(n, n, dtype=torch.float64)
        for c in range(n):
            for k in range(-r, r + 1):
                a[c, min(max(c + k, 0), n - 1)] += taps[k + r]
        return a

    expected = torch.einsum("rm,cn,bkmn->bkrc", weights(h).square(), weights(w).square(), var)
    torch.testing.assert_close(lowpass_variance(var, sigma), expected, rtol=1e-10, atol=1e-12)
    if shape == (9, 11) and sigma == 1.5:
        flat = torch.ones(1, 1, 20, 20)
        old = _separable(flat, _gaussian_taps(1.5, flat).square())      # sum_k g_k^2 V_{c-k}
        ratio = lowpass_variance(flat, 1.5) / old
        assert 5.5 < float(ratio[0, 0, 0, 0]) < 6.5 and 2.2 < float(ratio[0, 0, 10, 0]) < 2.7
        assert float(ratio[0, 0, 10, 10]) == pytest.approx(1.0)


def test_cli_guide_mode(tmp_path):
    """--guide-mode picks the mode (the header says which); --weights-layers has no
    weights to write in envelope mode: one clear error, exit 2; the API takes guide_mode."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=13)
    B.write_buffers(tmp_path / "in.exr", buf)
    C.init_checkpoint(tmp_path / "m.pt", "tiny", FeatureConfig())
    args = [str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q"]
    assert denoise_main(args + ["--guide-mode", "envelope", "-o", str(tmp_path / "env.exr")]) == 0
    env, header = B.read_rgb(tmp_path / "env.exr")
    assert header["ppmrecon.guide"] == "oidn(z4, fast) envelope anchor=z3 k=1 cross=2 y=0"
    np.testing.assert_array_equal(ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope"), env)
    assert denoise_main(args + ["--guide-mode", "envelope", "--weights-layers", "-o", str(tmp_path / "x.exr")]) == 2
    assert not (tmp_path / "x.exr").exists()
    assert denoise_main(args + ["--guide-mode", "weights", "--weights-layers", "-o", str(tmp_path / "w.exr")]) == 0
    assert denoise_main(args + ["--guide", "off", "--guide-mode", "envelope"]) == 2
    with pytest.raises(ValueError, match="mode"):
        GuideConfig(enabled=True, mode="blend")


def _envelope_cli(tmp_path, buf) -> list[str]:
    """``ppmrecon-denoise`` arguments for ``buf`` written to tmp_path/in.exr, an untrained
    tiny model tmp_path/m.pt, quiet, envelope mode."""
    B.write_buffers(tmp_path / "in.exr", buf)
    C.init_checkpoint(tmp_path / "m.pt", "tiny", FeatureConfig())
    return [str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q", "--guide-mode", "envelope"]


def _cli_and_api_agree(tmp_path, buf, args: list[str], flag: str, value: str, header_end: str, **api) -> np.ndarray:
    """``ppmrecon-denoise ARGS FLAG VALUE`` writes what ``ppmrecon.denoise(buf, ..., **api)``
    returns, and its guide header ends with ``header_end``; the image."""
    import ppmrecon

    assert denoise_main(args + [flag, value, "-o", str(tmp_path / "cli.exr")]) == 0
    image, header = B.read_rgb(tmp_path / "cli.exr")
    assert header["ppmrecon.guide"].endswith(header_end)
    np.testing.assert_array_equal(ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope", **api), image)
    return image


def _refuses_negative_and_nan(tmp_path, capsys, buf, args: list[str], flag: str) -> None:
    """``FLAG -1`` and ``FLAG nan`` on the command line, and -0.5 through ``ppmrecon.denoise``'s
    keyword of the same name: one line naming the option, exit 2, no output."""
    import ppmrecon

    for bad in ("-1", "nan"):
        assert denoise_main(args + [flag, bad, "-o", str(tmp_path / "x.exr")]) == 2
        assert flag in capsys.readouterr().err
    assert not (tmp_path / "x.exr").exists()
    keyword = flag[2:].replace("-", "_")
    with pytest.raises(UsageError, match=keyword):
        ppmrecon.denoise(buf, tmp_path / "m.pt", **{keyword: -0.5})


def _switch_agrees_and_refuses(tmp_path, capsys, buf, args: list[str], flag: str, on: str, on_header: str,
                               off_header: str = "y=0", **fixed) -> tuple[np.ndarray, np.ndarray]:
    """A guide setting's flag at ``on`` and at 0: CLI and API agree each time (its keyword
    ``flag`` read as snake case, with ``fixed`` keywords too), the two images differ, and
    negative or not-a-number values are refused (:func:`_refuses_negative_and_nan`); the two
    images."""
    keyword = flag[2:].replace("-", "_")
    image_on = _cli_and_api_agree(tmp_path, buf, args, flag, on, on_header, **fixed, **{keyword: float(on)})
    image_off = _cli_and_api_agree(tmp_path, buf, args, flag, "0", off_header, **fixed, **{keyword: 0.0})
    assert not np.array_equal(image_on, image_off)
    _refuses_negative_and_nan(tmp_path, capsys, buf, args, flag)
    return image_on, image_off


def test_cli_and_api_guide_y_weight(tmp_path, capsys):
    """--guide-y-weight / guide_y_weight= set the weight of OIDN's image of ~y in the guide
    (the header says it); negative or not a number, or with the guide off: one clear line, exit 2."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=14)
    args = _envelope_cli(tmp_path, buf)
    mixed = _cli_and_api_agree(tmp_path, buf, args, "--guide-y-weight", "2", "y=2", guide_y_weight=2.0)
    plain = ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope", guide_y_weight=0.0)
    assert not np.array_equal(plain, mixed)
    for bad in ("-0.5", "nan", "inf"):
        assert denoise_main(args + ["--guide-y-weight", bad, "-o", str(tmp_path / "x.exr")]) == 2
        assert "--guide-y-weight" in capsys.readouterr().err
    assert denoise_main(args[:-2] + ["--guide", "off", "--guide-y-weight", "2"]) == 2
    assert not (tmp_path / "x.exr").exists()
    with pytest.raises(UsageError, match="guide_y_weight"):
        ppmrecon.denoise(buf, tmp_path / "m.pt", guide_y_weight=-1.0)


def test_cli_and_api_guide_y_spike(tmp_path, capsys):
    """--guide-y-spike / guide_y_spike= set the envelope's lone-~y-spike factor (the header
    says it); 1, negative or not a number: one clear line, exit 2, no output."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=15)
    est = buf.estimates.copy()
    est[0, 12:14, 12:14] = 1e4
    buf = replace(buf, estimates=est, header=dict(buf.header, **{B.H_PASSES: 1 << 20}))
    B.write_buffers(tmp_path / "in.exr", buf)
    C.init_checkpoint(tmp_path / "m.pt", "tiny", FeatureConfig())
    args = [str(tmp_path / "in.exr"), "--model", str(tmp_path / "m.pt"), "-q", "--guide-mode", "envelope",
            "--guide-y-weight", "2"]
    assert denoise_main(args + ["--guide-y-spike", "16", "-o", str(tmp_path / "s.exr")]) == 0
    held, header = B.read_rgb(tmp_path / "s.exr")
    assert header["ppmrecon.guide"].endswith("y=2 spike=16")
    np.testing.assert_array_equal(ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope",
                                                   guide_y_weight=2.0, guide_y_spike=16.0), held)
    plain = ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope", guide_y_weight=2.0, guide_y_spike=0.0)
    assert float(plain[12:14, 12:14].mean()) > 10 * float(held[12:14, 12:14].mean())
    for bad in ("1", "-3", "nan"):
        assert denoise_main(args + ["--guide-y-spike", bad, "-o", str(tmp_path / "x.exr")]) == 2
        assert "--guide-y-spike" in capsys.readouterr().err
    assert not (tmp_path / "x.exr").exists()
    with pytest.raises(UsageError, match="guide_y_spike"):
        ppmrecon.denoise(buf, tmp_path / "m.pt", guide_y_spike=0.5)


def test_cli_and_api_guide_anchor_settled(tmp_path, capsys):
    """--guide-anchor-settled / guide_anchor_settled= switch the settled anchor on (the header
    says it; CLI and API agree); negative or not a number: one clear line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=16)
    args = _envelope_cli(tmp_path, buf)
    _cli_and_api_agree(tmp_path, buf, args, "--guide-anchor-settled", "0.5", " settled=0.5", guide_anchor_settled=0.5)
    assert denoise_main(args + ["-o", str(tmp_path / "p.exr")]) == 0
    assert "settled" not in B.read_rgb(tmp_path / "p.exr")[1]["ppmrecon.guide"]
    _refuses_negative_and_nan(tmp_path, capsys, buf, args, "--guide-anchor-settled")


def test_cli_and_api_guide_anchor_select(tmp_path, capsys):
    """--guide-anchor-select / guide_anchor_select= aim the anchor between ~z^3 and ~z^4 (the
    header says it; CLI and API agree; 0 turns it off); negative or not a number: one clear
    line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=17)
    args = _envelope_cli(tmp_path, buf)
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-anchor-select", "4", " select=4")


def test_cli_and_api_guide_terms_passes(tmp_path, capsys):
    """--guide-terms-passes / guide_terms_passes= widen the envelope's range towards Eq. 6's
    terms (the header says it; CLI and API agree; 0 turns it off); negative or not a number:
    one clear line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=18)
    buf = replace(buf, header=dict(buf.header, **{B.H_PASSES: 4}))
    args = _envelope_cli(tmp_path, buf)
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-terms-passes", "16", " terms=16")


def test_cli_and_api_guide_anchor_spikes(tmp_path, capsys):
    """--guide-anchor-spikes / guide_anchor_spikes= (the header says it; CLI and API agree; 0
    turns it off); 1, negative or not a number: one clear line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=19)
    est = buf.estimates.copy()
    est[0, 12, 12], est[1:, 12, 12] = 5e2, 2e3               # a small light seen from both hit points
    buf = replace(buf, estimates=est)
    args = _envelope_cli(tmp_path, buf)
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-anchor-spikes", "8", " spikes=8")
    assert denoise_main(args + ["--guide-anchor-spikes", "1", "-o", str(tmp_path / "x.exr")]) == 2
    assert "--guide-anchor-spikes" in capsys.readouterr().err


@pytest.mark.parametrize("name, header", [("y_found", "found"), ("y_empty", "empty")])
def test_cli_and_api_guide_y_found_and_y_empty(tmp_path, capsys, name, header):
    """--guide-y-found / guide_y_found= and --guide-y-empty / guide_y_empty= (the header says
    it; CLI and API agree; 0 turns it off); negative or not a number: one clear line, exit 2,
    no output."""
    flag = "--guide-" + name.replace("_", "-")
    buf = make_buffer(24, 24, seed=23)
    est, var = buf.estimates.copy(), buf.variances.copy()
    est[0, :, :12], var[0, :, :12] = 0.0, 0.0                # ~y caught no photon on the left
    buf = replace(buf, estimates=est, variances=var)
    args = _envelope_cli(tmp_path, buf) + ["--guide-y-weight", "2"]
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, flag, "4", f" {header}=4", "y=2", guide_y_weight=2.0)


def test_cli_and_api_guide_z_spike(tmp_path, capsys):
    """--guide-z-spike / guide_z_spike= (the header says it; CLI and API agree; 0 turns it
    off); 1, negative or not a number: one clear line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=24)
    est, var = buf.estimates.copy(), buf.variances.copy()
    est[1:, 12, 12], var[1:, 12, 12] = 3e3, 9e6            # one event at hit point B
    buf = replace(buf, estimates=est, variances=var, header=dict(buf.header, **{B.H_PASSES: 1 << 20}))
    args = _envelope_cli(tmp_path, buf)
    held, _ = _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-z-spike", "8", " zspike=8")
    np.testing.assert_allclose(held[12, 12], est[0, 12, 12], rtol=1e-6)
    assert denoise_main(args + ["--guide-z-spike", "1", "-o", str(tmp_path / "x.exr")]) == 2
    assert "--guide-z-spike" in capsys.readouterr().err


def test_cli_and_api_guide_anchor_free(tmp_path, capsys):
    """--guide-anchor-free / guide_anchor_free= (the header says it; CLI and API agree; 0 turns
    it off); negative or not a number: one clear line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=25)
    est, var = buf.estimates.copy(), buf.variances.copy()
    rng = np.random.default_rng(25)
    speck = rng.random((24, 12)) < 0.1
    est[:, :, :12] = (speck * 10.0)[None, :, :, None]        # a speckle field on the left
    var[:, :, :12] = (speck * 100.0)[None]
    buf = replace(buf, estimates=est, variances=var)
    args = _envelope_cli(tmp_path, buf)
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-anchor-free", "0.5", " free=0.5")


def test_cli_and_api_guide_redistribute(tmp_path, capsys):
    """--guide-redistribute / guide_redistribute= (the header says it; CLI and API agree; 0
    turns it off; on a speckle field it gives back what the clamp took, so the image is no
    darker); negative or not a number: one clear line, exit 2, no output."""
    buf = make_buffer(24, 24, seed=26)
    est, var = buf.estimates.copy(), buf.variances.copy()
    rng = np.random.default_rng(26)
    speck = rng.random((5, 24, 24)) < 0.3
    est[:] = (speck * 10.0)[..., None]                       # a speckle field: many pixels' estimates all 0
    var[:] = speck * 100.0
    buf = replace(buf, estimates=est, variances=var)
    args = _envelope_cli(tmp_path, buf)
    given, plain = _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-redistribute", "1.5", " redis=1.5")
    assert given.mean() >= plain.mean()
    assert (given <= est.max(0) + 1e-6).all() and (given >= 0).all()


def test_cli_and_api_guide_cascade(tmp_path, capsys):
    """--guide-cascade / guide_cascade= (the header says it; CLI and API agree; 0 turns it
    off); negative or not a number: one clear line, exit 2, no output."""
    buf = _biased_buffer(27)
    args = _envelope_cli(tmp_path, buf)
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-cascade", "4", " cascade=4")


def test_cli_and_api_guide_cascade_y(tmp_path, capsys):
    """--guide-cascade-y / guide_cascade_y= (the header says it after the cascade's; CLI and
    API agree; 0 turns it off; without the cascade it is inert); negative or not a number:
    one clear line, exit 2, no output."""
    buf = _biased_buffer(29)
    est = buf.estimates.copy()
    est[0] = 0.5                      # ~y below ~z^1 and ~z^2 (1), which lie below ~z^3 / ~z^4 (3) on the right
    buf = replace(buf, estimates=est)
    args = _envelope_cli(tmp_path, buf) + ["--guide-cascade", "4"]
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-cascade-y", "4", " cascade=4 ystep=4",
                               " cascade=4", guide_cascade=4.0)
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, anchor_window=3.0, cascade=0.0, cascade_y=4.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    np.testing.assert_array_equal(denoise(buf, model).rgb, denoise(buf, model, guide=replace(on, cascade_y=0.0)).rgb)


def test_cascade_y_up_gates_the_step_up_by_passes(tmp_path, capsys):
    """GuideConfig.cascade_y_up M: a render of fewer than M passes takes the step to ~y down
    only (a trend up leaves the output as with the step off), one of M or more as with M = 0;
    --guide-cascade-y-up / guide_cascade_y_up= agree and the header says it (``up=M``);
    negative or not a number: one clear line, exit 2, no output; the setting is checked."""
    buf = _biased_buffer(35)
    est = 4.0 - buf.estimates                           # a trend up: ~y 3.5 over ~z^1, ~z^2 3 over ~z^3, ~z^4 1
    est[0] = 3.5
    buf = replace(buf, estimates=est, header=dict(buf.header, **{B.H_PASSES: 32}))
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, anchor_window=3.0, cascade=4.0, cascade_y=4.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    both, off = denoise(buf, model).rgb, denoise(buf, model, guide=replace(on, cascade_y=0.0)).rgb
    assert not np.array_equal(both, off)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, cascade_y_up=64.0)).rgb, off)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, cascade_y_up=32.0)).rgb, both)
    args = _envelope_cli(tmp_path, buf) + ["--guide-cascade", "4", "--guide-cascade-y", "4"]
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-cascade-y-up", "64",
                               " cascade=4 ystep=4 up=64", " cascade=4 ystep=4",
                               guide_cascade=4.0, guide_cascade_y=4.0)
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match="cascade_y_up"):
            replace(on, cascade_y_up=bad)


def test_nlm_image_keeps_detail_above_the_noise_and_averages_noise():
    """nlm_image: an image with variance 0 comes back unchanged; on a flat field of known
    variance the noise falls several-fold, the mean stays; a step of 10 noise deviations
    stays sharp (no pixel takes more than a few percent of the other side)."""
    from ppmrecon.model.guide import nlm_image

    gen = torch.Generator().manual_seed(3)
    clean = torch.rand(3, 24, 24, generator=gen)
    torch.testing.assert_close(nlm_image(clean, torch.zeros(24, 24)), clean, rtol=0, atol=1e-6)
    sd = 0.1
    flat = 1.0 + sd * torch.randn(3, 32, 32, generator=gen)
    out = nlm_image(flat, torch.full((32, 32), sd * sd))
    assert float(out.std()) < float(flat.std()) / 3
    assert abs(float(out.mean()) - 1.0) < 0.02
    step = torch.where(torch.arange(32) < 16, 1.0, 2.0).expand(3, 32, 32) + 0.01 * torch.randn(3, 32, 32, generator=gen)
    kept = nlm_image(step, torch.full((32, 32), 1e-4))
    assert float(kept[..., :15].max()) < 1.05 and float(kept[..., 17:].min()) > 1.95


def test_cli_and_api_guide_denoiser(tmp_path, capsys):
    """--guide-denoiser nlm / nlm_source (and --guide-nlm-k, --guide-nlm-radius) agree with
    ppmrecon.denoise(guide_denoiser=...), the header names the denoiser, the images differ from
    OIDN's; an unknown denoiser, a radius that is not a whole number or k <= 0: one clear line,
    exit 2, no output."""
    import ppmrecon

    buf = make_buffer(24, 24, seed=37)
    args = _envelope_cli(tmp_path, buf)
    oidn = ppmrecon.denoise(buf, tmp_path / "m.pt", guide_mode="envelope")
    for name in ("nlm", "nlm_source"):
        image = _cli_and_api_agree(tmp_path, buf, args + ["--guide-nlm-radius", "3"], "--guide-denoiser", name,
                                   "", guide_denoiser=name,
                                   guide_nlm_radius=3)
        assert not np.array_equal(image, oidn)
        _, header = B.read_rgb(tmp_path / "cli.exr")
        assert header["ppmrecon.guide"].startswith("nlm k=0.45 r=3(z4")
    with pytest.raises(SystemExit) as stop:                      # argparse's own choice check
        denoise_main(args + ["--guide-denoiser", "bm3d", "-o", str(tmp_path / "x.exr")])
    assert stop.value.code == 2 and "--guide-denoiser" in capsys.readouterr().err
    for bad in (["--guide-denoiser", "nlm", "--guide-nlm-radius", "2.5"],
                ["--guide-denoiser", "nlm", "--guide-nlm-radius", "16"],
                ["--guide-denoiser", "nlm", "--guide-nlm-k", "0"]):
        assert denoise_main(args + bad + ["-o", str(tmp_path / "x.exr")]) == 2
        assert bad[-2] in capsys.readouterr().err
    assert not (tmp_path / "x.exr").exists()
    with pytest.raises(UsageError, match="guide_denoiser"):
        ppmrecon.denoise(buf, tmp_path / "m.pt", guide_denoiser="bm3d")


def test_cascade_passes_leaves_few_pass_renders_without_the_cascade(tmp_path, capsys):
    """GuideConfig.cascade_passes M: a render of fewer than M passes is denoised exactly as
    with the cascade off (no aim is made), one of M or more exactly as with it at every N; the
    setting is checked; --guide-cascade-passes / guide_cascade_passes= agree and the header
    says it (``from=M``); negative or not a number: one clear line, exit 2."""
    from ppmrecon.model.infer import buffer_aim

    buf = _biased_buffer(33)
    assert buf.header[B.H_PASSES] == 16
    on = replace(ENVELOPE, anchor_source=3, anchor_select=4.0, anchor_window=3.0, cascade=4.0)
    model = build("tiny", FeatureConfig(scale_free=True, outliers=True), DEFAULT_ON, on)
    always, never = denoise(buf, model).rgb, denoise(buf, model, guide=replace(on, cascade=0.0)).rgb
    assert not np.array_equal(always, never)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, cascade_passes=16.0)).rgb, always)
    np.testing.assert_array_equal(denoise(buf, model, guide=replace(on, cascade_passes=17.0)).rgb, never)
    assert buffer_aim(buf, replace(on, cascade_passes=17.0), DEFAULT_ON) is None
    assert buffer_aim(buf, replace(on, cascade_passes=16.0), DEFAULT_ON) is not None
    for bad in (-1.0, float("nan"), True):
        with pytest.raises(ValueError, match="cascade_passes"):
            replace(on, cascade_passes=bad)
    args = _envelope_cli(tmp_path, buf) + ["--guide-cascade", "4"]
    _switch_agrees_and_refuses(tmp_path, capsys, buf, args, "--guide-cascade-passes", "32", " cascade=4 from=32",
                               " cascade=4", guide_cascade=4.0)


def test_training_refuses_the_envelope_mode(tmp_path):
    """The envelope runs no network: a training config asking for it is one clear error
    (before any data is read)."""
    from ppmrecon.errors import UsageError
    from ppmrecon.train.loop import TrainConfig, train

    with pytest.raises(UsageError, match="envelope"):
        train(tmp_path / "no_data", tmp_path / "run", TrainConfig(guide={"enabled": True, "mode": "envelope"}),
              quiet=True)
