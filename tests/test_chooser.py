"""The chooser (ppmrecon/model/chooser.py): every candidate and every output held in the
five estimates' range (consistency), an untrained chooser is its prior, scale-free
features, checkpoints that carry it, and the denoise path that runs it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch

from conftest import make_buffer
from ppmrecon import buffers as B
from ppmrecon.errors import UsageError
from ppmrecon.model import checkpoint as C
from ppmrecon.model import cli as denoise_cli
from ppmrecon.model.chooser import (CANDIDATES, FEATURE_NORMAL_X, N_FEATURES, Chooser, ChooserConfig, band,
                                    candidates, features)
from ppmrecon.model.features import FeatureConfig
from ppmrecon.model.guard import DEFAULT_ON, guard_buffer
from ppmrecon.model.guide import DEFAULT_GUIDE
from ppmrecon.model.infer import buffer_envelope, buffer_guide_images, chooser_inputs, denoise
from ppmrecon.model.kpn import build


def _images(h: int = 12, w: int = 10, seed: int = 0):
    """Five estimates (5, H, W, 3) and four other images (H, W, 3), some outside their band."""
    g = torch.Generator().manual_seed(seed)
    est = torch.rand(5, h, w, 3, generator=g) * 3
    others = [torch.rand(h, w, 3, generator=g) * 6 - 1 for _ in range(4)]
    return est, others


def _random_chooser(seed: int = 1, cfg: ChooserConfig = ChooserConfig(width=4, layers=2)) -> Chooser:
    torch.manual_seed(seed)
    net = Chooser(cfg)
    torch.nn.init.normal_(net.head.weight, std=2.0)       # far from the prior
    return net.eval()


def _nchw(feats: torch.Tensor, cands: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The chooser's batch views of pixel-major features (H, W, C) and candidates (H, W, K, 3)."""
    return feats.permute(2, 0, 1)[None], cands.permute(2, 3, 0, 1)[None]


def test_candidates_and_any_mix_of_them_stay_in_the_band():
    est, (env, g, gz, gy) = _images()
    y, z = est[0], est[1:]
    lo, hi = band(y, z)
    cands = candidates(env, g, gz, gy, z, lo, hi)
    assert cands.shape == (12, 10, len(CANDIDATES), 3)
    assert torch.all(cands >= lo[:, :, None]) and torch.all(cands <= hi[:, :, None])
    torch.testing.assert_close(cands[:, :, 4:], z.permute(1, 2, 0, 3))     # ~z^j are their own candidates
    feats = features(cands, y, lo, hi, torch.rand(5, 12, 10), torch.rand(12, 10, 3), torch.rand(12, 10, 3), 1.0, 16)
    assert feats.shape == (12, 10, N_FEATURES)
    out = _random_chooser().predict(*_nchw(feats, cands))[0].permute(1, 2, 0)
    assert torch.all(out >= lo - 1e-5) and torch.all(out <= hi + 1e-5)
    with torch.no_grad():
        w = _random_chooser().weights(_nchw(feats, cands)[0])
    assert float(w.amax(1).min()) < 0.9                             # a real mix, not the prior alone


def test_untrained_chooser_is_its_prior():
    est, (env, g, gz, gy) = _images(seed=2)
    cands = candidates(env, g, gz, gy, est[1:], *band(est[0], est[1:]))
    feats = torch.randn(12, 10, N_FEATURES)
    net = Chooser(ChooserConfig(width=4, layers=1, prior=3.0))
    w = torch.softmax(torch.tensor([3.0] + [0.0] * (len(CANDIDATES) - 1)), 0)
    expected = (w.view(1, 1, -1, 1) * cands).sum(2).permute(2, 0, 1)
    torch.testing.assert_close(net.predict(*_nchw(feats, cands))[0], expected)
    with torch.no_grad():
        torch.testing.assert_close(net(*_nchw(feats, cands))[0], expected)


