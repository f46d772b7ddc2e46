"""Network, features, presets, checkpoints, tiled inference, and learning on a synthetic problem."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from ppmrecon import buffers as B
from ppmrecon.errors import UsageError
from ppmrecon.metrics import relmse
from ppmrecon.model import checkpoint as C
from ppmrecon.model.combine import combine
from ppmrecon.model.features import N_BASE_CHANNELS, FeatureConfig, build_features, from_buffer
from ppmrecon.model.infer import NonFiniteOutputError, denoise, denoise_inputs
from ppmrecon.model.kpn import KPN, PRESETS_DIR, Preset, build, load_preset, parameter_count
from ppmrecon.train.loss import relative_log_l1
from tests.conftest import make_buffer




# ------------------------------------------------------------------------- presets

def test_presets_are_package_data():
    names = {p.name for p in PRESETS_DIR.glob("*.json")}
    assert {"paper.json", "small.json", "tiny.json"} <= names
    assert PRESETS_DIR.parts[-3:] == ("ppmrecon", "data", "models")


def test_paper_preset_matches_the_paper():
    p = load_preset("paper")
    assert (p.layers, p.filters, p.kernel, p.window, p.final_kernel) == (10, 50, 5, 19, 5)
    n = parameter_count(build(p))
    assert 2.3e6 <= n <= 2.4e6          # "approximately 2.4M" (paper 002 Sec. 4.3)


@pytest.mark.parametrize("name,limit", [("small", 200_000), ("tiny", 30_000)])
def test_cpu_presets_are_small(name, limit):
    model = build(name)
    assert parameter_count(model) < limit
    assert model.head.out_channels == 4 * model.window ** 2


def test_load_preset_from_path_and_errors(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"name": "mine", "layers": 2, "filters": 4, "kernel": 3, "window": 3}))
    p = load_preset(str(path))
    assert p.final_kernel == 3 and p.receptive_radius == 2 and p.halo == 3
    with pytest.raises(UsageError, match="unknown model preset 'nope'.*tiny"):
        load_preset("nope")
    path.write_text(json.dumps({"name": "bad", "layers": 2, "filters": 4, "kernel": 4, "window": 3}))
    with pytest.raises(UsageError, match="kernel must be odd"):
        load_preset(str(path))
    path.write_text("{not json")
    with pytest.raises(UsageError, match="invalid model preset"):
        load_preset(str(path))


def test_receptive_radius_is_exact():
    """Perturbing one input pixel changes logits exactly within the stated radius."""
    torch.manual_seed(0)
    preset = Preset("probe", layers=3, filters=6, kernel=3, window=3, final_kernel=5)
    model = KPN(preset).double()
    x = torch.rand(1, N_BASE_CHANNELS, 21, 21, dtype=torch.float64)
    x2 = x.clone()
    x2[..., 10, 10] += 1.0
    with torch.no_grad():
        changed = (model(x2) - model(x)).abs().amax(1)[0] > 0
    rows, cols = torch.nonzero(changed, as_tuple=True)
    r = preset.receptive_radius
    assert r == 4
    assert int((rows - 10).abs().max()) == r and int((cols - 10).abs().max()) == r


def test_predict_matches_forward():
    torch.manual_seed(1)
    for name in ("tiny", "small"):
        model = build(name).eval()
        x = torch.rand(1, N_BASE_CHANNELS, 19, 23)
        with torch.no_grad():
            ref = model(x)
        torch.testing.assert_close(model.predict(x, "float32"), ref, rtol=1e-5, atol=1e-5)
        assert model.predict(x, "float32").is_contiguous()
        bf = model.predict(x, "bfloat16")
        assert bf.dtype == torch.float32 and bf.shape == ref.shape
        assert float((bf - ref).abs().max()) < 0.05 * float(ref.abs().max()) + 0.05


# ------------------------------------------------------------------------ features

def test_features_layout_and_ranges():
    buf = make_buffer(9, 11, seed=2)
    buf.estimates[0, 0, 0] = 1e8                     # a firefly
    buf.estimates[1:, 1, 1] = 0.0                    # black pixel
    buf.depth[:] = 0.0                               # e.g. all background
    inp = from_buffer(buf)
    assert inp.features.shape == (1, 27, 9, 11)
    assert torch.isfinite(inp.features).all()
    torch.testing.assert_close(inp.y[0].permute(1, 2, 0).numpy(), buf.estimates[0])   # raw radiance
    torch.testing.assert_close(inp.z[0, 3].permute(1, 2, 0).numpy(), buf.estimates[4])
    s = FeatureConfig().slices()
    assert float(inp.features[0, s["estimates"]].max()) == pytest.approx(np.log1p(1e8), rel=1e-6)
    assert float(inp.features[0, s["depth"]].abs().max()) == 0.0
    torch.testing.assert_close(inp.features[0, s["normal"]].permute(1, 2, 0).numpy(), buf.normal)


def test_depth_is_normalised_per_image_and_variance_is_delta_method():
    buf = make_buffer(4, 5, seed=3)
    feats = from_buffer(buf).features[0]
    s = FeatureConfig().slices()
    assert float(feats[s["depth"]].max()) == pytest.approx(1.0)
    mean = buf.estimates[2].mean(-1)
    expected = np.log1p(buf.variances[2] / (1 + mean) ** 2)
    np.testing.assert_allclose(feats[s["variances"]][2].numpy(), expected, rtol=1e-5)


def test_optional_feature_channels():
    buf = make_buffer(5, 6, seed=4)
    cfg = FeatureConfig(radius=True, passes=True)
    feats = from_buffer(buf, cfg).features
    assert feats.shape[1] == cfg.n_channels == 33
    s = cfg.slices()
    assert float(feats[0, s["radius"]].max()) <= 1.0 + 1e-6
    assert float(feats[0, s["passes"]].std()) == 0.0 and float(feats[0, s["passes"]].mean()) > 0
    del buf.header[B.H_PASSES]
    with pytest.raises(UsageError, match="pass count"):
        from_buffer(buf, FeatureConfig(passes=True))
    with pytest.raises(ValueError, match="unknown feature"):
        FeatureConfig.from_dict({"radius": True, "colour": 1})


# --------------------------------------------------------------------- checkpoints

def test_checkpoint_round_trip(tmp_path):
    path = tmp_path / "m.pt"
    model = C.init_checkpoint(path, "tiny", FeatureConfig(radius=True), seed=3)
    C.save_checkpoint(path, model, {"epochs": 7, "val_relmse": 0.125})
    loaded, meta = C.load_checkpoint(path)
    assert meta == {"epochs": 7, "val_relmse": 0.125}
    assert loaded.preset == model.preset and loaded.features == model.features
    x = torch.rand(1, loaded.features.n_channels, 8, 8)
    with torch.no_grad():
        torch.testing.assert_close(loaded(x), model(x), rtol=0, atol=0)


def _payload(path):
    return torch.load(path, weights_only=True)


@pytest.mark.parametrize("damage,message", [
    ("missing", "no such model checkpoint"),
    ("folder", "is a folder"),
    ("random", "not a PyTorch zip archive"),
    ("truncated", "corrupt or truncated"),
    ("pickle", "refusing to unpickle"),
    ("other", "not a ppmrecon model checkpoint"),
    ("newer", "newer than this ppmrecon"),
    ("schema", "buffer schema 99"),
    ("mismatch", "weights do not match"),
    ("nan", "NaN/Inf"),
    ("preset", "invalid architecture"),
])
def test_bad_checkpoints_give_one_clear_usage_error(tmp_path, damage, message):
    good = tmp_path / "good.pt"
    C.init_checkpoint(good, "tiny")
    path = tmp_path / "bad.pt"
    data = _payload(good)
    if damage == "missing":
        pass
    elif damage == "folder":
        path.mkdir()
    elif damage == "random":
        path.write_bytes(np.random.default_rng(0).bytes(300))
    elif damage == "truncated":
        path.write_bytes(good.read_bytes()[:2000])
    elif damage == "pickle":
        torch.save(torch.nn.Linear(2, 2), path)
    elif damage == "other":
        torch.save({"state_dict": data["state_dict"]}, path)
    else:
        if damage == "newer":
            data["format_version"] = C.FORMAT_VERSION + 1
        elif damage == "schema":
            data["schema_version"] = 99
        elif damage == "mismatch":
            data["preset"]["filters"] = 8
        elif damage == "nan":
            data["state_dict"]["head.bias"][0] = float("nan")
        elif damage == "preset":
            data["preset"]["window"] = 4
        torch.save(data, path)
    with pytest.raises(UsageError) as info:
        C.load_checkpoint(path)
    text = str(info.value)
    assert str(path) in text and message in text and "\n" not in text


# ------------------------------------------------------------------------ inference

@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_tiled_equals_untiled(precision):
    torch.manual_seed(5)
    model = KPN(Preset("t7", layers=3, filters=8, kernel=3, window=7, final_kernel=1)).eval()
    buf = make_buffer(45, 61, seed=6)
    buf.estimates[:, 20:25, 30:40] *= 1e4                  # a bright region crossing tile seams
    full = denoise(buf, model, tile=10_000, precision=precision)
    for tile in (13, 32):
        tiled = denoise(buf, model, tile=tile, precision=precision)
        scale = np.abs(full.rgb).max()
        np.testing.assert_allclose(tiled.rgb, full.rgb, rtol=1e-5, atol=1e-5 * scale)
        np.testing.assert_allclose(tiled.weights_per_z, full.weights_per_z, rtol=1e-5, atol=1e-6)


def test_denoise_reports_progress_and_is_consistent_with_combiner():
    model = build("tiny").eval()
    buf = make_buffer(20, 30, seed=7)
    calls = []
    out = denoise(buf, model, tile=8, progress=lambda d, t: calls.append((d, t)), precision="float32")
    assert calls[-1] == (12, 12) and len(calls) == 12
    inp = from_buffer(buf)
    with torch.no_grad():
        ref = combine(inp.y, inp.z, model(inp.features)).clamp(min=0)[0].permute(1, 2, 0).numpy()
    np.testing.assert_allclose(out.rgb, ref, rtol=1e-5, atol=1e-5 * np.abs(ref).max())
    np.testing.assert_allclose(out.weights_per_z.sum(0), 1.0, rtol=1e-5)


def test_output_is_clamped_at_zero_where_all_terms_are_negative():
    """~y = 0 and ~z^j brighter around the centre: every term y_i + z_c - z_i < 0 there."""
    buf = make_buffer(9, 9, seed=14)
    buf.estimates[0] = 0.0
    buf.estimates[1:] = 5.0
    buf.estimates[1:, 4, 4] = 0.0
    inp = from_buffer(buf)
    model = build("tiny").eval()
    with torch.no_grad():
        raw = combine(inp.y, inp.z, model(inp.features))
    assert float(raw[0, :, 4, 4].max()) < 0                       # Eq. 6 itself goes negative
    out = denoise(buf, model, precision="float32")
    assert out.rgb.min() >= 0 and np.all(out.rgb[4, 4] == 0)
    np.testing.assert_allclose(out.rgb, raw.clamp(min=0)[0].permute(1, 2, 0).numpy(), rtol=1e-5, atol=1e-6)


def test_worker_threads_give_the_same_image_and_restore_thread_count():
    model = build("tiny").eval()
    buf = make_buffer(40, 50, seed=12)
    one = denoise(buf, model, tile=16, workers=1)
    calls = []
    torch.set_num_threads(2)
    many = denoise(buf, model, tile=16, workers=3, progress=lambda d, t: calls.append((d, t)))
    assert torch.get_num_threads() == 2                  # ops ran single-threaded, then restored
    np.testing.assert_array_equal(many.rgb, one.rgb)
    np.testing.assert_array_equal(many.weights_per_z, one.weights_per_z)
    assert sorted(calls) == [(n, 12) for n in range(1, 13)]


def test_non_finite_network_output_is_refused():
    model = build("tiny").eval()
    with torch.no_grad():
        for p in model.parameters():
            p.fill_(1e30)                                   # logits overflow to inf / nan
    inp = from_buffer(make_buffer(20, 20, seed=8))
    for workers in (1, 2):
        with pytest.raises(NonFiniteOutputError, match="NaN/Inf"):
            denoise_inputs(inp, model, tile=8, workers=workers)


# -------------------------------------------------------- learning on a synthetic problem

SIGMAS = (0.8, 1.5, 2.5, 4.0)


def _blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    r = int(3 * sigma) + 1
    t = torch.arange(-r, r + 1, dtype=torch.float32)
    g = torch.exp(-t * t / (2 * sigma * sigma))
    g = g / g.sum()
    c = x.shape[1]
    x = F.pad(x, (r, r, r, r), mode="replicate")
    x = F.conv2d(x, g.view(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(x, g.view(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def _scenes(gen: torch.Generator, n: int, size: int) -> torch.Tensor:
    """Known images: coloured discs (radiance up to 4) on a lit gradient, (n, 3, size, size)."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, size), torch.linspace(0, 1, size), indexing="ij")
    out = []
    for _ in range(n):
        img = (0.2 + 0.8 * torch.rand(3, 1, 1, generator=gen)) * (0.3 + xx * torch.rand(1, generator=gen))
        for _ in range(4):
            cx, cy, rad = torch.rand(3, generator=gen)
            mask = ((xx - cx) ** 2 + (yy - cy) ** 2 < (0.1 + 0.25 * rad) ** 2).float()
            img = img * (1 - mask) + mask * 4 * torch.rand(3, 1, 1, generator=gen)
        out.append(img)
    return torch.stack(out)


