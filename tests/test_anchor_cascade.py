"""benchmarks/anchor_cascade.py: its full variant is what ``GuideConfig.cascade`` ships."""
from dataclasses import replace

import numpy as np

from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint
from ppmrecon.model.infer import denoise
from tests.conftest import load_script, make_buffer


def _module():
    return load_script("benchmarks", "anchor_cascade")


def test_the_full_variant_is_denoise_with_the_cascade_and_the_parts_differ():
    """On a render whose ~z^3 / ~z^4 carry a bias beside a bright patch, ``k=4`` is
    ``denoise`` with ``cascade=4`` bit for bit and ``no cascade`` is ``denoise`` with it off;
    each part changes the image; every variant is finite and nonnegative."""
    bench = _module()
    buf = make_buffer(32, 32, seed=9)
    est = buf.estimates.copy()
    est[3:, 8:24, 8:24] *= 6.0                         # the wide kernels' bandwidth bias, far above the noise
    buf = replace(buf, estimates=est)
    net = load_checkpoint(DEFAULT_MODEL).model
    imgs = bench.variants(buf, net, [4.0])
    assert list(imgs) == ["no cascade", "k=4 aim", "k=4 aim+range", "k=4"]
    np.testing.assert_array_equal(imgs["no cascade"], denoise(buf, net, guide=replace(net.guide, cascade=0.0)).rgb)
    np.testing.assert_array_equal(imgs["k=4"], denoise(buf, net, guide=replace(net.guide, cascade=4.0)).rgb)
    assert not np.array_equal(imgs["k=4 aim+range"], imgs["k=4 aim"])
    assert not np.array_equal(imgs["k=4"], imgs["k=4 aim+range"])
    assert imgs["k=4"][8:24, 8:24].mean() < imgs["no cascade"][8:24, 8:24].mean()
    for img in imgs.values():
        assert np.isfinite(img).all() and (img >= 0).all()