def test_features_do_not_change_when_all_radiance_is_scaled():
    est, (env, g, gz, gy) = _images(seed=3)
    var, albedo, normal = torch.rand(5, 12, 10) * 1e-2, torch.rand(12, 10, 3), torch.rand(12, 10, 3)
    def feats(k: float) -> torch.Tensor:
        lo, hi = band(est[0] * k, est[1:] * k)
        cands = candidates(env * k, g * k, gz * k, gy * k, est[1:] * k, lo, hi)
        return features(cands, est[0] * k, lo, hi, var * k * k, albedo, normal, 2.0 * k, 64)

    a, b = feats(1.0), feats(1e3)
    torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(a[..., FEATURE_NORMAL_X:FEATURE_NORMAL_X + 3], normal)


def test_config_rejects_nonsense():
    for bad in ({"width": 0}, {"layers": 1.5}, {"prior": float("nan")}, {"width": True}):
        with pytest.raises(ValueError):
            ChooserConfig(**bad)
    with pytest.raises(ValueError, match="unknown chooser setting"):
        ChooserConfig.from_dict({"depth": 3})


def _chooser_model(seed: int = 1):
    model = build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON, replace(DEFAULT_GUIDE, mode="chooser"))
    model.chooser = _random_chooser(seed)
    return model


def test_checkpoint_carries_the_chooser(tmp_path):
    model = _chooser_model()
    C.save_checkpoint(tmp_path / "m.pt", model, {"x": 1})
    back = C.load_checkpoint(tmp_path / "m.pt").model
    assert back.chooser is not None and back.chooser.cfg == model.chooser.cfg and back.guide.mode == "chooser"
    for k, v in model.chooser.state_dict().items():
        assert torch.equal(v, back.chooser.state_dict()[k])
    # mode "chooser" without chooser weights is refused on load, naming the file
    plain = build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON, replace(DEFAULT_GUIDE, mode="chooser"))
    C.save_checkpoint(tmp_path / "bad.pt", plain)
    with pytest.raises(UsageError, match=r"bad\.pt: guide mode 'chooser' but the checkpoint has no chooser"):
        C.load_checkpoint(tmp_path / "bad.pt")


def test_denoise_runs_the_chooser_on_the_envelope():
    buf = make_buffer(16, 20, seed=4)
    model = _chooser_model(seed=5)
    out = denoise(buf, model).rgb
    guarded = guard_buffer(buf, model.guard)
    guide = model.guide.in_mode("envelope")
    images, planes = buffer_guide_images(guarded, guide, model.guard, need_y=True)
    env = buffer_envelope(guarded, planes, model.guard, guide).rgb
    feats, cands, _, _ = chooser_inputs(guarded, env, images)
    expected = model.chooser.predict(feats[None], cands[None])[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)
    est = torch.from_numpy(guarded.estimates)
    lo, hi = band(est[0], est[1:])
    assert np.all(out >= lo.numpy() - 1e-5) and np.all(out <= hi.numpy() + 1e-5)
    # the envelope mode of the same model is its first candidate
    np.testing.assert_allclose(denoise(buf, model, guide=guide).rgb, env, rtol=1e-6, atol=1e-7)


def _bands(buf, model):
    """The chooser's candidates and band ``(lo, hi)`` for ``buf`` as ``model`` runs it, and the
    five guarded estimates' plain range ``(lo, hi)``."""
    guarded = guard_buffer(buf, model.guard)
    guide = model.guide.in_mode("envelope")
    images, planes = buffer_guide_images(guarded, guide, model.guard, need_y=True)
    env = buffer_envelope(guarded, planes, model.guard, guide).rgb
    _, cands, lo, hi = chooser_inputs(guarded, env, images, guide=guide, guard=model.guard)
    full_lo, full_hi = band(torch.from_numpy(guarded.estimates[0]), torch.from_numpy(guarded.estimates[1:]))
    return cands, lo, hi, full_lo, full_hi