def _noisy(gen: torch.Generator, clean: torch.Tensor):
    """~y = image x strong unbiased noise; ~z^j = increasingly blurred (image x weaker,
    independent noise). Returns (features, y, z)."""
    def gamma(shape_k: float) -> torch.Tensor:   # mean 1, std 1/sqrt(k), nonnegative
        return torch._standard_gamma(torch.full(clean.shape, shape_k), generator=gen) / shape_k

    y = clean * gamma(2.0)
    noisy_b = clean * gamma(8.0)
    z = torch.stack([_blur(noisy_b, s) for s in SIGMAS], 1)
    var = torch.stack([(clean * 0.71) ** 2] + [(_blur(clean, s) * 0.35 / (2 * s)) ** 2 for s in SIGMAS], 1).mean(2)
    albedo = clean / clean.amax((1, 2, 3), keepdim=True)
    normal = torch.zeros_like(clean)
    normal[:, 2] = 1
    depth = torch.ones(clean.shape[0], *clean.shape[2:])
    feats = build_features(torch.cat([y[:, None], z], 1), var, albedo, normal, depth)
    return feats, y, z


def test_tiny_network_learns_to_beat_every_single_input():
    gen = torch.Generator().manual_seed(0)
    size, patch, n_train = 64, 32, 16
    train_clean = _scenes(gen, n_train, size)
    train = _noisy(gen, train_clean)
    test_clean = _scenes(gen, 4, size)
    test = _noisy(gen, test_clean)
    torch.manual_seed(0)
    model = build("tiny")
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)

    def evaluate(data, clean):
        with torch.no_grad():
            out = combine(data[1], data[2], model(data[0]))
        return float(relative_log_l1(out, clean)), float(relmse(out, clean, channel_axis=1))

    loss_before, _ = evaluate(train, train_clean)
    start, steps = time.perf_counter(), 0
    while steps < 300 and time.perf_counter() - start < 60:
        idx = torch.randint(0, n_train, (8,), generator=gen)
        i0, j0 = (int(v) for v in torch.randint(0, size - patch + 1, (2,), generator=gen))
        win = (..., slice(i0, i0 + patch), slice(j0, j0 + patch))
        logits = model(train[0][idx][win])
        loss = relative_log_l1(combine(train[1][idx][win], train[2][idx][win], logits, "unfold"),
                               train_clean[idx][win])
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps += 1
    loss_after, _ = evaluate(train, train_clean)
    _, test_relmse = evaluate(test, test_clean)
    inputs = [test[1]] + list(test[2].unbind(1))
    best_input = min(float(relmse(x, test_clean, channel_axis=1)) for x in inputs)
    assert steps >= 100, f"only {steps} steps in 60 s"
    assert loss_after < 0.8 * loss_before
    assert test_relmse < 0.5 * best_input, (test_relmse, best_input)


