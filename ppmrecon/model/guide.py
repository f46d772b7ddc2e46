"""Denoiser-guided weights for the consistent combiner (paper 002 Eq. 6; issue 12).

Eq. 6 is consistent for *any* weights (paper 002 Appendix A): the output is a convex
combination of the terms ``t^j_{c,i} = ~y_i + ~z^j_c - ~z^j_i``, each of which converges
to the truth y_c. So the weights may depend on anything, in particular on an
off-the-shelf denoiser's image of the same render. The guide ``g`` is OIDN (``pyoidn``,
HDR, with albedo and normal) applied to the (firefly-guarded) widest estimate ~z^4; the
prior logit of each term is its Gaussian log-likelihood under the guide,

    l^j_{c,i} = - |t^j_{c,i} - g_c|^2 / (2 sigma_c^2),   sigma_c = beta gbar_c + f s,

with ``|.|^2`` the mean over R, G, B, ``gbar_c`` the guide's RGB mean, ``s`` the image's
radiance scale (:func:`.guard.image_scale`) and ``f`` the guard's relative floor: a
relative tolerance, so the prior is unchanged when all radiance is scaled. The network's
logits are added to the prior (its head starts at zero, so an untrained guided model
*is* the guide's projection onto the terms), and the softmax of Eq. 6 normalises the sum.

The guide never enters the output directly: with small ``beta`` the combination is
the convex combination of terms closest to ``g``, i.e. the denoiser's image projected
into the consistent range of Eq. 6. Where the terms agree (many passes) the output is
pinned to them whatever ``g`` says, so OIDN's own bias cannot survive convergence;
where they disagree (few passes) the denoiser chooses among them.

Two robustness rules, because the guide is only as good as OIDN's view of one estimate:

* **B-only spikes** (:func:`despike`): a pixel of ~z^4 far above its own 3 x 3 median and
  above every ~y of its window (a light seen through a rare specular chain from hit point
  B) is replaced by that median before OIDN, which would otherwise keep it.
* **A and B disagree** (``cross``): OIDN also denoises ~y (hit point A); where the two
  guides differ by more than ``cross`` x, the guide is their geometric mean. On
  ``water_caustic`` (N = 128, study seed 21) a sub-pixel sparkle sat in every ~z^j of the
  pixel next to the true one; with the guide of ~z^4 alone the output took it (relMSE
  0.0145, 78% of it from five pixels), with ``cross = 2`` 0.0044. The shipped envelope
  runs with the rule off: with the ~y weight below it no longer pays, and in a dark scene
  whose ~y saw no photon in most pixels it put the geometric mean with OIDN's near-zero
  image of ~y into the guide (all 216 images of ``data/v3_cpu``, ``bench_guide.py --split
  all``: 0.557 -> 0.539 of the best input, 18 -> 14 images worse than it, worst 3.38 -> 1.83).

**Envelope mode** (``mode = "envelope"``, :func:`envelope`): the output is the guide itself,
held per channel inside the range of the pixel's five estimates, low frequencies anchored
to ~z^3 where they differ by more than its noise. No weights, no network; consistent
because anything held between five estimates that converge to x_c converges to x_c.
Measured on 120 validation images of ``data/v3_cpu`` and the 15 study renders
(``bench_guide.py``, ``envelope k=1``): 0.495 / 0.448 against 0.520 / 0.470 for Eq. 6 with
the guide's prior and the shipped network, 0 / 0 images worse than their best input
(against 2 / 0), 8x8-block ratio 0.95 / 1.23 (against 1.04 / 1.16): the softmax over terms
near g averages their noise, the clamp returns g wherever the estimates leave it room.

Two robustness rules of the envelope (issue 12, measured on every image of ``data/v3_cpu``
and the study renders, ``benchmarks/results/guide_spike``): ``y_spike`` leaves ~y out of a
pixel's range where it is a lone spike (:func:`lone_y_spikes`), and ``anchor_window`` takes
the neighbour correlation of the anchor's noise into its test
(:func:`.guard.correlated_lowpass_variance`).

The shipped envelope also widens the range the guide is held in towards paper 002 Eq. 6's
terms at few passes (``terms_passes`` 16, :func:`terms_range`): a pixel's five estimates
share its photons, so at few passes the truth often lies outside their range (measured on
an unselected set of 96 generated images, 128 more, the 15 study renders and N = 1024:
relMSE 3-12% lower on every set; docs/RECONSTRUCTION_LOG.md, eighth session).

**The anchor cascade** (``cascade`` k, :func:`cascade_aim`; the shipped default has k = 4): the
anchor's aim steps on down to ~z^2 and ~z^1 wherever its low-pass departs from the narrower
estimate's by more than k times that one's noise, the range's wider ~z^j are pulled to the
final aim, and OIDN denoises that aim in place of ~z^4: beside a bright caustic the wide kernels
gather its photons, and the guide, the range and the anchor otherwise all follow them. With
``cascade_y`` (shipped at 4) the aim takes one more step, to ~y, where ~z^1 itself shows the
trend (:func:`y_step`): on a caustic's rim even ~z^1 carries its photons. The shipped step is
taken down only in renders of fewer than 64 passes (``cascade_y_up``): a photon near a hit
point lifts the narrow kernels most, which over few passes reads as the same trend upwards.

**Chooser mode** (``mode = "chooser"``; the shipped model carries a chooser, opt-in): the
envelope and seven other images held in the same range, mixed per pixel by a small trained
network (:mod:`.chooser`); consistent by the same argument.

**OIDN's image of ~y in the guide** (``y_weight`` F, :func:`y_share`): after the cross rule
the guide is ``g + w (OIDN(~y) - g)``, ``w = F Vz / (Vy + F Vz)`` from the inputs' locally
blurred variances of the mean. ~y comes from its own hit point A, so the two images' noise
is independent, and its bandwidth bias is the smallest; the shipped default has F = 2
(``bench_guide.py``, ``benchmarks/results/guide_y``: study / validation / N = 1024 renders
0.448 / 0.571 / 0.724 -> 0.438 / 0.538 / 0.701, no image worse than its best input). A fixed
share of a quarter did as well up to N = 256 but put two N = 1024 renders above their best
input, where ~y's noise is ten times ~z^4's.

**NL-means in place of OIDN for the source** (``denoiser``; the shipped default has
"nlm_source" since the twentieth session, "oidn" before; :func:`nlm_image`): the
variance-normalised NL-means of Rousselle, Knaus & Zwicker 2012 denoises the guide's source
(with "nlm" ~y too) from the buffer's own variances of the mean. OIDN takes a photon map's
blotches for signal and at many passes smooths detail the estimates already resolve (its image
of ~z^4 scores 1.1-1.9x ~z^4 on the literature scenes at N = 256-1024); NL-means leaves a pixel
alone where the noise is small against its differences. Against OIDN for the source, on six
sets (``benchmarks/results/guide_s20_final_*``, variant ``shipped denoiser=oidn``): relMSE over
the best input lower on all six (literature to N = 1024 0.676 -> 0.596, at N = 1024 0.898 ->
0.770; ``holdout_s16`` 0.471 -> 0.430), images worse than their best input 12 -> 8, the 8x8
ratio lower on five (``holdout_n1024_s17`` 0.829 -> 0.864 the exception). A 7 x 7 window
(``nlm_radius`` 3) did about as well as 11 x 11 and 15 x 15 (``guide_s20_nlmr_*``,
``guide_s20_nlm_*``) and costs what the OIDN call it replaces does (0.5 s at 1280x720 on two
cores: the whole denoise stays at 1.86x OIDN's time). From 16 to 511 passes
(``nlm_joint_passes``, k = 0.7 ``nlm_joint_k``) the source and ~y are denoised together by one
NL-means with joint weights: their noise is independent, so a difference both show is signal
(literature scenes 0.584 -> 0.546 of the best input, ``holdout_s16`` 0.430 -> 0.414;
``benchmarks/results/guide_s21_final_*``), and it replaces the OIDN call on ~y (1.25x OIDN's time in
all since the twenty-second session's faster loop, ``benchmarks/results/denoise_s22``). From 512
passes (``nlm_y_passes``) each image has its own NL-means, ~y's at k = 1 (``nlm_y_k``): there the
joint filter cost water_caustic (0.89 -> 1.06 of its best input at N = 512). With ``nlm_albedo`` (off
by default) each pair is also measured on the albedo-demodulated images and the smaller distance
kept: textures no longer stop the averaging (``holdout_s21`` 0.576 -> 0.551, 11 -> 5 images worse
than their best input) but a hold-out generated before that choice did not gain (``holdout_s22``
0.424 -> 0.425) and the filter takes twice the time (2.00x OIDN's).

OIDN runs at its "fast" quality by default (``quality``): half the time of "high" at
1280x720 for a relMSE within 1%. A model may also read the guide (``FeatureConfig.guide``)
and temper the prior per pixel (``temperature``, :func:`guided_logits`); trained on
v2_cpu that generalised worse to the study scenes (``benchmarks/results/guide_aware``).

Measured with ``benchmarks/bench_guide.py`` (``benchmarks/results/guide/guide.md``): on 15
renders of the three literature scenes and the two built-in caustic scenes (N = 16, 64,
256) and 56 validation images of ``data/v2_cpu`` (N = 4..256), the geometric mean of
relMSE over the best single input is, without the cross rule, 0.488 / 0.606 at
``beta = 0.03`` (0.488 / 0.606 at 0.01, 0.518 / 0.635 at 0.1); with ``cross = 2`` 0.473 /
0.577 at 0.03 (0.475 / 0.578 at 0.01, 0.502 / 0.603 at 0.1; cross 4: 0.480 / 0.589). With
beta = 0.03 no image is worse than its best input, with or without the rule.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any, Mapping, NamedTuple

import numpy as np
import torch

from ..errors import UsageError
from ..fileio import unknown_keys
from .combine import N_CORRELATED, N_RGB, _padded_differences
from .guard import rgb_mean

if TYPE_CHECKING:
    from .guard import GuardConfig

#: Estimate the guide denoises: ~z^4, the widest bandwidth (lowest variance) of the five.
GUIDE_SOURCE = 4
#: OIDN's quality modes (pyoidn's names).
OIDN_QUALITIES = ("high", "balanced", "fast")
#: the largest NL-means search window's half width: (2 r + 1)^2 offsets, 961 at 15 (about 10 s
#: at 1280x720 on two cores); a mistyped radius should not run for hours
NLM_MAX_RADIUS = 15
#: what denoises the guide's images: OIDN, or variance-normalised NL-means (:func:`nlm_image`)
#: for both images or for the source's alone
DENOISERS = ("oidn", "nlm", "nlm_source")
#: What NL-means' albedo-demodulated distance divides by (``nlm_albedo``): the albedo's RGB
#: mean (one scalar per pixel) or each channel's own albedo.
ALBEDO_CHANNELS = ("mean", "rgb")
#: How the guide enters the reconstruction (:attr:`GuideConfig.mode`).
GUIDE_MODES = ("weights", "envelope", "chooser")
#: Modes whose output is built on the envelope (no Eq. 6).
ENVELOPE_MODES = ("envelope", "chooser")
#: :func:`despike`'s ratio: a spike is this many times above both neighbourhood levels.
SPIKE_RATIO = 4.0
#: Width (pixels) of the Gaussian that averages the variances in :func:`y_share`.
Y_WEIGHT_SIGMA = 2.0
#: Window (pixels) over which :func:`terms_range` takes Eq. 6's terms: the combiner's 3 x 3.
TERMS_WINDOW = 3
#: :func:`candidate_medians` (the spike tests) computes the 3 x 3 medians of the whole image
#: when more than this fraction of its pixels are candidates, else at the candidates only.
DENSE_SPIKES = 0.05


#: The guide's numeric settings: name -> (valid range, what the one-line error calls a valid
#: value). The range is ">0" (finite, > 0), ">=0" (finite, >= 0) or "0|>1" (0 = off, or
#: finite and > 1); :meth:`GuideConfig.__post_init__` checks each, booleans refused.
_NUMBERS = {
    "beta": (">0", "a number > 0"),
    "anchor_noise": (">0", "a number > 0"),
    "y_weight": (">=0", "a number >= 0"),
    "y_spike": ("0|>1", "0 (off) or a finite factor > 1"),
    "anchor_window": (">=0", "a number >= 0"),
    "anchor_settled": (">=0", "a ratio >= 0 (0 = off)"),
    "anchor_select": (">=0", "a factor >= 0 (0 = off)"),
    "terms_passes": (">=0", "a pass count >= 0 (0 = off)"),
    "anchor_spikes": ("0|>1", "0 (off) or a finite factor > 1"),
    "z_spike": ("0|>1", "0 (off) or a finite factor > 1"),
    "anchor_free": (">=0", "a ratio >= 0 (0 = off)"),
    "redistribute": (">=0", "a width in px >= 0 (0 = off)"),
    "y_found": (">=0", "a width in px >= 0 (0 = off)"),
    "y_empty": (">=0", "a width in px >= 0 (0 = off)"),
    "cascade": (">=0", "a factor >= 0 (0 = off)"),
    "cascade_passes": (">=0", "a pass count >= 0 (0 = every N)"),
    "cascade_y": (">=0", "a factor >= 0 (0 = off)"),
    "nlm_k": (">0", "a factor > 0"),
    "nlm_radius": (">0", f"a whole number of pixels, 1..{NLM_MAX_RADIUS}"),
    "cascade_y_up": (">=0", "a pass count >= 0 (0 = up and down at every N)"),
    "nlm_y_passes": (">=0", "a pass count >= 0 (0 = never)"),
    "nlm_y_k": (">=0", "a factor >= 0 (0 = nlm_k)"),
    "anchor_free_dark": (">=0", "a factor >= 0 (0 = an empty ~z^4 only)"),
    "nlm_joint_passes": (">=0", "a pass count >= 0 (0 = never)"),
    "nlm_joint_k": (">=0", "a factor >= 0 (0 = nlm_k)"),
    "nlm_albedo": (">=0", "a factor >= 0 (0 = off)"),
    "nlm_albedo_eps": (">0", "a number > 0"),
    "range_sigma": (">=0", "a factor >= 0 (0 = off)"),
    "range_sigma_rel": (">=0", "a relative standard deviation >= 0 (0 = no test)"),
    "range_sigma_width": (">=0", "a factor >= 0 (0 = no test)"),
    "range_sigma_isolated": (">=0", "a factor >= 0 (0 = no test)"),
}


def _in_range(value: float, low: str) -> bool:
    if low == "0|>1":
        return value == 0 or (math.isfinite(value) and value > 1)
    return math.isfinite(value) and (value > 0 if low == ">0" else value >= 0)


@dataclass(frozen=True)
class GuideConfig:
    """Denoiser-guide settings; travel inside the checkpoint (``"guide"``)."""

    enabled: bool = False
    beta: float = 0.03           # relative tolerance of the prior: sigma = beta * gbar + floor * s
    source: int = GUIDE_SOURCE   # which estimate OIDN denoises (0 = ~y, 1..4 = ~z^j)
    #: > 1: also denoise ~y (its own hit point A) and, where the two guides differ by more
    #: than this factor, use their geometric mean; 0 = off
    cross: float = 0.0
    #: OIDN's quality mode for the guide ("high", "balanced" or "fast"): "fast" halves
    #: OIDN's time at 1280x720 for 0.2% better / 0.9% worse relMSE (study scenes /
    #: validation, ``bench_guide.py``); checkpoints without the setting read as "fast"
    quality: str = "fast"
    #: what denoises the guide's images (:data:`DENOISERS`; checkpoints without it read as "oidn")
    denoiser: str = "oidn"
    #: NL-means: the patch distance's tolerance k in units of the noise (Rousselle et al. 2012)
    nlm_k: float = 0.45
    #: NL-means: the search window's half width in px (patches of half width radius // 2, at
    #: least 1); the time grows as the window's area, (2 r + 1)^2 offsets (3: 0.28 s at 1280x720
    #: on two cores; 5 and 7 scored within 3% of it: ``benchmarks/results/guide_s20_nlmr_*``)
    nlm_radius: float = 3
    #: the network also predicts a per-pixel log-temperature tau of the prior:
    #: logits = prior * exp(-tau) + correction (see :func:`guided_logits`)
    temperature: bool = False
    #: how the guide enters: "weights" = the prior of Eq. 6's weights (the network adds its
    #: correction); "envelope" = the output is the guide held inside the range of the
    #: pixel's five estimates (:func:`envelope`; the network is not run); "chooser" = a learned
    #: per-pixel convex combination of the envelope and other band-held candidates
    #: (:mod:`.chooser`; needs a checkpoint with chooser weights)
    mode: str = "weights"
    #: envelope mode: the low-frequency anchor to ~z^(anchor_source) acts where the gap
    #: exceeds ``anchor_noise`` times the variance of that estimate's low-pass
    #: (:func:`.guard.anchor_where_biased`); ~z^3, not the widest ~z^4, whose bandwidth
    #: bias next to bright caustics the anchor would otherwise bring back
    anchor_noise: float = 1.0
    anchor_source: int = 3
    #: weight f of OIDN's image of ~y in the guide, against OIDN's image of the source, each
    #: weighted by the inverse of its input's local variance of the mean (:func:`y_share`):
    #: ~y is gathered at its own hit point A, so the two images' noise is independent and
    #: averages out, and ~y has the smallest bandwidth bias; 0 = the source's image alone
    #: (checkpoints without the setting read as 0)
    y_weight: float = 0.0
    #: envelope modes: > 1 leaves ~y out of a pixel's range where it is a lone spike, more
    #: than this factor above every ~z^j of the pixel and above its own 3 x 3 median
    #: (:func:`lone_y_spikes`); 0 = off (checkpoints without the setting read as 0)
    y_spike: float = 0.0
    #: envelope modes: > 0 estimates the neighbour correlation of the anchor's noise over a
    #: Gaussian window of this many pixels and takes it into the anchor's noise test
    #: (:func:`.guard.correlated_lowpass_variance`); 0 = independent pixels (checkpoints
    #: without the setting read as 0)
    anchor_window: float = 0.0
    #: envelope modes: > 0 lets the anchor act only where its own low-pass is settled,
    #: sqrt(Var(G * ~z^m)) below this r0 times G * ~z^m (:func:`.guard.anchor_where_biased`): a
    #: mean resting on one photon event has a ratio ~1, on k events ~1/sqrt(k), so one
    #: photon's plateau under a wide kernel is not taken for a low-frequency reference;
    #: 0 = off (checkpoints without the setting read as 0)
    anchor_settled: float = 0.0
    #: envelope modes: > 0 aims the anchor per pixel between ~z^m and the next wider
    #: ~z^(m+1) (:func:`anchor_target`): the wider, less noisy one where the two low-passes
    #: agree within this factor k times ~z^m's low-pass variance, ~z^m where the wider one's
    #: bandwidth bias shows; 0 = ~z^m alone, as with m = 4 (no wider estimate; checkpoints
    #: without the setting read as 0)
    anchor_select: float = 0.0
    #: envelope modes: > 0 widens each pixel's range towards that of Eq. 6's terms over its
    #: 3 x 3 window by the share 1 / (1 + N / M) for a render of N passes, M = this
    #: (:func:`terms_range`): all the way at few passes, where the five estimates' own range
    #: is too narrow to hold the truth, little at many; 0 = off (checkpoints without the
    #: setting read as 0)
    terms_passes: float = 0.0
    #: envelope modes: > 1 keeps the anchor from spreading the gap of an isolated bright pixel
    #: of its aim (RGB mean above this factor x its second brightest neighbour's) into its neighbours,
    #: and gives that pixel the inverse-variance mean of ~y and ~z^4 (:func:`aim_spikes`);
    #: 0 = off (checkpoints without the setting read as 0)
    anchor_spikes: float = 0.0
    #: > 0 scales ~y's share in the guide (:func:`y_share`) by the fraction of pixels, over a
    #: Gaussian of this many px, where ~y is not sparser than the source estimate: fewer than
    #: one photon event's worth (mean^2 / variance of the mean < 1, or ~y = 0) where the source
    #: has more. A photon-starved ~y reads 0 with variance 0 whatever the light there, and
    #: the share would trust its black image; 0 = off (checkpoints without it read as 0)
    y_found: float = 0.0
    #: > 0 scales ~y's share in the guide (:func:`y_share`) by the fraction of pixels, over a
    #: Gaussian of this many px, where ~y did not read 0 while the source estimate rests on
    #: more than one photon event: a ~y that caught nothing reads 0 with variance 0, which the
    #: share takes for certainty. The narrower sibling of ``y_found`` (which also counts a ~y
    #: of less than one event as starved); 0 = off (checkpoints without it read as 0)
    y_empty: float = 0.0
    #: envelope modes: > 1 holds a pixel at ~y alone where the ~z^j are a lone spike over a
    #: settled ~y: ~y's sqrt(V)/mean below the guard's r0 (many events), every ~z^j's at or
    #: above it (a few events) and every ~z^j more than this factor above ~y
    #: (:func:`lone_z_spikes`); 0 = off (checkpoints without it read as 0)
    z_spike: float = 0.0
    #: envelope modes: > 0 holds the anchored value of a pixel whose five estimates are all
    #: unsettled at this r (sqrt(V)/mean >= r, or 0) while ~z^4 caught a photon (a photon
    #: speckle field, whose per-pixel range says little about its mean) in its range widened
    #: to the 5 x 5 medians of its ends (:func:`speckle_field`, :func:`speckle_range`);
    #: 0 = off (checkpoints without it read as 0)
    anchor_free: float = 0.0
    #: envelope modes: > 0 gives back, within the range of the pixels around, what the final
    #: clamp took from the anchored image, over a Gaussian of this many px
    #: (:func:`redistribute`); 0 = off (checkpoints without it read as 0)
    redistribute: float = 0.0
    #: envelope modes: > 0 steps the anchor's aim on down ~z^(m-1), ..., ~z^1 per pixel
    #: wherever the aim's low-pass departs from the narrower estimate's by more than this k
    #: times the latter's noise, pulls the wider ~z^j the range is made of towards the final
    #: aim by as much, and gives OIDN that aim in place of its source estimate
    #: (:func:`cascade_aim`): a wide kernel beside a bright caustic gathers its photons
    #: (``0001_caustic_paths`` of ``holdout_n1024_s16``: 3.5-4.3x its best input at every N);
    #: 0 = off (checkpoints without it read as 0)
    cascade: float = 0.0
    #: with ``cascade``: renders of fewer passes than this run without it (0 = at every N). Its
    #: test weighs a gap against a sample variance, which over four passes has three degrees of
    #: freedom: a block of narrow estimates lifted in a few passes reads a small variance, and
    #: the steps follow it (``holdout_s18`` ``0010_indirect`` N = 4: 0.81 -> 1.06 of the best input)
    cascade_passes: float = 0.0
    #: with ``cascade`` (inert without it, so that turning the cascade off needs one setting):
    #: > 0 takes the aim one step further, to ~y (hit point A), wherever its low-pass departs
    #: from ~y's by more than this k times ~y's noise and ~z^1 departs from the wide estimates
    #: the same way; the ~z^j of the range are not pulled by this step (:func:`y_step`). Beside
    #: a bright caustic even ~z^1 gathers its photons: ``0001_caustic_paths`` of
    #: ``holdout_n1024_s16`` N = 64, pixel (52, 75): ~y 7.5, ~z^1..~z^4 14 / 22 / 37 / 62,
    #: reference 4.2; 0 = off (checkpoints without it read as 0)
    cascade_y: float = 0.0
    #: with ``cascade_y``: renders of fewer than this many passes take that step down only
    #: (~y below the aim); 0 = up and down at every N (checkpoints without it read as 0). A
    #: photon landing near a hit point adds E / (pi r^2) to every kernel that holds it, the
    #: narrow ones most, which over few passes reads as the trend of a real peak
    #: (``holdout_s18`` ``0010_indirect`` N = 16: ~y 42, ~z^1..~z^4 31 / 22 / 19 / 14, a 4096-pass
    #: reference 13.4; against it the image is 0.977 of its best input stepping down only, 1.055
    #: stepping up too); the bias the step is for lies the other way (wide kernels beside a
    #: bright caustic read high)
    cascade_y_up: float = 0.0
    #: with denoiser "nlm_source": renders of at least this many passes denoise ~y by NL-means
    #: too (OIDN below); 0 = never (checkpoints without it read as 0)
    nlm_y_passes: float = 0.0
    #: NL-means' k for ~y (with "nlm", or "nlm_source" and ``nlm_y_passes``); 0 = ``nlm_k``
    nlm_y_k: float = 0.0
    #: with denoiser "nlm" or "nlm_source", where the guide uses ~y: renders of at least this
    #: many passes (and fewer than ``nlm_y_passes``, where each image has its own NL-means)
    #: denoise the source and ~y by one NL-means with joint weights (:func:`nlm_image` of both;
    #: their noise is independent, so the patch distance has twice the evidence); 0 = never
    #: (checkpoints without it read as 0)
    nlm_joint_passes: float = 0.0
    #: the joint filter's k; 0 = ``nlm_k``
    nlm_joint_k: float = 0.0
    #: with ``anchor_free``: a pixel whose widest estimate ~z^4 reads at most this factor x the
    #: guard's floor x the image's scale is dark, not a speckle (:func:`speckle_field`); 0 = only
    #: an empty ~z^4 (checkpoints without it read as 0)
    anchor_free_dark: float = 0.0
    #: > 0: NL-means also measures each pair on the albedo-demodulated images, counted this many
    #: times, and keeps the smaller distance (:func:`nlm_image`'s ``albedo``; a textured surface
    #: no longer stops the averaging); 0 = off (checkpoints without it read as 0)
    nlm_albedo: float = 0.0
    #: the demodulation divides by the albedo's RGB mean plus this (a black albedo, or a
    #: surface whose G-buffer albedo says little, does not blow the division up)
    nlm_albedo_eps: float = 0.05
    #: the demodulation divides by the albedo's RGB mean ("mean") or each channel by its own
    #: albedo ("rgb": a texture of two hues, not only of two levels, divided out); checkpoints
    #: without it read as "mean"
    nlm_albedo_channels: str = "mean"
    #: envelope modes: > 0 widens each estimate X_k of a pixel's range to X_k +- this kappa
    #: times its own standard deviation of the mean (:func:`noise_range`): at many passes the
    #: five estimates share their photons, so their range is narrower than their noise and the
    #: clamp hands that noise back to the guide; 0 = off (checkpoints without it read as 0)
    range_sigma: float = 0.0
    #: with ``range_sigma``: only estimates whose standard deviation is at most this share of
    #: their own level are widened (a rare path's sparkle, sd ~ 0.4 x its level, keeps the bare
    #: range, which is what stops NL-means from flattening it); 0 = every estimate
    range_sigma_rel: float = 0.0
    #: with ``range_sigma``: widen only pixels whose bare range is at most this many times the
    #: widest estimate's standard deviation (estimates that agree within their noise err
    #: together; a range wider than that holds a feature's bandwidth bias, a caustic's);
    #: 0 = every pixel
    range_sigma_width: float = 0.0
    #: with ``range_sigma``: no widening where ~z^4 (its RGB mean) is more than this many times
    #: its own 3 x 3 median, an isolated sparkle (a rare path's, which NL-means flattens if
    #: the range lets it); a per-pixel alternative to ``range_sigma_rel``; 0 = no test
    range_sigma_isolated: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise ValueError(f"guide setting 'enabled' must be true or false, got {self.enabled!r}")
        for name, (low, what) in _NUMBERS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not _in_range(value, low):
                raise ValueError(f"guide setting '{name}' must be {what}, got {value!r}")
        if isinstance(self.cross, bool) or not isinstance(self.cross, (int, float)) \
                or not (self.cross == 0 or self.cross > 1):
            raise ValueError(f"guide setting 'cross' must be 0 (off) or a factor > 1, got {self.cross!r}")
        if not isinstance(self.temperature, bool):
            raise ValueError(f"guide setting 'temperature' must be true or false, got {self.temperature!r}")
        if self.temperature and not self.enabled:
            raise ValueError("guide setting 'temperature' needs the guide enabled")
        if self.quality not in OIDN_QUALITIES:
            raise ValueError(f"guide setting 'quality' must be one of {', '.join(OIDN_QUALITIES)}, "
                             f"got {self.quality!r}")
        if not (float(self.nlm_radius).is_integer() and self.nlm_radius <= NLM_MAX_RADIUS):
            raise ValueError(f"guide setting 'nlm_radius' must be a whole number of pixels, 1..{NLM_MAX_RADIUS:g}, "
                             f"got {self.nlm_radius!r}")
        if self.denoiser not in DENOISERS:
            raise ValueError(f"guide setting 'denoiser' must be one of {', '.join(DENOISERS)}, got {self.denoiser!r}")
        if self.nlm_albedo_channels not in ALBEDO_CHANNELS:
            raise ValueError(f"guide setting 'nlm_albedo_channels' must be one of {', '.join(ALBEDO_CHANNELS)}, "
                             f"got {self.nlm_albedo_channels!r}")
        if self.mode not in GUIDE_MODES:
            raise ValueError(f"guide setting 'mode' must be one of {', '.join(GUIDE_MODES)}, got {self.mode!r}")
        if self.mode in ENVELOPE_MODES and self.temperature:
            raise ValueError(f"guide setting 'temperature' shapes Eq. 6's weights: it has no meaning in '{self.mode}' mode")
        if isinstance(self.anchor_source, bool) or self.anchor_source not in range(1, 5):
            raise ValueError(f"guide setting 'anchor_source' must be a ~z index 1..4, got {self.anchor_source!r}")
        if isinstance(self.source, bool) or self.source not in range(5):
            raise ValueError(f"guide setting 'source' must be an estimate index 0..4, got {self.source!r}")
        if self.cascade and (self.source == 0 or self.anchor_source == 1):
            raise ValueError("guide setting 'cascade' steps the aim down from ~z^(anchor_source) to ~z^1 and "
                             "gives it to OIDN in place of a ~z^j: it needs anchor_source >= 2 and source >= 1, "
                             f"got anchor_source {self.anchor_source}, source {self.source}")

    def in_mode(self, mode: str) -> "GuideConfig":
        """The same settings in guide mode ``mode``; a learned temperature belongs to Eq. 6's
        weights and is dropped in the envelope."""
        return replace(self, mode=mode, temperature=self.temperature and mode == "weights")

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "GuideConfig":
        unknown = unknown_keys(cls, data)
        if unknown:
            raise ValueError(f"unknown guide setting(s) {', '.join(unknown)}")
        return cls(**dict(data))


#: The guide on, with the measured defaults (see the module docstring).
DEFAULT_GUIDE = GuideConfig(enabled=True, cross=2.0)


def _pyoidn():
    try:
        import pyoidn
    except ImportError:
        raise UsageError("the denoiser guide needs pyoidn (pip install 'pyoidn>=2.3'); "
                         "or run without it (--guide off)") from None
    return pyoidn


def oidn_image(colour: np.ndarray, albedo: np.ndarray, normal: np.ndarray, quality: str = "high") -> np.ndarray:
    """OIDN's HDR denoise of one (H, W, 3) image with its albedo and normal, float32."""
    out = _pyoidn().denoise(np.ascontiguousarray(colour, np.float32), np.ascontiguousarray(albedo, np.float32),
                            np.ascontiguousarray(normal, np.float32), hdr=True, quality=quality)
    out = np.asarray(out, np.float32)
    # OIDN may return tiny negatives near edges; radiance is >= 0 and the prior needs a finite guide
    return np.nan_to_num(out, nan=0.0, posinf=0.0, neginf=0.0).clip(min=0.0)