def test_the_chooser_band_leaves_out_a_lone_y_spike_as_the_envelope_does():
    """With the guide's ``y_spike`` on, every candidate and the output are held in the
    ~z^j's range at a lone ~y spike (issue 12, ``0036_bright_emitters``: 9-16x its best
    input in chooser mode before); elsewhere the band is the five estimates' range."""
    buf = make_buffer(16, 20, seed=6)
    est = buf.estimates.copy()
    est[0, 7:9, 9:11] = 3e4
    buf = replace(buf, estimates=est, header=dict(buf.header, **{B.H_PASSES: 1 << 20}))
    model = _chooser_model(seed=7)
    model.guide = replace(model.guide, y_weight=2.0, y_spike=8.0)
    out = denoise(buf, model).rgb
    z = est[1:, 7:9, 9:11]
    assert np.all(out[7:9, 9:11] <= z.max(0) + 1e-5) and np.all(out[7:9, 9:11] >= z.min(0) - 1e-5)
    cands, lo, hi, full_lo, full_hi = _bands(buf, model)
    assert float(cands[:, :, 7:9, 9:11].max()) <= float(z.max()) + 1e-5
    keep = np.ones((16, 20), bool)
    keep[7:9, 9:11] = False
    assert torch.equal(hi[keep], full_hi[keep]) and torch.equal(lo[keep], full_lo[keep])
    assert float(full_hi[7:9, 9:11].min()) == 3e4


def test_cli_chooser_mode_without_a_chooser_is_one_line(tmp_path, capsys):
    buf_path = tmp_path / "in.exr"
    B.write_buffers(buf_path, make_buffer(8, 8))
    ckpt = tmp_path / "env.pt"
    C.save_checkpoint(ckpt, build("tiny", FeatureConfig(scale_free=True), DEFAULT_ON,
                                  replace(DEFAULT_GUIDE, mode="envelope")))
    rc = denoise_cli.main([str(buf_path), "--model", str(ckpt), "--guide-mode", "chooser", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1 and "chooser" in err[0] and "--guide-mode envelope" in err[0]
    with_chooser = tmp_path / "ch.pt"
    C.save_checkpoint(with_chooser, _chooser_model())
    assert denoise_cli.main([str(buf_path), "--model", str(with_chooser), "-o", str(tmp_path / "o.exr"), "--quiet"]) == 0
    rgb, header = B.read_rgb(tmp_path / "o.exr")
    assert np.isfinite(rgb).all() and header["ppmrecon.guide"].split(" ")[2] == "chooser"


def test_the_chooser_band_holds_a_lone_z_spike_at_y_as_the_envelope_does():
    """With the guide's ``z_spike`` on, the band of a pixel whose four ~z^j are one photon
    event over a settled ~y is ~y itself (lo = hi = ~y), so every candidate and the output are
    ~y there; elsewhere the band is the five estimates' range."""
    buf = make_buffer(16, 20, seed=8)
    est, var = buf.estimates.copy(), buf.variances.copy()
    est[1:, 7, 9], var[1:, 7, 9] = 3e3, 9e6
    buf = replace(buf, estimates=est, variances=var, header=dict(buf.header, **{B.H_PASSES: 1 << 20}))
    model = _chooser_model(seed=9)
    model.guide = replace(model.guide, y_weight=2.0, z_spike=8.0)
    np.testing.assert_allclose(denoise(buf, model).rgb[7, 9], est[0, 7, 9], rtol=1e-5)
    _, lo, hi, full_lo, full_hi = _bands(buf, model)
    assert torch.equal(lo[7, 9], torch.from_numpy(est[0, 7, 9])) and torch.equal(hi[7, 9], lo[7, 9])
    keep = np.ones((16, 20), bool)
    keep[7, 9] = False
    assert torch.equal(hi[keep], full_hi[keep]) and torch.equal(lo[keep], full_lo[keep])