@pytest.mark.parametrize("h,w", [(1, 1), (2, 9), (3, 1)])
def test_images_smaller_than_the_window(h, w):
    model = build("small").eval()                     # K = 11 > image
    buf = make_buffer(h, w, seed=9)
    buf.estimates[:] = 0.0                            # all black
    out = denoise(buf, model)
    assert out.rgb.shape == (h, w, 3) and np.array_equal(out.rgb, np.zeros((h, w, 3), np.float32))
    buf = make_buffer(h, w, seed=10)
    out = denoise(buf, model)
    inp = from_buffer(buf)
    assert np.isfinite(out.rgb).all() and out.weights_per_z.shape == (4, h, w)
    np.testing.assert_allclose(out.weights_per_z.sum(0), 1.0, rtol=1e-5)
    # replicate padding: every term y_i + z_c - z_i uses pixels of the image itself
    y, z = inp.y.numpy(), inp.z.numpy()
    assert out.rgb.min() >= y.min() + z.min() - z.max() - 1e-5
    assert out.rgb.max() <= y.max() + z.max() - z.min() + 1e-5


@pytest.mark.parametrize("config", [FeatureConfig(), FeatureConfig(radius=True, passes=True),
                                    FeatureConfig(scale_free=True, outliers=True)])
def test_cropped_features_equal_the_crop_of_whole_image_features(config):
    from ppmrecon.model.features import buffer_scales

    buf = make_buffer(17, 23, seed=13)
    guide = torch.rand(1, 4, 17, 23)             # any whole-image planes: cropped like the rest
    whole = from_buffer(buf, config, guide=guide)
    rows, cols = slice(3, 11), slice(15, 23)
    part = from_buffer(buf, config, (rows, cols), buffer_scales(buf, config), guide)
    for a, b in zip(part, whole):
        torch.testing.assert_close(a, b[..., rows, cols], rtol=0, atol=0)
    alone = from_buffer(buf, config, (rows, cols))        # scales default to the whole buffer's too
    torch.testing.assert_close(alone.features, part.features, rtol=0, atol=0)
