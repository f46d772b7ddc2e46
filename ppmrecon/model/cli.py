"""``ppmrecon-denoise``: buffer file -> consistent learned reconstruction (paper 002 Eq. 6).

    ppmrecon-denoise INPUT.exr [INPUT.exr | 'PATTERN*.exr' ...] [--model CKPT]
                     [--output OUT.exr] [--tile N] [--weights-layers] [--device cpu|cuda]
                     [--threads N] [--guard model|on|off] [--guide model|on|off]
                     [--guide-quality high|balanced|fast] [--guide-mode envelope|weights] [--quiet]
    ppmrecon-denoise --init-checkpoint CKPT [--preset tiny|small|paper|FILE.json]

The output is a plain R,G,B EXR (default: ``INPUT_denoised.exr`` next to the input),
written atomically. Several inputs (files or glob patterns, e.g. the snapshots of one
render) are denoised in one call with the model loaded once; a pattern leaves out files
that are themselves ``*_denoised.exr`` outputs; ``--weights-layers`` adds ``weight.z1 .. weight.z4``, the summed
combination weight of each ~z^j (paper 002 Fig. 6). Without ``--model`` the shipped
default model is used if the package has one (``ppmrecon/data/models/default.pt``).
``--init-checkpoint`` writes an untrained network, for trying the pipeline end to end
before a model has been trained. ``--guard`` switches the consistent firefly guard
(:mod:`ppmrecon.model.guard`) on or off; by default it is on (measured on renders it was
not tuned on: benchmarks/results/guard.md). ``--guide`` likewise switches the denoiser guide
(:mod:`ppmrecon.model.guide`: OIDN's image of ~z^4, never at the cost of the output's
consistency); on by default. ``--guide-mode`` says how it enters: ``envelope`` (the shipped
model's: OIDN's image held inside the range of each pixel's five estimates, no network)
or ``weights`` (the prior of Eq. 6's weights, corrected by the network).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Callable, Mapping, Sequence

import torch

from ..buffers import ESTIMATES, read_buffers, write_rgb
from ..cli_common import ArgumentParser, Progress, expand_paths, nonnegative_float, positive_int, run_main
from ..errors import UsageError
from . import checkpoint
from .features import FeatureConfig
from .guard import DEFAULT_ON, GuardConfig
from .guide import ALBEDO_CHANNELS, DEFAULT_GUIDE, DENOISERS, ENVELOPE_MODES, GUIDE_MODES, NLM_MAX_RADIUS, OIDN_QUALITIES, GuideConfig
from .infer import denoise
from .kpn import DEFAULT_PRESET, load_preset, parameter_count, preset_names

PROG = "ppmrecon-denoise"
WEIGHT_LAYER = "weight"
H_DENOISER = "ppmrecon.denoiser"
H_MODEL = "ppmrecon.model"
H_DENOISE_SECONDS = "ppmrecon.denoise_seconds"
H_GUARD = "ppmrecon.guard"
H_ANCHOR = "ppmrecon.guard.anchor"
H_GUIDE = "ppmrecon.guide"



#: The guide's numeric settings as options: (flag, metavar, GuideConfig key, help). The
#: API's keyword for each is the flag without its dashes (``guide_y_weight=``).
GUIDE_NUMBERS: tuple[tuple[str, str, str, str], ...] = (
    ("--guide-y-weight", "F", "y_weight",
     "weight of OIDN's image of ~y (hit point A) in the guide, F >= 0: mixed with OIDN's image of ~z^4 by the "
     "inverse of their inputs' local variances, ~y's times F; 0 = ~z^4's alone (default: the checkpoint's; the "
     "shipped model's 2)"),
    ("--guide-y-spike", "R", "y_spike",
     "envelope modes: leave ~y out of a pixel's range where it is a lone spike, R x above every ~z^j of the "
     "pixel and its own 3 x 3 median; 0 = off, else R > 1 (default: the checkpoint's; the shipped model's 8)"),
    ("--guide-z-spike", "R", "z_spike",
     "envelope modes: hold a pixel at ~y where its four ~z^j are a lone spike over a settled ~y: each more than "
     "R x above ~y, none settled (sqrt(V)/mean below the guard's r0) while ~y is (light hit point B's eye path alone "
     "saw once); 0 = off, else R > 1 (default: the checkpoint's)"),
    ("--guide-anchor-free", "R", "anchor_free",
     "envelope modes: where ~y and every ~z^j of a pixel are unsettled at R (sqrt(V)/mean >= R, or 0: a photon "
     "speckle field) while ~z^4 caught a photon, hold the anchored value in its range widened to the 5 x 5 "
     "medians of its ends instead of the pixel's own; 0 = off (default: the checkpoint's)"),
    ("--guide-redistribute", "S", "redistribute",
     "envelope modes: give what the final clamp into each pixel's range took back to the pixels around, over a "
     "Gaussian of S px, each within its own range (lower low-frequency error, a little higher relMSE; README); "
     "0 = off (default: the checkpoint's; the shipped model's 0)"),
    ("--guide-anchor-settled", "R", "anchor_settled",
     "envelope modes: the anchor acts only where its own low-pass is settled, its standard deviation below R x "
     "its level (helps next to small bright emitters, costs the glossy Cornell box's low frequencies; README); "
     "0 = off (default: the checkpoint's; the shipped model's 0)"),
    ("--guide-anchor-select", "K", "anchor_select",
     "envelope modes: aim the anchor per pixel between its ~z^m (the shipped ~z^3) and the wider ~z^(m+1), at "
     "the wider one where their low-passes agree within K x ~z^m's noise; 0 = ~z^m alone (default: the "
     "checkpoint's; the shipped model's 4)"),
    ("--guide-terms-passes", "M", "terms_passes",
     "envelope modes: widen the range each pixel's guide is held in towards that of Eq. 6's terms over its "
     "3 x 3 window by the share 1 / (1 + N / M) for a render of N passes, each end by at most the range's "
     "width (the anchor keeps to the estimates' range or the held guide); 0 = off (default: the checkpoint's)"),
    ("--guide-anchor-spikes", "R", "anchor_spikes",
     "envelope modes: keep the anchor from spreading the gap of a light of one or two pixels in its aim (RGB "
     "mean above R x its second brightest neighbour's: a small light OIDN flattened) into its neighbours, "
     "and set that pixel to the inverse-variance mean of ~y and ~z^4; 0 = off, else R > 1 (default: the "
     "checkpoint's)"),
    ("--guide-y-found", "S", "y_found",
     "scale ~y's share in the guide by the share of pixels, over a Gaussian of S px, where ~y is not sparser "
     "than ~z^4 (under one photon event, mean^2 / variance < 1, where ~z^4 has more): a photon-starved ~y "
     "reads black with variance 0; 0 = off (default: the checkpoint's)"),
    ("--guide-cascade", "K", "cascade",
     "envelope modes: step the anchor's aim on down to ~z^2 and ~z^1 per pixel where its low-pass departs from "
     "the narrower estimate's by more than K x that one's noise (a wide kernel's bandwidth bias beside a bright "
     "caustic), pull the wider ~z^j of the pixel's range towards it, and give OIDN that aim in place of ~z^4; "
     "0 = off (default: the checkpoint's)"),
    ("--guide-cascade-passes", "N", "cascade_passes",
     "envelope modes: run renders of fewer than N passes without the cascade (its noise test rests on a "
     "sample variance over the passes); 0 = at every N (default: the checkpoint's)"),
    ("--guide-cascade-y", "K", "cascade_y",
     "envelope modes, with the cascade: take its aim one step further, to ~y (hit point A, the narrowest "
     "kernel), where their low-passes differ by more than K x ~y's noise and ~z^1 departs from the wide "
     "estimates the same way (beside a bright caustic even ~z^1 gathers its photons); 0 = off (default: the "
     "checkpoint's)"),
    ("--guide-cascade-y-up", "M", "cascade_y_up",
     "envelope modes, with --guide-cascade-y: renders of fewer than M passes take its step to ~y down only (a "
     "photon near the hit points lifts the narrow kernels most, which over few passes reads as the same trend "
     "up); 0 = up and down at every N (default: the checkpoint's; the shipped model's 64)"),
    ("--guide-nlm-k", "K", "nlm_k",
     "with --guide-denoiser nlm or nlm_source: the patch distance's tolerance in units of the noise, K > 0 "
     "(default: the checkpoint's; the shipped model's 0.8, used below --guide-nlm-joint-passes and from "
     "--guide-nlm-y-passes)"),
    ("--guide-nlm-radius", "R", "nlm_radius",
     f"with --guide-denoiser nlm or nlm_source: the search window's half width in px, a whole number 1..{NLM_MAX_RADIUS} "
     "(patches of half width R // 2; the time grows as R^2; default: the checkpoint's, 3)"),
    ("--guide-nlm-y-passes", "M", "nlm_y_passes",
     "with --guide-denoiser nlm_source: renders of at least M passes denoise ~y by its own NL-means too (and the "
     "joint filter stops there), OIDN below (OIDN smooths detail a many-pass ~y resolves); 0 = never (default: "
     "the checkpoint's; the shipped model's 512)"),
    ("--guide-nlm-y-k", "K", "nlm_y_k",
     "NL-means' tolerance K for ~y (with nlm, or nlm_source and --guide-nlm-y-passes); 0 = --guide-nlm-k "
     "(default: the checkpoint's; the shipped model's 1)"),
    ("--guide-nlm-joint-passes", "M", "nlm_joint_passes",
     "with --guide-denoiser nlm or nlm_source, where the guide uses ~y: renders of at least M passes (and fewer "
     "than --guide-nlm-y-passes) denoise the source and ~y by one NL-means with joint weights (their noise is "
     "independent); 0 = never (default: the checkpoint's; the shipped model's 16)"),
    ("--guide-nlm-joint-k", "K", "nlm_joint_k",
     "the joint NL-means' tolerance K; 0 = --guide-nlm-k (default: the checkpoint's; the shipped model's 0.7)"),
    ("--guide-anchor-free-dark", "D", "anchor_free_dark",
     "with --guide-anchor-free: a pixel whose widest estimate ~z^4 reads at most D x the guard's floor x the "
     "image's scale is dark, not a photon speckle, and keeps its own range; 0 = only an empty ~z^4 (default: the "
     "checkpoint's; the shipped model's 0.1)"),
    ("--guide-nlm-albedo", "F", "nlm_albedo",
     "with --guide-denoiser nlm or nlm_source: NL-means also measures each pair of pixels on the images divided "
     "by the albedo (its RGB mean plus --guide-nlm-albedo-eps), counted F times, and keeps the smaller distance "
     "(a texture no longer stops the averaging; a highlight or caustic over it keeps the plain distance); 0 = off "
     "(default: the checkpoint's)"),
    ("--guide-nlm-albedo-eps", "E", "nlm_albedo_eps",
     "with --guide-nlm-albedo: what is added to the albedo before dividing by it, E > 0 (default: the "
     "checkpoint's, 0.05)"),
    ("--guide-range-sigma", "K", "range_sigma",
     "envelope modes: widen each pixel's range to hold every estimate +- K times its own standard deviation of "
     "the mean (at many passes the five estimates err together and their bare range hands their noise back to "
     "the guide); 0 = off (default: the checkpoint's)"),
    ("--guide-range-sigma-rel", "R", "range_sigma_rel",
     "with --guide-range-sigma: widen only estimates whose standard deviation is at most R x their level (a "
     "rare path's sparkle keeps its bare range); 0 = every estimate (default: the checkpoint's)"),
    ("--guide-range-sigma-width", "W", "range_sigma_width",
     "with --guide-range-sigma: widen only pixels whose bare range is at most W x the widest estimate's standard "
     "deviation (a wider range holds a feature's bandwidth bias, a caustic's); 0 = every pixel (default: the "
     "checkpoint's)"),
    ("--guide-range-sigma-isolated", "F", "range_sigma_isolated",
     "with --guide-range-sigma: no widening where the widest estimate is above F x its own 3 x 3 median (an "
     "isolated sparkle keeps its bare range); 0 = no test (default: the checkpoint's)"),
    ("--guide-y-empty", "S", "y_empty",
     "scale ~y's share in the guide by the share of pixels, over a Gaussian of S px, where ~y did not read 0 "
     "while ~z^4 rests on more than one photon event (a ~y that caught nothing reads black with variance 0); "
     "0 = off (default: the checkpoint's; the shipped model's 3)"),
)


def build_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Denoise a ppmrecon buffer file with the consistent kernel-predicting combiner\n"
                    "(Choi & Moon 2021): the output stays a convex combination of terms that\n"
                    "converge to the true radiance, whatever the network predicts.",
        epilog="examples:\n"
               "  ppmrecon-denoise scene.exr --model run/model.pt\n"
               "  ppmrecon-denoise scene.exr --model run/model.pt -o clean.exr --weights-layers\n"
               "  ppmrecon-denoise --init-checkpoint untrained.pt --preset tiny")
    p.add_argument("inputs", nargs="*", metavar="INPUT.exr",
                   help="buffer file(s) written by ppmrecon-render; several files or quoted glob patterns "
                        "(e.g. 'out_p*.exr') are denoised in one call, loading the model once")
    p.add_argument("--model", metavar="CKPT",
                   help="model checkpoint (.pt) from ppmrecon-train (default: the model shipped with "
                        "ppmrecon, if installed)")
    p.add_argument("--output", "-o", metavar="OUT.exr",
                   help="output RGB EXR, for a single input (default: INPUT_denoised.exr next to each input)")
    p.add_argument("--tile", type=positive_int, metavar="N",
                   help="tile side in pixels (default: automatic, bounded memory)")
    p.add_argument("--weights-layers", action="store_true",
                   help="also write weight.z1..weight.z4, the summed weight of each ~z^j")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu", help="torch device (default: cpu)")
    p.add_argument("--threads", type=positive_int, metavar="N",
                   help="CPU threads; tiles are denoised side by side (default: all cores)")
    p.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto",
                   help="network precision; auto = bfloat16 on CPUs with native bf16 (AMX/AVX512-BF16), "
                        "else float32. The combiner is always float32")
    p.add_argument("--guard", choices=("model", "on", "off"), default=None,
                   help="consistent firefly guard: replace statistical outliers of each input by "
                        "their 3x3 median and keep the output within its five inputs; 'on' (default; "
                        "the checkpoint's guard settings if it has them), 'model' = as the checkpoint "
                        "was trained, 'off'; with --init-checkpoint, 'on' stores it in the new model "
                        "(default there: off)")
    p.add_argument("--guide", choices=("model", "on", "off"), default=None,
                   help="denoiser guide: weights that pull the combination towards OIDN's image of "
                        "~z^4 (pyoidn), still a convex combination of consistent terms; 'on' (default; "
                        "the checkpoint's guide settings if it has them), 'model' = as the checkpoint "
                        "was trained, 'off'; with --init-checkpoint, 'on' stores it in the new model "
                        "(default there: off)")
    p.add_argument("--guide-mode", choices=GUIDE_MODES, default=None,
                   help="how the guide enters: 'envelope' = OIDN's image held inside the range of each "
                        "pixel's five estimates (no network), 'chooser' = a learned per-pixel mix of the "
                        "envelope and other images held in that range (a checkpoint trained with "
                        "`ppmrecon-train chooser`), 'weights' = the prior of Eq. 6's weights, "
                        "corrected by the network (default: the checkpoint's)")
    p.add_argument("--guide-quality", choices=OIDN_QUALITIES, default=None,
                   help="OIDN's quality mode for the guide (default: the checkpoint's, 'fast')")
    p.add_argument("--guide-denoiser", choices=DENOISERS, default=None,
                   help="what denoises the guide's images: 'oidn' (OIDN for both), 'nlm' = NL-means "
                        "with the patch distance in units of each pixel's noise (Rousselle et al. 2012) for "
                        "both the source and ~y, 'nlm_source' = NL-means for the source, OIDN for ~y "
                        "(default: the checkpoint's; the shipped model's nlm_source): NL-means keeps detail "
                        "the noise does not hide, where OIDN smooths it (README)")
    for flag, metavar, _, text in GUIDE_NUMBERS:
        p.add_argument(flag, type=float, default=None, metavar=metavar, help=text)
    p.add_argument("--guide-nlm-albedo-channels", choices=ALBEDO_CHANNELS, default=None,
                   help="with --guide-nlm-albedo: divide by the albedo's RGB mean ('mean') or each channel by its "
                        "own albedo ('rgb': a texture of two hues divided out too) (default: the checkpoint's)")
    p.add_argument("--anchor", type=nonnegative_float, metavar="SIGMA",
                   help="with the guard on: width (pixels) of the low-frequency anchor to ~z^4, "
                        "0 = off (default: the guard's, 1.5)")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar or summary")
    g = p.add_argument_group("making an untrained model")
    g.add_argument("--init-checkpoint", metavar="CKPT",
                   help="write a freshly initialised model to CKPT and exit (takes no INPUT)")
    g.add_argument("--preset", default=DEFAULT_PRESET, metavar="NAME",
                   help=f"architecture for --init-checkpoint: {', '.join(preset_names())} or a .json "
                        f"file (default: {DEFAULT_PRESET})")
    g.add_argument("--seed", type=int, default=0, help="initialisation seed (default: 0)")
    g.add_argument("--radius-features", action="store_true", help="network also sees the 5 bandwidths")
    g.add_argument("--pass-feature", action="store_true", help="network also sees the pass count")
    g.add_argument("--scale-free-features", action="store_true",
                   help="radiance over the image's scale and relative variances (unit-free inputs)")
    g.add_argument("--outlier-features", action="store_true",
                   help="network also sees how the five estimates disagree (6 channels)")
    return p


DENOISED_SUFFIX = "_denoised"


def default_output(path: Path) -> Path:
    """``scene.exr`` -> ``scene_denoised.exr`` in the same folder."""
    return path.with_name(f"{path.stem}{DENOISED_SUFFIX}.exr")


def expand_inputs(items: Sequence[str]) -> list[Path]:
    """Input arguments -> buffer files (see :func:`.cli_common.expand_paths`); patterns
    leave out ``*_denoised.exr`` outputs of earlier runs."""
    return expand_paths(items, "buffer file", exclude=lambda p: p.stem.endswith(DENOISED_SUFFIX))


def _choice(choice: str, from_model, off, on):
    """``off``, the model's settings (``model``), or on: the model's if they are on, else ``on``."""
    if choice == "off":
        return off
    if choice == "on":
        return from_model if from_model.enabled else on
    return from_model


def guard_choice(choice: str, model_guard: GuardConfig) -> GuardConfig:
    """The guard to run with: the model's (``model``), on (the model's settings if it has
    them, else :data:`.guard.DEFAULT_ON`) or off."""
    return _choice(choice, model_guard, GuardConfig(), DEFAULT_ON)


def guide_choice(choice: str, model_guide: GuideConfig) -> GuideConfig:
    """The denoiser guide to run with, chosen as :func:`guard_choice` chooses the guard
    (on without the model's: :data:`.guide.DEFAULT_GUIDE`)."""
    return _choice(choice, model_guide, GuideConfig(), DEFAULT_GUIDE)


def _with_guide_setting(guide: GuideConfig, key: str, value: str | None, allowed: Sequence[str], option: str,
                        switch: str) -> GuideConfig:
    """``guide`` with setting ``key`` = ``value`` (None: unchanged), checked against
    ``allowed``; ``option`` and the guide's own ``switch`` name the settings in the
    one-line error (the guide must be on)."""
    if value is None:
        return guide
    if value not in allowed:
        raise UsageError(f"{option}: must be one of {', '.join(allowed)}, got {value!r}")
    if not guide.enabled:
        raise UsageError(f"{option} is part of the guide: it needs {switch} on (the default)")
    return guide.in_mode(value) if key == "mode" else replace(guide, **{key: value})


def with_guide_mode(guide: GuideConfig, mode: str | None, option: str, switch: str) -> GuideConfig:
    """``guide`` in mode ``mode`` ("weights" or "envelope"; None: unchanged), errors named
    as :func:`with_guide_quality` names them; the envelope drops a learned temperature."""
    return _with_guide_setting(guide, "mode", mode, GUIDE_MODES, option, switch)


def with_guide_denoiser(guide: GuideConfig, denoiser: str | None, option: str, switch: str) -> GuideConfig:
    """``guide`` with the guide images' denoiser ``denoiser`` (one of :data:`.guide.DENOISERS`;
    None: unchanged), errors named as :func:`with_guide_quality` names them."""
    return _with_guide_setting(guide, "denoiser", denoiser, DENOISERS, option, switch)


def with_guide_albedo_channels(guide: GuideConfig, channels: str | None, option: str, switch: str) -> GuideConfig:
    """``guide`` with NL-means' demodulation ``channels`` (one of :data:`.guide.ALBEDO_CHANNELS`;
    None: unchanged), errors named as :func:`with_guide_quality` names them."""
    return _with_guide_setting(guide, "nlm_albedo_channels", channels, ALBEDO_CHANNELS, option, switch)


def with_guide_quality(guide: GuideConfig, quality: str | None, option: str, switch: str) -> GuideConfig:
    """``guide`` with OIDN's quality mode ``quality`` (None: unchanged); ``option`` and the
    guide's own ``switch`` name the settings in the one-line error (the guide must be on,
    the mode one of :data:`.guide.OIDN_QUALITIES`)."""
    return _with_guide_setting(guide, "quality", quality, OIDN_QUALITIES, option, switch)


def with_guide_numbers(guide: GuideConfig, values: Mapping[str, float | None], option_of: Callable[[str], str],
                       switch: str) -> GuideConfig:
    """``guide`` with each numeric setting of :data:`GUIDE_NUMBERS` whose value in ``values``
    (GuideConfig key -> value) is not None; ``option_of(flag)`` and the guide's own
    ``switch`` name the settings in the one-line error, as :func:`with_guide_quality` (the
    guide must be on; each value is checked by :class:`.guide.GuideConfig`)."""
    for flag, _, key, _ in GUIDE_NUMBERS:
        guide = _with_guide_number(guide, key, values.get(key), option_of(flag), switch)
    return guide


def _with_guide_number(guide: GuideConfig, key: str, value: float | None, option: str, switch: str) -> GuideConfig:
    if value is None:
        return guide
    if not guide.enabled:
        raise UsageError(f"{option} is part of the guide: it needs {switch} on (the default)")
    try:
        return replace(guide, **{key: value})
    except ValueError as exc:
        raise UsageError(f"{option}: {exc}") from None


def _init_checkpoint(args) -> int:
    features = FeatureConfig(radius=args.radius_features, passes=args.pass_feature,
                             scale_free=args.scale_free_features, outliers=args.outlier_features)
    model = checkpoint.init_checkpoint(args.init_checkpoint, load_preset(args.preset), features, seed=args.seed,
                                       guard=guard_choice(args.guard or "off", GuardConfig()),
                                       guide=guide_choice(args.guide or "off", GuideConfig()))
    if not args.quiet:
        print(f"{args.init_checkpoint}: untrained '{model.preset.name}' model, "
              f"{parameter_count(model):,} parameters, {features.n_channels} input channels")
    return 0


def torch_device(name: str) -> torch.device:
    """The torch device ``name`` (cpu or cuda), refused in one line when it is not there."""
    if name not in ("cpu", "cuda"):
        raise UsageError(f"device '{name}': choose cpu or cuda")
    if name == "cuda" and not torch.cuda.is_available():
        raise UsageError("--device cuda: torch sees no CUDA device (CPU-only build or no GPU); use --device cpu")
    return torch.device(name)


def _outputs(args: argparse.Namespace, inputs: list[Path]) -> list[Path]:
    """One output per input; refuses -o with several inputs and any output that would
    overwrite an input."""
    if args.output and len(inputs) > 1:
        raise UsageError(f"--output {args.output} names one file but {len(inputs)} inputs were given; "
                         f"leave it out to write INPUT_denoised.exr next to each input")
    outs = [Path(args.output)] if args.output else [default_output(p) for p in inputs]
    sources = {p.resolve() for p in inputs if p.exists()}
    for out in outs:
        if out.suffix.lower() != ".exr":
            raise UsageError(f"--output {out}: the output must be an .exr file")
        if out.exists() and out.resolve() in sources:
            raise UsageError(f"{out}: output would overwrite the input; choose another --output")
    return outs


def _main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.init_checkpoint:
        if args.inputs:
            parser.error("--init-checkpoint takes no INPUT.exr")
        return _init_checkpoint(args)
    if not args.inputs:
        parser.error("the following arguments are required: INPUT.exr")
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch_device(args.device)
    model_path = checkpoint.model_path(args.model)
    inputs = expand_inputs(args.inputs)
    outputs = _outputs(args, inputs)
    for src in inputs:  # before the model loads: a typo costs nothing
        if not src.exists():
            raise UsageError(f"{src}: no such file")

    model, _meta = checkpoint.load_checkpoint(model_path, map_location=device)
    guard = guard_choice(args.guard or "on", model.guard)
    if args.anchor is not None:
        if not guard.enabled:
            raise UsageError("--anchor is part of the guard: it needs --guard on (the default)")
        guard = replace(guard, anchor=args.anchor)
    guide = with_guide_quality(guide_choice(args.guide or "on", model.guide), args.guide_quality, "--guide-quality",
                               "--guide")
    guide = with_guide_mode(guide, args.guide_mode, "--guide-mode", "--guide")
    guide = with_guide_denoiser(guide, args.guide_denoiser, "--guide-denoiser", "--guide")
    guide = with_guide_albedo_channels(guide, args.guide_nlm_albedo_channels, "--guide-nlm-albedo-channels",
                                       "--guide")
    guide = with_guide_numbers(guide, {key: getattr(args, flag[2:].replace("-", "_"))
                                       for flag, _, key, _ in GUIDE_NUMBERS}, lambda flag: flag, "--guide")
    if args.weights_layers and guide.enabled and guide.mode in ENVELOPE_MODES:
        raise UsageError(f"--weights-layers: the guide's {guide.mode} has no combination weights "
                         "(use --guide-mode weights, or --guide off)")
    for src, out in zip(inputs, outputs):
        _denoise_one(args, src, out, model, model_path, device, guard, guide)
    return 0


def _denoise_one(args: argparse.Namespace, src: Path, out: Path, model, model_path: Path,
                 device: torch.device, guard: GuardConfig, guide: GuideConfig) -> None:
    """Denoise one buffer file into ``out`` (atomically) and print its summary line."""
    buf = read_buffers(src)
    progress = Progress("denoise", quiet=args.quiet)

    def report(done: int, total: int) -> None:
        progress.total = total
        progress.update(done, force=done == total)

    start = time.perf_counter()
    try:
        result = denoise(buf, model, tile=args.tile, device=device, progress=report, precision=args.precision,
                         guard=guard, guide=guide)
    finally:
        progress.close()
    seconds = time.perf_counter() - start

    extra = {}
    if args.weights_layers:
        extra = {f"{WEIGHT_LAYER}.{name}": result.weights_per_z[j] for j, name in enumerate(ESTIMATES[1:])}
    header = dict(buf.header)
    header.update({H_DENOISER: model.preset.name, H_MODEL: str(model_path), H_DENOISE_SECONDS: round(seconds, 4),
                   H_GUARD: "on" if guard.enabled else "off", H_ANCHOR: guard.anchor if guard.enabled else 0.0,
                   H_GUIDE: _guide_header(guide)})
    write_rgb(out, result.rgb, extra=extra, header=header)
    if not args.quiet:
        h, w = buf.shape
        how = (f"the guide's {guide.mode}" if guide.enabled and guide.mode in ENVELOPE_MODES
               else f"'{model.preset.name}'")
        print(f"{out}: {w}x{h} denoised with {how} in {seconds:.2f} s")


def _guide_header(guide: GuideConfig) -> str:
    """The guide's settings as the output's ``ppmrecon.guide`` header says them."""
    if not guide.enabled:
        return "off"
    how = (f"anchor=z{guide.anchor_source} k={guide.anchor_noise:g}" if guide.mode in ENVELOPE_MODES
           else f"beta={guide.beta:g}")
    spike = f" spike={guide.y_spike:g}" if guide.y_spike and guide.mode in ENVELOPE_MODES else ""
    spike += f" zspike={guide.z_spike:g}" if guide.z_spike and guide.mode in ENVELOPE_MODES else ""
    spike += f" free={guide.anchor_free:g}" if guide.anchor_free and guide.mode in ENVELOPE_MODES else ""
    spike += f" redis={guide.redistribute:g}" if guide.redistribute and guide.mode in ENVELOPE_MODES else ""
    spike += f" cascade={guide.cascade:g}" if guide.cascade and guide.mode in ENVELOPE_MODES else ""
    spike += (f" from={guide.cascade_passes:g}" if guide.cascade and guide.cascade_passes
              and guide.mode in ENVELOPE_MODES else "")
    ystep = bool(guide.cascade and guide.cascade_y and guide.mode in ENVELOPE_MODES)
    spike += f" ystep={guide.cascade_y:g}" if ystep else ""
    spike += f" up={guide.cascade_y_up:g}" if ystep and guide.cascade_y_up else ""
    spike += (f" dark={guide.anchor_free_dark:g}" if guide.anchor_free and guide.anchor_free_dark
              and guide.mode in ENVELOPE_MODES else "")
    settled = f" settled={guide.anchor_settled:g}" if guide.anchor_settled and guide.mode in ENVELOPE_MODES else ""
    select = f" select={guide.anchor_select:g}" if guide.anchor_select and guide.mode in ENVELOPE_MODES else ""
    terms = f" terms={guide.terms_passes:g}" if guide.terms_passes and guide.mode in ENVELOPE_MODES else ""
    terms += (f" range={guide.range_sigma:g}sd" + (f"(<={guide.range_sigma_rel:g})" if guide.range_sigma_rel else "")
              + (f"(width<={guide.range_sigma_width:g}sd)" if guide.range_sigma_width else "")
              + (f"(isolated>{guide.range_sigma_isolated:g}x)" if guide.range_sigma_isolated else "")
              if guide.range_sigma and guide.mode in ENVELOPE_MODES else "")
    spikes = f" spikes={guide.anchor_spikes:g}" if guide.anchor_spikes and guide.mode in ENVELOPE_MODES else ""
    found = f" found={guide.y_found:g}" if guide.y_found and guide.y_weight else ""
    found += f" empty={guide.y_empty:g}" if guide.y_empty and guide.y_weight else ""
    nlm = f"nlm k={guide.nlm_k:g} r={guide.nlm_radius:g}" + (
        f" albedo={guide.nlm_albedo:g}(+{guide.nlm_albedo_eps:g}"
        f"{', rgb' if guide.nlm_albedo_channels == 'rgb' else ''})" if guide.nlm_albedo else "")
    uses_y = bool(guide.y_weight or guide.cross)
    # the joint filter holds from nlm_joint_passes up to nlm_y_passes (from there ~y has its own NL-means)
    joint = bool(uses_y and guide.nlm_joint_passes and guide.denoiser != "oidn"
                 and not (guide.nlm_y_passes and guide.nlm_y_passes <= guide.nlm_joint_passes))
    y_k = f" k(y)={guide.nlm_y_k:g}" if guide.nlm_y_k else ""
    y_alone = {"oidn": "", "nlm": y_k, "nlm_source": f" oidn(y, {guide.quality})"
               + (f" nlm(y from N={guide.nlm_y_passes:g}){y_k}" if guide.nlm_y_passes and not joint else "")
               }[guide.denoiser]
    source = {"oidn": f"oidn(z{guide.source}, {guide.quality})",
              "nlm": f"{nlm}(z{guide.source}{', y' if uses_y else ''})",
              "nlm_source": f"{nlm}(z{guide.source})"}[guide.denoiser] + (y_alone if uses_y else "")
    if joint:
        source += (f" below N={guide.nlm_joint_passes:g}, joint(z{guide.source} + y) from "
                   f"N={guide.nlm_joint_passes:g} k={guide.nlm_joint_k or guide.nlm_k:g}"
                   + (f" below N={guide.nlm_y_passes:g}, nlm(y) from N={guide.nlm_y_passes:g}{y_k}"
                      if guide.nlm_y_passes else ""))
    return (f"{source} {guide.mode} {how} cross={guide.cross:g} "
            f"y={guide.y_weight:g}{found}{spike}{settled}{select}{terms}{spikes}")


def main(argv: Sequence[str] | None = None) -> int:
    """Console-script entry point: one-line errors, exit code 2 for usage errors, 1 for failures."""
    return run_main(PROG, _main, argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