#: NL-means: a patch distance beyond this many noise units gets weight 0 (e^-30 ~ 1e-13)
NLM_CUT = 30.0


def nlm_window(cfg: GuideConfig) -> tuple[int, int]:
    """The NL-means search window's and patches' half widths in px from ``cfg.nlm_radius``."""
    radius = int(cfg.nlm_radius)
    return radius, max(1, radius // 2)


def nlm_image(colour: torch.Tensor, variance: torch.Tensor, k: float = 0.45, radius: int = 3,
              patch: int = 1, albedo: torch.Tensor | None = None, albedo_penalty: float = 2.0) -> torch.Tensor:
    """Non-local means with the variance-normalised patch distance of Rousselle, Knaus &
    Zwicker 2012 ("Adaptive Rendering with Non-Local Means Filtering", their per-pixel distance
    with the variance-cancellation term, alpha = 1): colour (3 G, H, W), G images of R, G, B,
    ``variance`` (G, H, W) (or (H, W) for one image) each one's variance of the mean,

        d^2_g(p, q) = (|u_p - u_q|^2 - (V_p + min(V_p, V_q))) / (eps + k^2 (V_p + V_q))
        d^2(p, q) = box_f [ mean_g d^2_g(p, q) ]
        out_p = sum_q w_pq u_q / sum_q w_pq,   w_pq = exp(-max(0, d^2(p, q)))

    over a (2 radius + 1)^2 window, |.|^2 the mean over R, G, B, box_f the mean over a
    (2 patch + 1)^2 patch (cut at the image's edges). Where the noise is small against the
    image's own differences the weights vanish and the image is kept; OIDN assumes noise and
    smooths detail instead. With G > 1 the images share one set of weights (a joint filter:
    images of independent noise, ~y and the guide's source, each denoised with the evidence
    of both). Memory-bound: the buffers are reused across the window's offsets, and each offset
    o is taken with its mirror -o, whose pairs are the same pairs seen from the other end (the
    terms symmetric in p and q computed once; the whole filter 1.5-1.9x faster than one pass per
    offset with ``avg_pool2d`` for the patch, at 1280x720 on two cores).

    ``albedo`` (H, W), a positive scalar albedo a per pixel: each pair (p, q) also takes the
    distance d_a^2 of the demodulated images u / a, V / a^2 (the albedo's texture divided out,
    as where diffuse radiance is a times a smooth irradiance), counted ``albedo_penalty`` times,
    and keeps the smaller of the two; a pair that chose the demodulated distance is averaged as
    a_p u_q / a_q. ``albedo`` (3, H, W) divides each channel by its own albedo (a texture of
    two hues, not only two levels, divided out): the demodulated distance is the plain one with
    |u_p - u_q|^2 replaced by mean_c a_pc a_qc (u_pc / a_pc - u_qc / a_qc)^2, which is the plain
    distance exactly wherever the albedo is the same at p and q (V, the mean of the channels'
    variances, stays as it is; dividing it by a level of the albedo instead lets a saturated
    albedo, 0.01 / 0.01 / 0.89, pass a channel's real differences for noise: the literature
    ``box`` scene's caustic spots on its blue wall were smoothed over, 0.57 -> 0.64-0.71 of the
    best input). Texture then no longer stops the averaging, while a pair whose radiance is
    not the albedo's (a glossy highlight, a caustic or an emitter over a texture) stays with
    the plain distance. Where a is flat the two distances are equal and the plain one wins."""
    groups = 1 if variance.dim() == 2 else variance.shape[0]
    u = colour[None].float().contiguous()
    v = variance.reshape(1, groups, *variance.shape[-2:]).float().clamp(min=0.0)
    height, width = u.shape[-2:]
    r = radius
    tiny = torch.finfo(torch.float32).tiny

    def padded(x: torch.Tensor) -> torch.Tensor:
        return torch.nn.functional.pad(x, (r, r, r, r), mode="replicate")

    domains = [(padded(u), padded(v))]                  # (padded u, padded V): plain, then u / a
    pad_a = None                                        # per channel: the pair weight's albedo
    if albedo is not None:
        if albedo.dim() == 3:       # per channel: u_c / a_c, each difference weighted by a_pc a_qc (below)
            a = albedo[None].float().repeat(1, groups, 1, 1)
            domains.append((padded(u / a), domains[0][1]))
            pad_a = padded(a)
        else:
            a = albedo.reshape(1, 1, height, width).float()
            domains.append((padded(u / a), padded(v / a.square())))
        num_a, chose_a = torch.zeros_like(u), torch.empty_like(v[:, :1], dtype=torch.bool)
    num, den = torch.zeros_like(u), torch.zeros_like(v[:, :1])
    region = (height + r) * (width + 2 * r)             # the largest pair region (below)
    store = {name: torch.empty(c * region) for name, c in (("diff", 3 * groups), ("sum", groups),
                                                          ("low", groups), ("scale", groups))}
    dist, joint, rows, w_a = torch.empty_like(v), torch.empty_like(den), torch.empty_like(den), torch.empty_like(den)
    inv_count = box_sum(torch.ones_like(den), patch, rows, torch.empty_like(den)).reciprocal_()

    def buffer(name: str, channels: int, h: int, w: int) -> torch.Tensor:
        return store[name][:channels * h * w].view(1, channels, h, w)

    def pair_distances(pad_u: torch.Tensor, pad_v: torch.Tensor, oy: int, ox: int,
                       weight: torch.Tensor | None = None) -> list[torch.Tensor]:
        """d^2(p, p + o) and d^2(p, p - o) of every p, each (1, 1, H, W) (one for o = 0): the
        terms symmetric in a pair (|u_p - u_q|^2, min(V_p, V_q), V_p + V_q) are computed once
        for both offsets, over the region of pairs (x, x + o) that either needs. ``weight``
        (padded, per channel): each channel's squared difference times weight_p weight_q."""
        h, w = height + oy, width + abs(ox)
        y0, x0 = r - oy, r - max(ox, 0)
        first = (..., slice(y0, y0 + h), slice(x0, x0 + w))
        second = (..., slice(y0 + oy, y0 + oy + h), slice(x0 + ox, x0 + ox + w))
        diff = torch.sub(pad_u[first], pad_u[second], out=buffer("diff", 3 * groups, h, w)).square_()
        if weight is not None:
            diff.mul_(weight[first]).mul_(weight[second])
        total = torch.sum(diff.view(1, groups, 3, h, w), 2, out=buffer("sum", groups, h, w)).mul_(1.0 / 3.0)
        v1, v2 = pad_v[first], pad_v[second]
        low = torch.minimum(v1, v2, out=buffer("low", groups, h, w))
        scale = torch.add(v1, v2, out=buffer("scale", groups, h, w)).mul_(k * k).add_(tiny)
        out = []
        # p + o: p is the pair's first pixel; p - o: its second
        for at, v_p in (((..., slice(oy, oy + height), slice(max(ox, 0), max(ox, 0) + width)), v1),
                        ((..., slice(0, height), slice(max(-ox, 0), max(-ox, 0) + width)), v2)):
            torch.add(low[at], v_p[at], out=dist)                            # V_p + min(V_p, V_q)
            torch.sub(total[at], dist, out=dist).div_(scale[at])
            d = dist if groups == 1 else torch.mean(dist, 1, keepdim=True, out=joint)
            out.append(box_sum(d, patch, rows, torch.empty_like(den)).mul_(inv_count))
            if oy == 0 and ox == 0:
                break
        return out

    # each offset o of the upper half window with its mirror -o (and o = 0 once)
    for oy in range(r + 1):
        for ox in range(-r if oy else 0, r + 1):
            plain = pair_distances(*domains[0], oy, ox)
            demod = pair_distances(*domains[1], oy, ox, pad_a) if albedo is not None else [None] * len(plain)
            for sign, w, d_a in zip((1, -1), plain, demod):
                window = (..., slice(r + sign * oy, r + sign * oy + height),
                          slice(r + sign * ox, r + sign * ox + width))
                if d_a is not None:
                    d_a.mul_(albedo_penalty)
                    torch.lt(d_a, w, out=chose_a)
                    torch.minimum(w, d_a, out=w)
                # weights below e^-NLM_CUT are set to 0 exactly: subnormal products otherwise slow
                # the loop down 1.3-1.7x on CPUs (measured at 1280x720)
                w.clamp_(0.0, NLM_CUT).neg_().exp_().sub_(math.exp(-NLM_CUT))
                den.add_(w)
                if d_a is not None:
                    num_a.addcmul_(torch.mul(w, chose_a, out=w_a), domains[1][0][window])
                    w.sub_(w_a)
                num.addcmul_(w, domains[0][0][window])
    if albedo is not None:
        num.addcmul_(num_a, a)
    return (num / den)[0]


def box_sum(x: torch.Tensor, half: int, rows: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """The sum of ``x`` (..., H, W) over the (2 half + 1)^2 box around each pixel, cut at the
    image's edges, into ``out``; ``rows`` (as x) holds the horizontal pass. Separable, in place:
    3.5x faster than ``avg_pool2d`` of one channel at 1280x720 on two cores."""
    rows.copy_(x)
    for s in range(1, half + 1):
        rows[..., s:].add_(x[..., :-s])
        rows[..., :-s].add_(x[..., s:])
    out.copy_(rows)
    for s in range(1, half + 1):
        out[..., s:, :].add_(rows[..., :-s, :])
        out[..., :-s, :].add_(rows[..., s:, :])
    return out


def despike(source: torch.Tensor, y: torch.Tensor, eps: float, ratio: float = SPIKE_RATIO) -> torch.Tensor:
    """The guide's input without the spikes that hit point B alone saw, (3, H, W).

    source, y (3, H, W): the estimate OIDN will denoise and ~y. A pixel is a spike when its
    RGB mean exceeds ``ratio`` x (the 3 x 3 median of the source + eps) *and* ``ratio`` x
    (the largest ~y of its 3 x 3 window + eps): ~y gathers at its own hit point A, so a
    light seen through a rare specular chain from B shows in every ~z^j (and so in all
    their terms but i = c) while ~y around it stays low; OIDN keeps such a lone bright
    pixel, and the guide would then pick the spike. Spikes are replaced by the source's
    3 x 3 median. Only the weights depend on the guide, so this costs no consistency.
    """
    lum, ylum = rgb_mean(source, 0), rgb_mean(y, 0)
    ymax = window_max(ylum, size=3)
    rows, cols, med = candidate_medians(source, lum > ratio * (ymax + eps))
    spike = lum[rows, cols] > ratio * (med.mean(0) + eps)
    out = source.clone()
    out[:, rows[spike], cols[spike]] = med[:, spike]
    return out


def candidate_medians(x: torch.Tensor, candidate: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The 3 x 3 medians of x (C, H, W) at the ``candidate`` pixels (H, W) bool: rows, cols
    and the medians (C, n). At the candidates only when they are few (the usual case: a
    whole-image median costs about 60 ms at 1280 x 720), from the whole image's median when
    more than :data:`DENSE_SPIKES` of the pixels are candidates; the two agree exactly."""
    from .guard import median3x3, median3x3_at

    rows, cols = candidate.nonzero(as_tuple=True)
    if len(rows) > DENSE_SPIKES * candidate.numel():
        return rows, cols, median3x3(x)[:, rows, cols]
    return rows, cols, median3x3_at(x, rows, cols)


def lone_y_spikes(y: torch.Tensor, z: torch.Tensor, eps: torch.Tensor | float, ratio: float) -> torch.Tensor:
    """Where ~y is a lone spike, (B, 1, H, W) bool: its RGB mean exceeds ``ratio`` x (the
    largest ~z^j's RGB mean at the pixel + eps) *and* ``ratio`` x (its own 3 x 3 median's +
    eps). y (B, 3, H, W), z (B, 4, 3, H, W), eps a scalar or (B, 1, 1, 1).

    ~y gathers at its own hit point A; a rare path seen from A alone (a small emitter's
    edge through a specular chain) leaves one bright pixel that no ~z^j and no neighbour
    shares. The guard keeps it once its threshold has grown with N (16 sqrt N), OIDN
    spreads it into the guide, and the envelope's range reaches up to it: on
    ``0036_bright_emitters`` of ``data/v3_cpu`` at N = 256 one such pixel (~y 2.9e3, every
    ~z^j and the reference about 40) made the output 55x its best input. Leaving ~y out of
    the range there costs no consistency, as the ~z^j alone converge to the truth; and as
    the test compares ~y with the ~z^j of the same pixel it does not loosen with N.
    """
    ylum = y.mean(1, keepdim=True)
    eps = torch.as_tensor(eps, dtype=y.dtype, device=y.device).reshape(-1, 1, 1, 1).expand(y.shape[0], 1, 1, 1)
    spikes = ylum > ratio * (rgb_mean(z, 2).amax(1, keepdim=True) + eps)
    for b in range(y.shape[0]):                     # images of a batch (one at inference)
        rows, cols, med = candidate_medians(y[b], spikes[b, 0])
        spikes[b, 0, rows, cols] = ylum[b, 0, rows, cols] > ratio * (med.mean(0) + eps[b, 0, 0, 0])
    return spikes


def dark_level(cfg: GuideConfig, guard: GuardConfig, scale: torch.Tensor | float) -> torch.Tensor | float:
    """:func:`speckle_field`'s ``dark``: ``cfg.anchor_free_dark`` x the guard's floor x
    ``scale`` (:func:`.guard.floor_of`)."""
    from .guard import floor_of

    return cfg.anchor_free_dark * floor_of(guard) * scale


def y_spike_mask(y: torch.Tensor, z: torch.Tensor, cfg: GuideConfig, guard: GuardConfig,
                 scale: torch.Tensor | float) -> torch.Tensor | None:
    """:func:`lone_y_spikes` with the guide's factor ``cfg.y_spike`` and eps = the guard's
    floor x ``scale`` (:data:`.guard.RELATIVE_FLOOR` with the guard off); None when the rule
    is off. y (B, 3, H, W), z (B, 4, 3, H, W); the envelope and the chooser's band share it."""
    from .guard import floor_of

    if not cfg.y_spike:
        return None
    return lone_y_spikes(y, z, floor_of(guard) * scale, cfg.y_spike)


def lone_z_spikes(y: torch.Tensor, z: torch.Tensor, variances: torch.Tensor, eps: torch.Tensor | float,
                  ratio: float, r0: float) -> torch.Tensor:
    """Where the ~z^j are a lone spike over a settled ~y, (B, 1, H, W) bool: ~y's RGB mean is
    settled (sqrt(V) < r0 x mean, :func:`.guard.settled_mask`: many photon events), no ~z^j
    is, and every ~z^j's RGB mean exceeds ``ratio`` x (~y's + eps). y (B, 3, H, W), z (B, 4,
    3, H, W), ``variances`` (B, 5, H, W) the five variances of the mean, eps a scalar or
    (B, 1, 1, 1).

    The mirror of :func:`lone_y_spikes`: the four ~z^j share hit point B, so light that B's
    eye path alone saw in one pass (a small emitter through glass or in a mirror) lifts all
    four together, to the same value at every radius (emission, not a photon density:
    every pixel where the rule fires in the study renders and in ``0148`` has its four ~z^j
    within 1%). Beside a small light the guard's 3 x 3 median is
    high and keeps it (``0148_bright_emitters`` N = 64: every ~z^j 0.97 at sqrt(V)/mean 1.0,
    ~y 0.013 at 0.10, reference 0.016; the output was 0.42, 96% of the image's scaled
    error). A pixel held at ~y costs no consistency: ~y alone converges to the truth.
    """
    from .guard import settled_mask

    ylum, zlum = y.mean(1, keepdim=True), rgb_mean(z, 2)
    eps = torch.as_tensor(eps, dtype=y.dtype, device=y.device).reshape(-1, 1, 1, 1)
    settled_y = settled_mask(ylum, variances[:, :1], r0)
    loose_z = ~settled_mask(zlum, variances[:, 1:], r0).any(1, keepdim=True)
    return settled_y & loose_z & (zlum.amin(1, keepdim=True) > ratio * (ylum + eps))


def z_spike_mask(y: torch.Tensor, z: torch.Tensor, variances: torch.Tensor | None, cfg: GuideConfig,
                 guard: GuardConfig, scale: torch.Tensor | float) -> torch.Tensor | None:
    """:func:`lone_z_spikes` with the guide's factor ``cfg.z_spike``, eps as for
    :func:`y_spike_mask` and r0 the guard's ``min_rel_error`` (its default with the guard
    off); None when the rule is off. ``variances`` (B, 5, H, W)."""
    from .guard import DEFAULT_ON, floor_of

    if not cfg.z_spike:
        return None
    if variances is None:
        raise ValueError("the guide's z_spike needs the five variances of the mean")
    r0 = guard.min_rel_error if guard.enabled else DEFAULT_ON.min_rel_error
    return lone_z_spikes(y, z, variances, floor_of(guard) * scale, cfg.z_spike, r0)


def y_share(variances: np.ndarray, source: int, weight: float, found: float = 0.0,
            estimates: np.ndarray | None = None, empty: float = 0.0) -> torch.Tensor:
    """The share of OIDN's image of ~y in the guide, per pixel, (1, H, W):

        w = f Vbar_s / (Vbar_y + f Vbar_s),   Vbar = G_sigma * V

    with V the buffer's variance of the mean of ~y and of the source estimate s
    (``variances`` (5, H, W)), G_sigma a Gaussian of :data:`Y_WEIGHT_SIGMA` px and f =
    ``weight``: each OIDN image weighted by the inverse of its input's local noise, ~y's
    by f more (the shipped f = 2 lies between the validation images' best, 4, and the
    study scenes', 1; ``bench_guide.py``). Where neither input is noisy, 0. Many passes
    make ~y's noise the larger, so w falls with N.

    With ``found`` = S > 0 (and ``estimates`` (5, H, W, 3)), w is multiplied by
    G_S * [not (k_y < 1 <= k_s)], k = mean^2 / V about the number of photon events behind ~y
    and behind the source (RGB means; k >= 1 is :func:`.guard.settled_mask` at r0 = 1, 0 where
    nothing was seen, unbounded at an emitter seen directly): the local share of pixels where
    ~y is not sparser than the source. A
    photon-starved ~y (thin light leaks at a few passes) reads 0 with variance 0, or rests
    on less than one event, and would otherwise take the guide to black; where the source
    is as sparse (next to a small light, where ~y's image keeps the source's fireflies out
    of the guide) the share stays. The factor is 1 once ~y has seen its photons, so it
    leaves renders of many passes alone.

    With ``empty`` = S > 0 (and ``estimates``), w is multiplied by G_S * [not (~y = 0 and
    k_s > 1)]: the local share of pixels where ~y read something or the source is as sparse.
    Only a ~y that caught nothing counts as starved, not one of less than one event, whose
    OIDN image still helps at few passes (``benchmarks/results/guide_s12_yempty``: with
    ``found`` = 3 the control scene ``0110_glossy_interreflection`` at N = 4 went from 0.22 to
    0.40 of its best input, with ``empty`` = 3 to 0.25, while the thin light leaks of
    ``0039_texture_leaks``, worse than their best input at N = 4..64 with neither, improve
    with both).
    """
    from .guard import gaussian_lowpass, settled_mask

    raw = torch.from_numpy(np.ascontiguousarray(variances[[0, source]], np.float32))
    v = gaussian_lowpass(raw[None], Y_WEIGHT_SIGMA)[0]
    vs = weight * v[1:2]
    w = vs / (v[0:1] + vs).clamp(min=torch.finfo(v.dtype).tiny)     # 0 / tiny = 0 where nothing is noisy
    if (found or empty) and estimates is not None:
        means = rgb_mean(torch.from_numpy(np.ascontiguousarray(estimates[[0, source]], np.float32)), -1)
        events = settled_mask(means, raw, 1.0)                 # mean^2 / V > 1: more than one event
        for width, starved in ((found, ~events[0]), (empty, means[0] <= 0)):
            if width:
                w = w * gaussian_lowpass((~(starved & events[1])).to(raw.dtype)[None, None], width)[0]
    return w


class GuideImages(NamedTuple):
    """The guide and the two denoised images it is made of, each (3, H, W)."""

    guide: torch.Tensor
    source: torch.Tensor          # the denoiser's image of the (despiked) source estimate
    y: torch.Tensor | None        # the denoiser's image of ~y, when it was made


def guide_images(estimates: np.ndarray, albedo: np.ndarray, normal: np.ndarray, cfg: GuideConfig,
                 scale: float, floor: float, variances: np.ndarray | None = None,
                 need_y: bool = False, passes: float | None = None) -> GuideImages:
    """The guide ``g`` of a whole image and OIDN's images it is made of. ``estimates``
    (5, H, W, 3) are the (guarded) inputs; ``scale`` the image's radiance scale. OIDN
    denoises the source estimate with its B-only spikes removed (:func:`despike`); with
    ``cross``, ``y_weight`` or ``need_y`` it also denoises ~y, once. ``variances`` (5, H, W),
    the inputs' variances of the mean, are needed with ``y_weight`` (:func:`y_share`);
    ``passes``, the render's, decides ``nlm_joint_passes`` and ``nlm_y_passes``. Whole images
    only: neither denoiser has a halo."""
    mix_y = bool(cfg.y_weight and cfg.source)
    if mix_y and variances is None:
        raise ValueError("guide_images: the guide's y_weight needs the inputs' variances")
    est = torch.from_numpy(np.ascontiguousarray(estimates, np.float32)).permute(0, 3, 1, 2)
    source = despike(est[cfg.source], est[0], floor * float(scale)) if cfg.source else est[0]
    if cfg.denoiser != "oidn" and variances is None:
        raise ValueError("guide_images: the NL-means guide needs the inputs' variances")
    albedo_t = None
    if cfg.nlm_albedo and cfg.denoiser != "oidn":
        albedo_t = torch.from_numpy(np.ascontiguousarray(albedo, np.float32)).permute(2, 0, 1)
        if cfg.nlm_albedo_channels == "mean":
            albedo_t = albedo_t.mean(0)
        albedo_t = torch.nan_to_num(albedo_t, 0.0, 0.0, 0.0).clamp_(min=0.0).add_(cfg.nlm_albedo_eps)

    def nlm_of(images: list[torch.Tensor], indices: list[int], k: float) -> torch.Tensor:
        """NL-means (tolerance ``k``) of ``images`` (each (3, H, W)) with one set of weights,
        estimates ``indices``' variances; (3 len(images), H, W)."""
        variance = torch.from_numpy(np.ascontiguousarray(variances[indices], np.float32))
        return nlm_image(torch.cat(images), variance[0] if len(images) == 1 else variance, k, *nlm_window(cfg),
                         albedo=albedo_t, albedo_penalty=cfg.nlm_albedo)

    def denoised(image: torch.Tensor, index: int, nlm: bool, k: float) -> torch.Tensor:
        """OIDN's or NL-means' (tolerance ``k``) image of ``image`` (3, H, W), estimate
        ``index``'s variances."""
        if nlm:
            return nlm_of([image], [index], k)
        return torch.from_numpy(oidn_image(image.permute(1, 2, 0).numpy(), albedo, normal, cfg.quality)).permute(2, 0, 1)

    with_y, gy = bool(cfg.source and (cfg.cross or mix_y or need_y)), None
    many = bool(cfg.nlm_y_passes) and passes is not None and passes >= cfg.nlm_y_passes
    if with_y and cfg.denoiser != "oidn" and cfg.nlm_joint_passes and passes is not None \
            and passes >= cfg.nlm_joint_passes and not many:
        both = nlm_of([source, est[0]], [cfg.source, 0], cfg.nlm_joint_k or cfg.nlm_k)
        g, gy = both[:N_RGB], both[N_RGB:]
    else:
        g = denoised(source, cfg.source, cfg.denoiser != "oidn", cfg.nlm_k)
    g_source = g
    if with_y:
        if gy is None:
            nlm_y = cfg.denoiser == "nlm" or (cfg.denoiser == "nlm_source" and many)
            gy = denoised(est[0], 0, nlm_y, cfg.nlm_y_k or cfg.nlm_k)
        if cfg.cross:
            # A and B disagree: a sparkle seen from one hit point only (sub-pixel apart, or
            # a rare path); neither guide is to be trusted, their geometric mean lies between
            eps = floor * float(scale)
            a, b = g.mean(0, keepdim=True) + eps, gy.mean(0, keepdim=True) + eps
            apart = torch.maximum(a / b, b / a) > cfg.cross
            g = torch.where(apart, (g.clamp(min=0) * gy.clamp(min=0)).sqrt(), g)
        if mix_y:
            g = torch.lerp(g, gy, y_share(variances, cfg.source, cfg.y_weight, cfg.y_found, estimates, cfg.y_empty))
    elif need_y:
        gy = g                                          # the source is ~y itself
    return GuideImages(g, g_source, gy)


def planes(g: torch.Tensor, cfg: GuideConfig, scale: float, floor: float) -> torch.Tensor:
    """The guide planes (1, 4, H, W) of a guide image ``g`` (3, H, W): R, G, B of ``g`` and
    ``sigma = beta gbar + floor * scale``."""
    sigma = cfg.beta * g.mean(0, keepdim=True) + floor * float(scale)
    return torch.cat([g, sigma], 0)[None].contiguous()


def guide_planes(estimates: np.ndarray, albedo: np.ndarray, normal: np.ndarray, cfg: GuideConfig,
                 scale: float, floor: float, variances: np.ndarray | None = None) -> torch.Tensor:
    """The guide and its tolerance for a whole image, (1, 4, H, W): R, G, B of ``g``
    (:func:`guide_images`) and ``sigma = beta gbar + floor * scale``."""
    g = guide_images(estimates, albedo, normal, cfg, scale, floor, variances).guide
    return planes(g, cfg, scale, floor)


def anchor_target(z: torch.Tensor, anchor_variance: torch.Tensor, wider_variance: torch.Tensor | None,
                  cfg: GuideConfig, sigma: float) -> tuple[torch.Tensor, torch.Tensor]:
    """The envelope's anchor aim and its variance of the mean, (B, 3, H, W) and (B, 1, H, W):
    ~z^m (m = ``cfg.anchor_source``) itself, or with ``cfg.anchor_select`` k a per-pixel
    convex combination of ~z^m and the next wider ~z^(m+1) (``wider_variance`` its variance):

        w = |D|^2 / (|D|^2 + k Var(G_sigma * ~z^m)),   D = G_sigma * (~z^(m+1) - ~z^m)
        t = ~z^(m+1) + w (~z^m - ~z^(m+1)),           V_t = V_(m+1) + w (V_m - V_(m+1))

    (|D|^2 the mean over R, G, B; Var from :func:`.guard.lowpass_variance`). The wider
    estimate's low-pass is less noisy (its photon plateaus average over more photons, e.g.
    ``texture_leaks``' blotches), but carries more bandwidth bias next to caustics and light
    leaks; where the two low-passes differ by more than ~z^m's noise, that bias shows and
    the aim returns to ~z^m. Consistent: t lies between two estimates that converge to x_c.
    V_t is the same convex combination of the variances (an upper bound of t's variance by
    convexity for w fixed; w depends on the noise only through D)."""
    from .guard import gaussian_lowpass, lowpass_variance

    m = cfg.anchor_source
    if not cfg.anchor_select or m == z.shape[1]:         # off, or no wider estimate than ~z^4
        return z[:, m - 1], anchor_variance
    if wider_variance is None:
        raise ValueError("anchor_target: the guide's anchor_select needs the wider estimate's variance")
    narrow, wide = z[:, m - 1], z[:, m]
    d2 = gaussian_lowpass(wide - narrow, sigma).square().mean(1, keepdim=True)
    noise = cfg.anchor_select * lowpass_variance(anchor_variance.clamp(min=0.0), sigma)
    w = torch.where(d2 > 0, d2 / (d2 + noise).clamp(min=torch.finfo(d2.dtype).tiny), torch.zeros_like(d2))
    return torch.lerp(wide, narrow, w), torch.lerp(wider_variance, anchor_variance, w)


class Aim(NamedTuple):
    """The cascade's anchor aim (:func:`cascade_aim`): t (B, 3, H, W), its variance of the
    mean (B, 1, H, W), the four ~z^j pulled towards t (B, 4, 3, H, W), and the speckle field
    the steps left alone (:func:`speckle_field` of the buffer's own estimates, or None)."""

    t: torch.Tensor
    variance: torch.Tensor
    z: torch.Tensor
    free: torch.Tensor | None = None


def cascade_aim(z: torch.Tensor, variances: torch.Tensor, radii: torch.Tensor, cfg: GuideConfig, sigma: float,
                free: torch.Tensor | None, y: torch.Tensor | None = None, y_up: bool = True) -> Aim:
    """The anchor aim stepped on down to the narrower ~z^j (``cfg.cascade`` k), per pixel:

        t, V_t = :func:`anchor_target` (~z^m or between ~z^m and ~z^(m+1)),  m = ``cfg.anchor_source``
        for j = m-1, ..., 1:
            D = G_sigma * (t - ~z^j),   w_j = max(0, |D|^2 - k Var(G_sigma * ~z^j)) / |D|^2
            t = t + w_j (~z^j - t),    V_t = V_t + w_j (V_j - V_t)
        ~z^i' = ~z^i + p_i (t - ~z^i),  p_i = 1 - prod_{j < i} (1 - w_j)
        with ``cfg.cascade_y``, one more step, to ~y (y (B, 3, H, W)), no ~z^j pulled by it:
        t = t + w_y (~y - t),  V_t = V_t + w_y (V_y - V_t),  w_y from :func:`y_step` (down only
        with ``y_up`` False)

    z (B, 4, 3, H, W), ``variances`` and ``radii`` (B, 5, H, W) in schema order, ``free`` the
    speckle field (:func:`speckle_field`, w = 0 there: the guard's thinning makes a narrow
    low-pass dark) or None. |D|^2 is the mean over R, G, B; Var(G_sigma * ~z^j) takes the
    neighbour correlation of ~z^j's noise (``cfg.anchor_window``,
    :func:`.guard.correlated_lowpass_variance`) with V_j floored at V_i (r_i / r_j)^2 of every
    wider ~z^i: a photon estimate's variance of the mean grows as 1 / its kernel area, and a
    narrow kernel whose passes missed the rare bright photons reads a low sample variance.
    Unlike :func:`anchor_target`'s soft weight, w_j is 0 for a gap within k times the noise:
    a narrower estimate is only taken where the wider one's bandwidth bias shows.
    Why: beside a bright caustic the wide kernels gather its photons (``0001_caustic_paths``
    of ``holdout_n1024_s16``, N = 1024, pixel (67, 67): 1.40 / 1.62 / 1.98 / 6.08 / 19.3 in ~y,
    ~z^1..~z^4 against a reference of 1.68), and the guide of ~z^4, the range's upper end and
    the anchor all followed them: 3.5-4.3x the best input at every N. Measured in
    docs/RECONSTRUCTION_LOG.md (seventeenth session).
    Consistent: t and every ~z^i' are convex combinations of estimates that converge to x_c.
    """
    from .guard import estimated_lowpass_variance, gaussian_lowpass

    m, k = cfg.anchor_source, cfg.cascade
    t, vt = anchor_target(z, variances[:, m:m + 1], variances[:, m + 1:m + 2] if m < z.shape[1] else None,
                          cfg, sigma)
    t0 = t                                                # the wide estimates' aim, for y_step
    tiny = torch.finfo(z.dtype).tiny
    pulled = torch.zeros_like(z[:, :, :1])
    energy = variances.clamp(min=0.0) * radii.square()   # V_i r_i^2: V_i (r_i / r_j)^2 = V_i r_i^2 / r_j^2
    wider = energy[:, m:].amax(1, keepdim=True)           # the largest over the estimates wider than ~z^j
    for j in range(m - 1, 0, -1):                         # ~z^j, schema index j, z index j - 1
        vj = variances[:, j:j + 1].clamp(min=0.0)
        rj2 = radii[:, j:j + 1].square()
        floor = torch.where(rj2 > 0, torch.maximum(vj, wider / rj2.clamp(min=tiny)), vj)
        wider = torch.maximum(wider, energy[:, j:j + 1])
        noise = estimated_lowpass_variance(z[:, j - 1], floor, cfg.anchor_window, sigma)
        w = step_weight(gaussian_lowpass(t - z[:, j - 1], sigma).square().mean(1, keepdim=True), noise, k)
        if free is not None:
            w = torch.where(free, torch.zeros_like(w), w)
        t, vt = torch.lerp(t, z[:, j - 1], w), torch.lerp(vt, vj, w)
        pulled[:, j:] = 1.0 - (1.0 - pulled[:, j:]) * (1.0 - w[:, None])
    if cfg.cascade_y:
        if y is None:
            raise ValueError("cascade_aim: the guide's cascade_y needs ~y")
        w = y_step(t0, t, y, z, variances, radii, cfg, sigma, free, y_up)
        return Aim(torch.lerp(t, y, w), torch.lerp(vt, variances[:, :1].clamp(min=0.0), w),
                   torch.lerp(z, t[:, None], pulled), free)
    return Aim(t, vt, torch.lerp(z, t[:, None], pulled), free)


def step_weight(d2: torch.Tensor, noise: torch.Tensor, k: float) -> torch.Tensor:
    """The cascade's soft step weight ``max(0, d2 - k noise) / d2`` in [0, 1] (0 where d2 = 0):
    the share of a low-pass gap |D|^2 = ``d2`` beyond k times its noise; d2 and noise (B, 1, H, W)."""
    return ((d2 - k * noise) / d2.clamp(min=torch.finfo(d2.dtype).tiny)).clamp(0.0, 1.0)


#: :func:`y_step`: ~y's test variance is at least this share of what the ~z^j predict for it.
Y_NULL_SHARE = 0.25


def y_step(t0: torch.Tensor, t: torch.Tensor, y: torch.Tensor, z: torch.Tensor, variances: torch.Tensor,
           radii: torch.Tensor, cfg: GuideConfig, sigma: float, free: torch.Tensor | None,
           up: bool = True) -> torch.Tensor:
    """The weight w_y (B, 1, H, W) of :func:`cascade_aim`'s last step, from its aim t to ~y
    (hit point A, the narrowest kernel r_0), k = ``cfg.cascade_y``:

        D = G_sigma * (t - ~y),    w_y = max(0, |D|^2 - k Var(G_sigma * ~y)) / |D|^2
        Var from V_y' = max(sqrt(V_y max(V_y, V_0)), V_0 / 4),  V_0 = L_t max_i (V_i r_i^2 / L_i) / r_0^2

    and w_y = 0 unless the ~z^j show the same trend: G_sigma * (t_0 - ~z^1), t_0 the aim of
    the wide estimates (:func:`anchor_target`), departs from 0 by more than k times ~z^1's
    noise, with the sign of D (RGB means: ~y lies on ~z^1's side of t); 0 in the speckle
    field ``free``; with ``up`` False, also where the step would go up (mean D < 0: ~y above
    t), as :func:`.infer.buffer_aim` asks below ``cfg.cascade_y_up`` passes: a photon near the
    hit points lifts the narrow kernels most, a trend up that noise makes at few passes.
    V_0 is the variance the ~z^j predict for ~y were its mean the aim's level L_t (a photon
    estimate's variance of the mean is its level times the energy per event over its kernel
    area, V_i r_i^2 / L_i for ~z^i, L the RGB mean): a ~y whose passes missed photons reads
    both low and a low sample variance (0 where it caught none), and its own variance alone
    would have the step favour it (the glossy ``cornell-box-spotlight`` N = 256: 8x8-block
    relMSE 1.03 -> 1.44 of its best input). The trend test keeps a ~y that departs from
    estimates that agree among themselves (noise in ~y alone) from being taken.
    Why: beside a bright caustic even ~z^1 gathers its photons (``0001_caustic_paths`` of
    ``holdout_n1024_s16`` N = 64, pixel (52, 75): ~y 7.5, ~z^1..~z^4 14 / 22 / 37 / 62,
    reference 4.2; the output was 44). Measured in docs/RECONSTRUCTION_LOG.md (nineteenth
    session). Consistent: the step's aim is a convex combination of estimates that converge."""
    from .guard import estimated_lowpass_variance, gaussian_lowpass

    tiny = torch.finfo(z.dtype).tiny
    k = cfg.cascade_y
    # the ~z^j's own trend first: ~z^1 departs from t_0 beyond its noise (most pixels do not)
    v1 = variances[:, 1:2].clamp(min=0.0)
    narrow = gaussian_lowpass(t0 - z[:, 0], sigma)
    trend = narrow.square().mean(1, keepdim=True) > k * estimated_lowpass_variance(z[:, 0], v1, cfg.anchor_window,
                                                                                 sigma)
    if free is not None:
        trend &= ~free
    if not bool(trend.any()):
        return torch.zeros_like(trend, dtype=z.dtype)
    vy = variances[:, :1].clamp(min=0.0)
    level = rgb_mean(z, 2)                                       # (B, 4, H, W)
    per_event = torch.where(level > 0, variances[:, 1:].clamp(min=0.0) * radii[:, 1:].square()
                            / level.clamp(min=tiny), torch.zeros_like(level)).amax(1, keepdim=True)
    r02 = radii[:, :1].square()
    null = torch.where(r02 > 0, per_event * t.mean(1, keepdim=True).clamp(min=0.0) / r02.clamp(min=tiny),
                       torch.zeros_like(vy))
    vy_test = torch.maximum(torch.sqrt(vy * torch.maximum(vy, null)), Y_NULL_SHARE * null)
    noise = estimated_lowpass_variance(y, vy_test, cfg.anchor_window, sigma)
    gap = gaussian_lowpass(t - y, sigma)
    w = step_weight(gap.square().mean(1, keepdim=True), noise, k)
    side = gap.mean(1, keepdim=True)
    trend &= side * narrow.mean(1, keepdim=True) > 0                 # ~y on ~z^1's side of t
    if not up:
        trend &= side > 0                                            # ~y below the aim: a step down
    return torch.where(trend, w, torch.zeros_like(w))


def aim_spikes(target: torch.Tensor, eps: torch.Tensor | float, ratio: float) -> torch.Tensor:
    """The isolated bright pixels of the anchor's aim, (B, 1, H, W) bool: RGB mean above
    ``ratio`` x (the second largest of its eight neighbours' + eps), i.e. a light of one or
    two pixels; a corner or edge of a bright patch or a pixel of a thin bright line has at
    least two bright neighbours and is not one. target (B, 3, H, W), eps a scalar or
    (B, 1, 1, 1); the neighbours are looked up only where the pixel is above ``ratio`` x
    (its 3 x 3 minimum + eps), a necessary condition that few pixels meet."""
    lum = target.mean(1, keepdim=True)
    eps = torch.as_tensor(eps, dtype=lum.dtype, device=lum.device).reshape(-1, 1, 1, 1).expand(lum.shape[0], 1, 1, 1)
    spikes = lum > ratio * (window_max(lum, torch.minimum) + eps)
    h, w = lum.shape[-2:]
    dr = torch.tensor([-1, -1, -1, 0, 0, 1, 1, 1], device=lum.device)
    dc = torch.tensor([-1, 0, 1, -1, 1, -1, 0, 1], device=lum.device)
    for b in range(lum.shape[0]):                   # images of a batch (one at inference)
        rows, cols = spikes[b, 0].nonzero(as_tuple=True)
        r = (rows[:, None] + dr).clamp(0, h - 1)    # replicate padding, as the other window tests
        c = (cols[:, None] + dc).clamp(0, w - 1)
        second = lum[b, 0, r, c].topk(2, dim=1).values[:, 1]
        spikes[b, 0, rows, cols] = lum[b, 0, rows, cols] > ratio * (second + eps[b, 0, 0, 0])
    return spikes


def spike_estimate(y: torch.Tensor, z: torch.Tensor, y_variance: torch.Tensor,
                   z_variance: torch.Tensor) -> torch.Tensor:
    """The inverse-variance mean of ~y and one ~z^j, (B, 3, H, W): ``(~y V_z + ~z V_y) /
    (V_y + V_z)`` (their plain mean where both variances are 0). The two gather at
    independent hit points (A and B), so their errors are close to independent; consistent,
    as a convex combination of two estimates that converge to the truth."""
    total = y_variance + z_variance
    w = torch.where(total > 0, z_variance / total.clamp(min=torch.finfo(total.dtype).tiny),
                    torch.full_like(total, 0.5))
    return torch.lerp(z, y, w)


def window_max(x: torch.Tensor, op=torch.maximum, size: int = TERMS_WINDOW) -> torch.Tensor:
    """The maximum (``op`` = ``torch.minimum``: minimum) of ``x`` (..., H, W) over each
    pixel's ``size`` x ``size`` window (odd size; the window cut at the image's edges, as
    with replicate padding). As running extremes of shifted views, rows then columns:
    ``max_pool2d`` takes about 5x as long on a CPU (1.2 s against 0.22 s for 24 x 1280 x 720).
    Each pass writes its first shift straight into a new tensor (no copy of its source:
    about a quarter of the time for 12 x 1280 x 720)."""
    out = x
    for axis in (-1, -2):
        src = out
        n = src.shape[axis]
        out = torch.empty_like(src)
        for shift in range(1, size // 2 + 1):
            if shift >= n:
                break
            head, tail = src.narrow(axis, 0, n - shift), src.narrow(axis, shift, n - shift)
            if shift == 1:      # out_c = op(src_c, src_{c-1}) for c >= 1, src_0 at the edge ...
                op(tail, head, out=out.narrow(axis, 1, n - 1))
                out.narrow(axis, 0, 1).copy_(src.narrow(axis, 0, 1))
            else:
                op(out.narrow(axis, shift, n - shift), head, out=out.narrow(axis, shift, n - shift))
            op(out.narrow(axis, 0, n - shift), tail, out=out.narrow(axis, 0, n - shift))   # ... and src_{c+s}
        if n == 1 or size == 1:
            out.copy_(src)
    return out


def terms_share(passes: float, cfg: GuideConfig) -> float:
    """The share s = 1 / (1 + N / M) of the way :func:`terms_range` widens a render of N
    passes, M = ``cfg.terms_passes`` (0: off, s = 0)."""
    return 1.0 / (1.0 + passes / cfg.terms_passes) if cfg.terms_passes else 0.0


def terms_range(y: torch.Tensor, z: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                share: float) -> tuple[torch.Tensor, torch.Tensor]:
    """A pixel's range ``[lo, hi]`` (B, 3, H, W) widened towards the range of paper 002
    Eq. 6's terms ``t^j_{c,i} = ~y_i + ~z^j_c - ~z^j_i`` over its K x K window (K =
    :data:`TERMS_WINDOW`, replicate padding), by the share s, each end by at most the
    range's own width w = hi - lo (a ~y spike in the window would otherwise move it by the
    spike's height):

        lo' = lo + s (max(min(lo, min_{i,j} t^j_{c,i}), lo - w)^+ - lo)
        hi' = hi + s (min(max(hi, max_{i,j} t^j_{c,i}), hi + w) - hi)

    y (B, 3, H, W), z (B, 4, 3, H, W). Consistent: every term converges to the truth x_c
    (Appendix A) and w to 0, so both ends do; s itself falls with N (:func:`terms_share`).
    Why: at few passes the five estimates of a pixel share most of their photons, so its
    truth often lies outside their range; the terms bring in the neighbours' ~y, gathered
    at their own hit points, with ~z^j's difference between the two pixels (measured with
    ``benchmarks/guide_inputs.py``, ``terms 3 n16 cap``: see the README)."""
    t_lo = t_hi = None
    for zj in z.unbind(1):                  # one ~z^j at a time: image-sized temporaries, reused
        d = zj - y                          # t^j_{c,i} = ~z^j_c - d^j_i
        near = window_max(d)
        near = torch.sub(zj, near, out=near)
        t_lo = near if t_lo is None else torch.minimum(t_lo, near, out=t_lo)
        near = window_max(d, torch.minimum)
        near = torch.sub(zj, near, out=near)
        t_hi = near if t_hi is None else torch.maximum(t_hi, near, out=t_hi)
    width = hi - lo
    lo_t = torch.maximum(torch.minimum(lo, t_lo), lo - width).clamp_(min=0.0)
    hi_t = torch.minimum(torch.maximum(hi, t_hi), hi + width)
    return torch.lerp(lo, lo_t, share), torch.lerp(hi, hi_t, share)


def envelope(guide: torch.Tensor, y: torch.Tensor, z: torch.Tensor, anchor_variance: torch.Tensor,
             guard: GuardConfig, cfg: GuideConfig, scale: torch.Tensor | float = 0.0,
             wider_variance: torch.Tensor | None = None, passes: float | None = None,
             spike_variances: tuple[torch.Tensor, torch.Tensor] | None = None,
             variances: torch.Tensor | None = None, aim: Aim | None = None) -> torch.Tensor:
    """The guide held in the consistent envelope ("envelope" mode), (B, 3, H, W):

        e_c = clamp(g_c, min_k X_{k,c}, max_k X_{k,c})            per channel, X = ~y, ~z^1..~z^4
        e'  = e + a G_sigma * (t - e)                             (:func:`.guard.anchor_where_biased`)
        out = clamp(e', min_k X_{k,c}, max_k X_{k,c})

    ``guide`` (B, 4, H, W) the planes of :func:`guide_planes` (only R, G, B are used), y
    (B, 3, H, W) and z (B, 4, 3, H, W) the guarded inputs, ``anchor_variance`` (B, 1, H, W)
    the variance of the mean of ~z^m, m = ``cfg.anchor_source``, t = ~z^m or, with
    ``cfg.anchor_select``, the per-pixel aim of :func:`anchor_target` between ~z^m and
    ~z^(m+1) (``wider_variance`` the latter's variance); sigma = ``guard.anchor``
    (0: no anchor), k = ``cfg.anchor_noise``; the range widened by the guard's band h when
    h > 1; with ``cfg.y_spike`` the range of the ~z^j alone where ~y is a lone spike
    (:func:`lone_y_spikes`, eps = the guard's floor x ``scale``, the image's radiance scale,
    a float or (B, 1, 1, 1)); with ``cfg.anchor_window`` the anchor's noise test takes the
    correlation of ~z^m's noise between neighbours; with ``cfg.anchor_settled`` r0 the anchor
    acts only where its low-pass is settled (its standard deviation below r0 times its level);
    with ``cfg.terms_passes`` the guide held in the range widened towards Eq. 6's terms
    (:func:`terms_range`) for a render of ``passes`` N, and the anchored image then held in
    ``[min(lo, e), max(hi, e)]``, [lo, hi] the five estimates' range and e that held guide; with ``cfg.anchor_spikes`` R the isolated bright pixels of
    the aim t (:func:`aim_spikes`, eps as for ``y_spike``) take part in the anchor with t = e
    (their gap is not spread into their neighbours) and are set to the inverse-variance mean
    of ~y and ~z^4 (:func:`spike_estimate`, ``spike_variances`` = (V_y, V_4), each (B, 1, H, W));
    with ``cfg.z_spike`` the range of ~y alone where the ~z^j are a lone spike over a settled ~y
    (:func:`lone_z_spikes`, ``variances`` (B, 5, H, W) the five variances of the mean);
    with ``cfg.anchor_free`` the anchored value of a pixel whose five estimates are all
    unsettled (:func:`speckle_field`) held in its range widened to the 5 x 5 medians of its
    ends (:func:`speckle_range`), so that a speckle field keeps its mean, while a firefly in
    all five estimates is not lifted further (``water_caustic`` N = 256 with the anchored
    value unclamped: 0.63 -> 0.69 of its best input from one such pixel) and a light beside
    the pixel does not widen it (``0164_bright_emitters`` N = 4 with the Gaussian mean of
    the ends: 0.20 -> 51).
    With ``cfg.range_sigma`` the range also holds each estimate's own noise interval
    (:func:`noise_range`, ``variances`` needed): at many passes the five estimates err together.
    With ``aim`` (:func:`cascade_aim`, ``cfg.cascade``) the anchor aims at its t, every
    range is that of ~y and its pulled ~z^j, and the speckle field is the aim's (that of
    the buffer's own estimates).
    Consistent there too: the anchored value converges (the held guide does, and the
    anchor's correction, a fixed blur of ``t - e``, goes to 0), and the widened range
    contains [lo, hi], whose ends converge to the truth.
    Why: OIDN takes a small bright light (seen directly or through a specular chain) for a
    firefly and flattens it; the anchor then spread the light's whole gap over its sigma,
    lifting a ring of neighbours to the top of their ranges (``0021_caustic_paths``: all of
    that image's excess over its best input lay within 4 px of one such pixel).
    Consistent: the five estimates of pixel c converge to its truth x_c, so does anything
    clamped between them (the guard's output band), and the anchor's correction vanishes.
    Measured (``benchmarks/bench_guide.py``, ``envelope`` variants) against Eq. 6 with the
    guide as prior: see the module docstring and the README.
    Why it can beat Eq. 6 with the same guide: the softmax over the 4 K^2 terms near g
    averages their noise (and weighs them by the RGB mean alone), while the clamp returns g
    itself wherever the pixel's estimates leave room for it.
    """
    from .guard import anchor_where_biased, band_bounds

    if aim is not None:
        z = aim.z
    spikes = y_spike_mask(y, z, cfg, guard, scale)
    lo, hi = band_bounds(y, z, guard.band if guard.enabled and guard.band else 1.0, spikes)
    if cfg.range_sigma:
        if variances is None:
            raise ValueError("envelope: the guide's range_sigma needs the five variances of the mean")
        lo, hi = noise_range(y, z, variances, lo, hi, cfg.range_sigma, rel=cfg.range_sigma_rel, y_out=spikes,
                             width=cfg.range_sigma_width, isolated=cfg.range_sigma_isolated)
    z_out = z_spike_mask(y, z, variances, cfg, guard, scale)
    if z_out is not None:             # a zero-width range: terms_range cannot widen it either
        lo, hi = torch.where(z_out, y, lo), torch.where(z_out, y, hi)
    if cfg.terms_passes:
        if passes is None:
            raise ValueError("envelope: the guide's terms_passes needs the render's pass count")
        wide_lo, wide_hi = terms_range(y, z, lo, hi, terms_share(passes, cfg))
        held = torch.minimum(torch.maximum(guide[:, :N_RGB], wide_lo), wide_hi)
        # the widened room is the guide's, not the anchor's: the anchor's correction stays
        # within the five estimates' range or the held guide (its spread of a light's gap
        # would otherwise lift a ring of neighbours further, to the widened top)
        lo, hi = torch.minimum(lo, held), torch.maximum(hi, held)
    else:
        held = torch.minimum(torch.maximum(guide[:, :N_RGB], lo), hi)
    if guard.enabled and guard.anchor > 0:
        target, target_variance = (aim.t, aim.variance) if aim is not None else \
            anchor_target(z, anchor_variance, wider_variance, cfg, guard.anchor)
        spikes = None
        if cfg.anchor_spikes:
            if spike_variances is None:
                raise ValueError("envelope: the guide's anchor_spikes needs the variances of ~y and ~z^4")
            spikes = aim_spikes(target, guard.floor * scale, cfg.anchor_spikes)
            target = torch.where(spikes, held, target)
        held = anchor_where_biased(held, target, target_variance, guard.anchor, cfg.anchor_noise,
                                   cfg.anchor_window, cfg.anchor_settled)
        if spikes is not None:
            held = torch.where(spikes, spike_estimate(y, z[:, -1], *spike_variances), held)
        free = aim.free if aim is not None else speckle_field(y, z, variances, cfg.anchor_free,
                                                              dark_level(cfg, guard, scale))
        if free is not None:
            lo, hi = speckle_range(lo, hi, free)
        anchored, held = held, torch.minimum(torch.maximum(held, lo), hi)
        if cfg.redistribute:
            held = redistribute(anchored, held, lo, hi, cfg.redistribute)
    return held


def noise_range(y: torch.Tensor, z: torch.Tensor, variances: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                kappa: float, rel: float = 0.0, y_out: torch.Tensor | None = None,
                width: float = 0.0, isolated: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """A pixel's range ``[lo, hi]`` widened to hold each estimate's own noise interval,
    (B, 3, H, W) each:

        lo' = min(lo, max(0, min_k (X_k - kappa s_k))),   hi' = max(hi, max_k (X_k + kappa s_k))
        s_k = sqrt(V_k)  where sqrt(V_k) <= rel |X_k|  (rel > 0; |.| the RGB mean), else 0

    X = ~y, ~z^1..~z^4 (y (B, 3, H, W), z (B, 4, 3, H, W)), ``variances`` (B, 5, H, W) their
    variances of the mean; ~y takes no part where ``y_out`` (B, 1, H, W) marks it a lone spike.
    With ``width`` > 0 only pixels whose bare range (RGB mean of hi - lo) is at most ``width``
    x sqrt(V) of the widest estimate ~z^4 are widened: estimates that agree within their noise
    err together, while a range wider than that holds a feature's bandwidth bias (a caustic, where
    NL-means' smoothing is a bias the bare range stops: the built-in ``cornell_caustics`` at N = 64,
    0.31 -> 0.35 of its best input widened everywhere, 0.31 -> 0.32 with ``width`` 3).
    With ``isolated`` > 0 pixels where ~z^4's RGB mean exceeds ``isolated`` x its 3 x 3 median
    keep the bare range: the sparkle test of ``rel`` made per pixel by its neighbours, so a
    smooth glossy lobe with a noisy ~y is widened while a rare path's lone bright pixel is not.
    Why: at many passes a pixel's five estimates gather the same photons, so they err together
    and their range is narrower than their noise; the clamp then hands that noise back to a
    guide that had averaged it away (``holdout_s23`` at N = 256 against its deep references:
    the guide alone 0.16 / 0.15 / 0.13 of the best input's error in noise on ``glossy``,
    ``bright_emitters``, ``glossy_interreflection``, the clamped output 0.24 / 0.27 / 0.21). The
    test on ``rel`` keeps the bare range where an estimate is a rare path's sparkle (relative
    sd ~0.4), the very pixels NL-means takes for noise while the truth is that bright.
    Consistent: s_k -> 0 as the passes grow, so [lo', hi'] shrinks onto the estimates' own
    range, whose ends converge to the truth."""
    x = torch.cat([y[:, None], z], 1)                                  # (B, 5, 3, H, W)
    s = variances.clamp(min=0.0).sqrt()[:, :, None]                    # (B, 5, 1, H, W)
    if rel > 0:
        s = s * (s <= rel * x.mean(2, keepdim=True).abs())
    s = s.mul_(kappa)
    low = x - s
    high = x.add_(s)                                # x is a copy (the cat): no third 5-estimate tensor
    if y_out is not None:                       # a lone ~y spike: ~z^j's own ends stand in for it
        low[:, 0] = torch.where(y_out, low[:, 1:].amin(1), low[:, 0])
        high[:, 0] = torch.where(y_out, high[:, 1:].amax(1), high[:, 0])
    new_lo, new_hi = torch.minimum(lo, low.amin(1).clamp(min=0.0)), torch.maximum(hi, high.amax(1))
    if width > 0:
        narrow = (hi - lo).mean(1, keepdim=True) <= width * variances[:, -1:].clamp(min=0.0).sqrt()
        new_lo, new_hi = torch.where(narrow, new_lo, lo), torch.where(narrow, new_hi, hi)
    if isolated > 0:
        from .guard import median3x3, rgb_mean

        level = rgb_mean(z[:, -1], 1, keepdim=True)
        alone = level > isolated * median3x3(level)
        new_lo, new_hi = torch.where(alone, lo, new_lo), torch.where(alone, hi, new_hi)
    return new_lo, new_hi


def redistribute(anchored: torch.Tensor, held: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
                 sigma: float) -> torch.Tensor:
    """What the clamp of ``anchored`` into ``[lo, hi]`` took, given back to the pixels
    around within their own ranges, (B, 3, H, W) per channel (``held`` the clamped image):

        D = G_sigma * (anchored - held)                      the clamp's local loss (signed)
        U = min(hi - held, L),  W = min(held - lo, L),  L = G_sigma * held
        out = held + U min(1, D / G_sigma * U)               where D > 0
        out = held - W min(1, -D / G_sigma * W)              where D < 0

    a pixel's room capped at the local level L (uncapped, a firefly's
    room drew the loss into it: ``0086_glossy_interreflection`` N = 4, 0.28 -> 0.88 of its
    best input). Each pixel takes a share of the loss in proportion to its room, so the sum over a
    neighbourhood moves by about D's, as far as the room allows. Why: in a field of photon
    speckles or at a sharp light edge the clamp is one-sided (a pixel whose estimates all
    missed is pushed to 0, one that caught a photon is barely lifted), so the envelope came
    out darker than every one of its inputs at few passes (``data/v3_cpu``, N = 4: median
    image mean 0.98 of the reference's, ``0023_texture_leaks`` 0.75 against 0.93-0.96).
    Consistent: the output stays in ``[lo, hi]``, whose ends converge to the truth.
    Not shipped (opt-in): it trades plain relMSE for 8x8-block relMSE (``data/v3_cpu``,
    sigma 1.5: 0.620 -> 0.627 and 1.235 -> 1.181 of the best input; scaled 0.403 -> 0.423;
    study 0.414 -> 0.419 and 1.152 -> 1.096; ``benchmarks/results/guide_s13_redis_cap``)."""
    from .guard import gaussian_lowpass

    tiny = torch.finfo(held.dtype).tiny
    loss = gaussian_lowpass(anchored - held, sigma)
    level = gaussian_lowpass(held, sigma)
    up, down = torch.minimum(hi - held, level), torch.minimum(held - lo, level)
    lift = up * (loss / gaussian_lowpass(up, sigma).clamp(min=tiny)).clamp(0.0, 1.0)
    drop = down * (-loss / gaussian_lowpass(down, sigma).clamp(min=tiny)).clamp(0.0, 1.0)
    return held + lift - drop


def speckle_field(y: torch.Tensor, z: torch.Tensor, variances: torch.Tensor | None, r: float,
                  dark: torch.Tensor | float = 0.0) -> torch.Tensor | None:
    """Where every one of a pixel's five estimates is unsettled at ``r`` (sqrt(V)/mean >= r,
    or a mean of 0: :func:`.guard.settled_mask`) while the widest, ~z^4, caught more than
    ``dark`` (a float or (B, 1, 1, 1)), (B, 1, H, W) bool; None for r = 0 (off). y (B, 3, H,
    W), z (B, 4, 3, H, W), ``variances`` (B, 5, H, W). A pixel whose widest gather stayed
    empty for N passes is dark, not a speckle (``0178_indirect``: a black region beside a
    bright one); so is one whose ~z^4 caught only a negligible photon (``dark`` > 0:
    ``holdout_n1024_s16`` ``0000_bright_emitters`` N = 16, pixel (113, 53) beside a light:
    all five estimates below 1e-8, reference 1.0, the range widened to the light's 5 x 5
    median let the anchor lift it to 161).

    Such a pixel lies in a field of photon speckles (the literature ``cornell-box``'s glossy
    floor at N = 64: most pixels' five estimates are 0 or one event), where the range of its
    own estimates says little about its mean: clamping a smooth value into it took energy
    from every pixel whose estimates all missed and gave little back, so that image's dark
    8x8 blocks came out 1.5-4x too dark and its 8x8-block relMSE was 2.1x that of ~z^4.
    :func:`envelope` widens such a pixel's range to its neighbourhood's (:func:`speckle_range`).
    """
    from .guard import settled_mask

    if not r:
        return None
    if variances is None:
        raise ValueError("the guide's anchor_free needs the five variances of the mean")
    free = z[:, -1].amax(1, keepdim=True) > dark
    free &= ~settled_mask(y.mean(1, keepdim=True), variances[:, :1], r)
    free &= ~settled_mask(rgb_mean(z, 2), variances[:, 1:], r).any(1, keepdim=True)
    return free


#: :func:`speckle_range`'s window (pixels, odd): about the anchor's blur (sigma 1.5 px).
SPECKLE_WINDOW = 5


def speckle_range(lo: torch.Tensor, hi: torch.Tensor, free: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The range ``(lo, hi)`` (B, 3, H, W) widened at the speckle pixels ``free`` (B, 1, H, W)
    to the :data:`SPECKLE_WINDOW` medians of its ends, ``[min(lo, med lo), max(hi, med hi)]``
    per channel; elsewhere unchanged. A median, not a mean: the few bright pixels of a window
    (a light, a firefly beside a dark pixel: ``0028_bright_emitters`` N = 64 with a Gaussian
    mean of the speckle pixels' ends, 0.14 -> 0.91 of its best input) do not set it. Only the
    speckle pixels' windows are gathered."""
    from .guard import window_median

    b, _, r, c = free.nonzero(as_tuple=True)
    if not b.numel():
        return lo, hi
    idx = (b, torch.zeros_like(b), r, c)
    lo, hi = lo.clone(), hi.clone()
    lo[b, :, r, c] = torch.minimum(lo[b, :, r, c], window_median(lo[:, None], idx, SPECKLE_WINDOW))
    hi[b, :, r, c] = torch.maximum(hi[b, :, r, c], window_median(hi[:, None], idx, SPECKLE_WINDOW))
    return lo, hi


#: Bound of the learned log-temperature: the prior is at most e^4 ~ 55x sharper or flatter.
TAU_LIMIT = 4.0


def net_channels(cfg: GuideConfig, k: int) -> int:
    """Output channels of the network for window K: the 4 K^2 logits (their correction
    to the prior when the guide is on), plus the log-temperature with ``temperature``."""
    return N_CORRELATED * k * k + (1 if cfg.temperature else 0)


def guided_logits(net: torch.Tensor, y: torch.Tensor, z: torch.Tensor, guide: torch.Tensor | None, k: int,
                  cfg: GuideConfig) -> torch.Tensor:
    """Eq. 6's logits from the network's output ``net`` (B, :func:`net_channels` of the
    model's ``cfg``, H, W) and the guide planes: ``prior + correction``, or with
    ``cfg.temperature`` ``prior * exp(-tau) + correction``, tau (the last channel) clamped
    to [-:data:`TAU_LIMIT`, :data:`TAU_LIMIT`]. tau = 0 (the zero-initialised head) is the
    plain prior; tau > 0 flattens it where the network trusts the guide less (more terms
    averaged), tau < 0 sharpens it. Without ``guide`` (switched off) the correction alone.
    Any logits keep Eq. 6 consistent."""
    correction = net[:, :-1] if cfg.temperature else net
    if guide is None:
        return correction
    prior = prior_logits(y, z, guide, k)                 # a new tensor: summed into in place
    if cfg.temperature:
        prior = prior * torch.exp(-net[:, -1:].clamp(-TAU_LIMIT, TAU_LIMIT))
    return prior.add_(correction)


def guide_channels(guide: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The guide as network input (``FeatureConfig.guide``): log1p(g / s), (B, 3, H, W),
    scale-free like the ``scale_free`` estimates (s = the image's radiance scale, (B,))."""
    s = scale.to(guide.dtype).view(-1, 1, 1, 1)
    return torch.log1p(guide[:, :N_RGB].clamp(min=0) / torch.where(s > 0, s, torch.ones_like(s)))


def prior_logits(y: torch.Tensor, z: torch.Tensor, guide: torch.Tensor, k: int) -> torch.Tensor:
    """The guide's prior logits in the combiner's layout, (B, 4 K^2, H, W).

    y (B, 3, H, W), z (B, 4, 3, H, W) as :func:`.combine.combine` gets them, ``guide``
    (B, 4, H, W) from :func:`guide_planes` (cropped like y). Channel ``4 (a K + b) + j``
    is ``-|t^j_{c,i} - g_c|^2 / (2 sigma_c^2)`` for the term at offset (a - K//2, b - K//2),
    the terms padded as the combiner pads them (replicate), ``t - g`` evaluated as
    ``(y_i - z^j_i) + (z^j_c - g_c)`` (the combiner's terms up to rounding).
    """
    b, _, h, w = y.shape
    dpad = _padded_differences(y, z, k // 2).view(b, N_CORRELATED, N_RGB, h + k - 1, w + k - 1)
    z_minus_g = z - guide[:, :N_RGB].unsqueeze(1)                      # (B, 4, 3, H, W)
    scale = -0.5 / (N_RGB * guide[:, N_RGB:].square())                 # the mean over RGB folded in
    out = torch.empty(b, N_CORRELATED * k * k, h, w, dtype=y.dtype, device=y.device)
    t = torch.empty_like(z)                                            # one buffer for every offset
    for row in range(k):
        for col in range(k):
            # t^j_{c,i} - g_c = (y_i - z^j_i) + (z^j_c - g_c) at this offset, in place
            torch.add(dpad[..., row:row + h, col:col + w], z_minus_g, out=t)
            base = N_CORRELATED * (row * k + col)
            t.square_()
            # the sum over R, G, B as two adds (torch.sum(out=) first zero-fills its output)
            torch.add(t[:, :, 0], t[:, :, 1], out=out[:, base:base + N_CORRELATED]).add_(t[:, :, 2])
    return out.mul_(scale)
