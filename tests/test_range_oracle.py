"""benchmarks/range_oracle.py: the oracles are the reference held in nested ranges."""

import numpy as np

from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint
from ppmrecon.metrics import relmse
from tests.conftest import load_script, make_buffer


def _module():
    return load_script("benchmarks", "range_oracle")


def test_oracles_hold_the_reference_in_ever_wider_ranges():
    """A reference far from every estimate at some pixels: the bare-range oracle is that
    reference clamped into [min, max] of the five guarded estimates, so it never leaves
    that range; each widening (the shipped share, then all the way) only brings the
    oracle closer to the reference; the shipped image is ``denoise``'s."""
    oracle = _module()
    buf = make_buffer(24, 24, seed=5)
    rng = np.random.default_rng(1)
    ref = (buf.estimates.mean(0) * rng.uniform(0.2, 3.0, (24, 24, 1))).astype(np.float32)
    net = load_checkpoint(DEFAULT_MODEL).model
    imgs = oracle.images(buf, ref, net)
    assert set(imgs) == set(oracle.VARIANTS)
    from ppmrecon.model.guard import guard_buffer
    est = guard_buffer(buf, net.guard).estimates
    bare = imgs["oracle range"]
    assert (bare >= est.min(0) - 1e-6).all() and (bare <= est.max(0) + 1e-6).all()
    assert 0 < relmse(imgs["oracle terms all"], ref) <= relmse(imgs["oracle terms"], ref) <= relmse(bare, ref)
    assert relmse(imgs["oracle terms all"], ref) < relmse(bare, ref)
    from ppmrecon.model.infer import denoise
    np.testing.assert_array_equal(imgs["shipped"], denoise(buf, net).rgb)
    # every guarded estimate lies in the range, so the oracle is at least as close as the best of them
    assert relmse(bare, ref) <= min(relmse(e, ref) for e in est) + 1e-9
    ratios = oracle.score(buf, ref, net)
    assert set(ratios) == set(oracle.VARIANTS) and all(v["ratio"] > 0 for v in ratios.values())
