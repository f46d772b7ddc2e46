"""``ppmrecon-render``: render a scene with multi-bandwidth progressive photon mapping.

Writes one buffer file (five bandwidth estimates, variances, radii, G-buffers; SPEC
section 2), or with ``--single`` the conventional single-bandwidth image as a plain
R,G,B EXR. Ctrl-C or the end of a ``--time`` budget writes the passes completed so far
and records why in the header (``ppmrecon.stopped``).
"""

from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path
from typing import Sequence


from .. import buffers as B
from ..backend import VARIANTS, choose_variant
from ..cli_common import ArgumentParser, Progress, positive_float, positive_int, run_main
from ..errors import UsageError
from .kernels import KERNELS

PROG = "ppmrecon-render"
DEFAULT_PASSES = 16


def _max_depth(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not an integer") from None
    if value == 0 or value < -1:
        raise argparse.ArgumentTypeError(f"must be a positive number of segments or -1 (unbounded), got {value}")
    return value


def _resolution(text: str) -> tuple[int, int] | int:
    m = re.fullmatch(r"\s*(\d+)\s*(?:[xX]\s*(\d+))?\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"'{text}' is not WxH (e.g. 256x256) or a width")
    w = int(m.group(1))
    h = int(m.group(2)) if m.group(2) else None
    if w <= 0 or (h is not None and h <= 0):
        raise argparse.ArgumentTypeError(f"resolution must be positive, got '{text}'")
    return (w, h) if h is not None else w


def build_parser() -> ArgumentParser:
    from .controllers import CONTROLLERS

    p = ArgumentParser(
        prog=PROG,
        description="Render a Mitsuba 3 / Mitsuba 0.6 scene (or a built-in one) with "
                    "multi-bandwidth progressive photon mapping into a buffer EXR.",
        epilog="Built-in scenes: see --list-scenes. Example: ppmrecon-render --passes 64 "
               "--output cbox.exr && ppmrecon-denoise cbox.exr")
    p.add_argument("scene", nargs="?", default=None,
                   help="built-in scene name or path to a Mitsuba 3/0.6 XML (default: the built-in default scene)")
    p.add_argument("--method", default="sppm", choices=sorted(CONTROLLERS),
                   help="bandwidth controller (default: sppm)")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--passes", type=positive_int, default=None,
                        help=f"number of passes (default: {DEFAULT_PASSES})")
    budget.add_argument("--time", type=positive_float, default=None, metavar="SECONDS",
                        help="render for this wall-clock budget instead of a pass count")
    p.add_argument("--photons", type=positive_int, default=1 << 17, metavar="J",
                   help="photons emitted per pass (default: 131072)")
    p.add_argument("--resolution", type=_resolution, default=None, metavar="WxH",
                   help="film size; a single width keeps the scene's aspect ratio")
    p.add_argument("--seed", type=int, default=0, help="random seed (same seed, same file)")
    p.add_argument("--kernel", default="constant", choices=KERNELS, help="density kernel (default: constant)")
    p.add_argument("--max-depth", type=_max_depth, default=None, metavar="D",
                   help="longest path in segments, camera to light, as Mitsuba's max_depth; -1 = unbounded "
                        "(default: the scene integrator's max_depth, else -1)")
    p.add_argument("--rr-depth", type=positive_int, default=None, metavar="D",
                   help="bounces before Russian roulette on photon and eye paths "
                        "(default: the scene integrator's rr_depth, else 5)")
    p.add_argument("--alpha", type=float, default=2.0 / 3.0,
                   help="radius reduction alpha of SPPM and of FPPM's lower bound (default: 2/3)")
    p.add_argument("--knn", type=positive_int, default=20,
                   help="k of the k-NN initial bandwidth (default: 20; also CPPM's first photon-count threshold)")
    tests = p.add_argument_group("CPPM / FPPM bandwidth tests (SPEC section 4)")
    tests.add_argument("--significance", type=float, default=None, metavar="P",
                       help="significance level of the chi-squared (cppm, default 0.05) or F test (fppm, default 0.01)")
    tests.add_argument("--shrink-k", type=float, default=None, metavar="K",
                       help="radius shrink factor k: cppm r*sqrt(k) (default 0.8), fppm k*r (default 0.7)")
    tests.add_argument("--beta", type=float, default=None,
                       help="cppm: growth of the photon-count threshold per shrink (default 1.5625)")
    tests.add_argument("--r-min-frac", type=float, default=None, metavar="F",
                       help="fppm: r_min as a fraction of each chain's initial radius (default 0.25)")
    tests.add_argument("--per-channel", action="store_true",
                       help="fppm: F-test R, G and B separately (chromatic or textured lights) instead of luminance")
    p.add_argument("--direct", choices=("none", "glossy", "all"), default="all",
                   help="direct lighting by emitter + BSDF sampling (MIS) at gather points, photons for "
                        "the indirect part only there: none (photons carry all light), glossy (gather "
                        "points with a glossy BSDF) or all (default: all)")
    p.add_argument("--single", action="store_true",
                   help="render the conventional single-bandwidth image (one chain, one eye path) "
                        "into a plain R,G,B EXR")
    p.add_argument("--single-knn", type=positive_int, default=None, metavar="K",
                   help="--single: initial radius = distance to the K-th nearest photon (default: 10, "
                        "the r_20/sqrt(2) radius paper 002 calls 'roughly k = 10')")
    p.add_argument("--shared-hit-point", action="store_true",
                   help="diagnostic: gather all five chains at one hit point (no decorrelation)")
    p.add_argument("--output", "-o", type=Path, default=None, metavar="FILE.exr",
                   help="output EXR (default: <scene>_<method>[_single].exr in the current folder)")
    p.add_argument("--variant", choices=VARIANTS, default=None,
                   help="force a Mitsuba variant (default: cuda_ad_rgb if a GPU is usable, else llvm_ad_rgb)")
    p.add_argument("--list-scenes", action="store_true", help="list the built-in scenes and exit")
    p.add_argument("--check", action="store_true",
                   help="load the scene, report what the import approximated, and exit without rendering")
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bar")
    return p


#: CLI option -> (controller parameter, methods that take it).
METHOD_OPTIONS: dict[str, tuple[str, tuple[str, ...]]] = {
    "significance": ("significance", ("cppm", "fppm")),
    "shrink_k": ("k", ("cppm", "fppm")),
    "beta": ("beta", ("cppm",)),
    "r_min_frac": ("r_min_frac", ("fppm",)),
    "per_channel": ("per_channel", ("fppm",)),
}


def method_params(args: argparse.Namespace) -> dict:
    """The controller options given on the command line, checked against the method."""
    params = {}
    for option, (param, methods) in METHOD_OPTIONS.items():
        value = getattr(args, option)
        if value is None or value is False:
            continue
        flag = "--" + option.replace("_", "-")
        if args.method not in methods:
            raise UsageError(f"{flag} applies to --method {' or '.join(methods)}, not {args.method}")
        if option in ("significance", "shrink_k") and not 0.0 < value < 1.0:
            raise UsageError(f"{flag} must lie in (0, 1), got {value}")
        if option == "beta" and not 1.0 <= value < float("inf"):
            raise UsageError(f"{flag} must be at least 1, got {value}")
        if option == "r_min_frac" and not 0.0 < value <= 1.0:
            raise UsageError(f"{flag} must lie in (0, 1], got {value}")
        params[param] = value
    return params


def _default_output(scene_name: str, method: str, single: bool) -> Path:
    stem = Path(scene_name).stem if scene_name.endswith(".xml") else scene_name
    return Path(f"{stem}_{method}{'_single' if single else ''}.exr")


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .scene import DEFAULT_SCENE, builtin_scenes

    if args.list_scenes:
        for name, path in builtin_scenes().items():
            mark = " (default)" if name == DEFAULT_SCENE else ""
            print(f"{name}{mark}\t{path}")
        return 0
    if not 0.0 < args.alpha < 1.0:
        raise UsageError(f"--alpha must lie in (0, 1), got {args.alpha}")
    params = method_params(args)
    if args.single and args.shared_hit_point:
        raise UsageError("--single and --shared-hit-point exclude each other")
    if args.single_knn is not None and not args.single:
        raise UsageError("--single-knn applies to --single renders only")
    if args.output is not None:
        if args.output.suffix.lower() != ".exr":
            raise UsageError(f"--output {args.output}: the output must be an .exr file")
        if not args.output.parent.exists():
            raise UsageError(f"--output {args.output}: folder '{args.output.parent}' does not exist")

    variant = choose_variant(args.variant)
    from .integrator import Renderer, RenderSettings
    from .scene import load_scene

    loaded = load_scene(args.scene, resolution=args.resolution, warn=not args.check)
    if args.check:
        from ..scene.loader import check_report
        sys.stdout.write(check_report(loaded))
        return 0
    scene_max_depth, scene_rr_depth = loaded.depths()
    max_depth = args.max_depth if args.max_depth is not None else scene_max_depth
    rr_depth = args.rr_depth or scene_rr_depth
    layout = "single" if args.single else ("shared" if args.shared_hit_point else "multi")
    settings = RenderSettings(
        method=args.method, passes=args.passes if args.passes else (None if args.time else DEFAULT_PASSES),
        time_budget=args.time, photons=args.photons, seed=args.seed, kernel=args.kernel,
        max_depth=max_depth, rr_depth=rr_depth, alpha=args.alpha, knn=args.knn,
        single_knn=args.single_knn or RenderSettings.single_knn, direct=args.direct, layout=layout,
        method_params=params)
    output = args.output or _default_output(loaded.name, args.method, args.single)

    renderer = Renderer(loaded.scene, settings, scene_name=loaded.name)
    progress = Progress(f"{PROG} {loaded.name} {renderer.width}x{renderer.height} {args.method}",
                        total=settings.passes, quiet=args.quiet)

    def on_pass(r: Renderer) -> None:
        rate = r.passes_done * settings.photons / max(r.seconds, 1e-9)
        progress.update(r.passes_done, force=r.passes_done == settings.passes,
                        photons_per_s=f"{rate / 1e6:.2f}M")

    result = renderer.run(on_pass)
    progress.close()
    result.header["ppmrecon.variant"] = variant
    if loaded.notes:
        result.header[B.H_IMPORT_NOTES] = B.encode_notes(loaded.notes)
    if result.nonfinite:
        where = ", ".join(f"{result.header[f'ppmrecon.nonfinite.{k}']} {k}" for k in renderer.nonfinite)
        sys.stderr.write(f"{PROG}: warning: dropped {result.nonfinite} non-finite terms ({where}; "
                         f"recorded as ppmrecon.nonfinite.*)\n")
    if args.single:
        B.write_rgb(output, result.estimates[0], header=result.header)
    else:
        B.write_buffers(output, result.buffer_file())
    note = ""
    if result.stopped != "complete":
        note = f" ({result.stopped} after {result.passes} passes)"
    if not args.quiet:
        stages = ", ".join(f"{k} {v:.2f}s" for k, v in result.stage_seconds.items())
        sys.stderr.write(f"{PROG}: wrote {output}: {result.passes} passes in {result.seconds:.2f}s{note} [{stages}]\n")
    return 130 if result.stopped == "interrupted" else 0


def entry() -> None:
    """Console-script entry point."""
    raise SystemExit(run_main(PROG, main))


if __name__ == "__main__":  # pragma: no cover
    entry()
