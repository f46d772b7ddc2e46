"""``ppmrecon-render``: render a scene with multi-bandwidth progressive photon mapping.

Writes one buffer file (five bandwidth estimates, variances, radii, G-buffers; SPEC
section 2), or with ``--single`` the conventional single-bandwidth image as a plain
R,G,B EXR, and beside it the render's state (``FILE.exr.state.npz``, see
:mod:`.state`), from which ``--resume FILE.exr`` continues it pass for pass as if it had
never stopped. Ctrl-C finishes the pass in progress (a second Ctrl-C stops at once), and
the end of a ``--time`` budget stops between passes; both write the passes completed so
far and record why in the header (``ppmrecon.stopped``). ``--checkpoint-every K`` saves
file and state every K passes, so a killed process loses at most K passes;
``--snapshots`` writes a separate buffer file at chosen pass counts.
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

#: Options (argparse dests) that define a render: a continued render keeps its own.
RESUME_FIXED: tuple[str, ...] = (
    "method", "photons", "resolution", "seed", "kernel", "max_depth", "rr_depth", "alpha", "knn",
    "significance", "shrink_k", "beta", "r_min_frac", "per_channel", "direct", "single", "single_knn",
    "shared_hit_point")


def snapshot_list(text: str) -> tuple[int, ...]:
    """argparse type: pass counts ``16,64,256``; ``FIRST..LAST`` doubles from FIRST up to
    at most LAST (``16..256`` = 16,32,64,128,256); both forms may be mixed."""
    counts: set[int] = set()
    for part in text.split(","):
        m = re.fullmatch(r"\s*(\d+)\s*(?:\.\.\s*(\d+)\s*)?", part)
        if not m:
            raise argparse.ArgumentTypeError(f"'{part.strip()}' is neither a pass count nor FIRST..LAST")
        first = int(m.group(1))
        last = int(m.group(2)) if m.group(2) else first
        if first <= 0 or last < first:
            raise argparse.ArgumentTypeError(f"'{part.strip()}': pass counts must be positive and FIRST <= LAST")
        n = first
        while n <= last:  # a few doublings, not a loop over data
            counts.add(n)
            n *= 2
    return tuple(sorted(counts))


def snapshot_path(output: Path, passes: int) -> Path:
    """``out.exr`` -> ``out_p0016.exr`` (zero-padded so that the files sort by passes)."""
    return output.with_name(f"{output.stem}_p{passes:04d}{output.suffix}")


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
                   help="built-in scene name or path to a Mitsuba 3/0.6 XML (default: the built-in default scene; "
                        "with --resume: the scene recorded in the state, or its new path if it moved)")
    p.add_argument("--method", default="sppm", choices=sorted(CONTROLLERS),
                   help="bandwidth controller (default: sppm)")
    budget = p.add_mutually_exclusive_group()
    budget.add_argument("--passes", type=positive_int, default=None,
                        help=f"number of passes; with --resume, passes to add (default: {DEFAULT_PASSES}, or up to "
                             f"the last --snapshots count)")
    budget.add_argument("--time", type=positive_float, default=None, metavar="SECONDS",
                        help="render for this wall-clock budget instead of a pass count (with --resume: this "
                             "much longer)")
    progressive = p.add_argument_group("continuing, checkpoints and snapshots")
    progressive.add_argument("--resume", type=Path, default=None, metavar="FILE.exr",
                             help="continue the render that wrote FILE.exr (from FILE.exr.state.npz) by "
                                  "--passes more passes or --time more seconds; the settings are the "
                                  "recorded ones; writes FILE.exr again unless --output is given")
    progressive.add_argument("--checkpoint-every", type=positive_int, default=None, metavar="K",
                             help="also write the output and its state every K passes, so that a killed "
                                  "process loses at most K passes (default: only at the end)")
    progressive.add_argument("--no-state", action="store_true",
                             help="keep no state file beside the output (it cannot be continued then; a "
                                  "CPPM/FPPM state at 1280x720 is 0.2-0.6 GB)")
    progressive.add_argument("--snapshots", type=snapshot_list, default=None, metavar="LIST",
                             help="also write a buffer file at these pass counts, e.g. 16,64,256, or "
                                  "16..256 for every doubling from 16 to 256; named OUTPUT_p0016.exr ...")
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
    tests = p.add_argument_group("CPPM / FPPM bandwidth tests, APPM bounds (SPEC section 4)")
    tests.add_argument("--significance", type=float, default=None, metavar="P",
                       help="significance level of the chi-squared (cppm, default 0.05) or F test (fppm, default 0.01)")
    tests.add_argument("--shrink-k", type=float, default=None, metavar="K",
                       help="radius shrink factor k: cppm r*sqrt(k) (default 0.8), fppm k*r (default 0.7)")
    tests.add_argument("--beta", type=float, default=None,
                       help="cppm: growth of the photon-count threshold per shrink (default 1.5625)")
    tests.add_argument("--r-min-frac", type=float, default=None, metavar="F",
                       help="fppm, appm: r_min as a fraction of each chain's initial radius (default 0.25 "
                            "fppm, 0.1 appm)")
    tests.add_argument("--r-max-frac", type=float, default=None, metavar="F",
                       help="appm: r_max as a multiple of each chain's initial radius, bound r_max N^(-1/6) "
                            "(default 2)")
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
    "r_min_frac": ("r_min_frac", ("fppm", "appm")),
    "r_max_frac": ("r_max_frac", ("appm",)),
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
        if option == "r_max_frac" and not 1.0 <= value < float("inf"):
            raise UsageError(f"{flag} must be at least 1, got {value}")
        params[param] = value
    return params


def _default_output(scene_name: str, method: str, single: bool) -> Path:
    stem = Path(scene_name).stem if scene_name.endswith(".xml") else scene_name
    return Path(f"{stem}_{method}{'_single' if single else ''}.exr")


def _explicit_options(parser: argparse.ArgumentParser, argv: Sequence[str] | None) -> set[str]:
    """The dests of the options the user actually gave (parsed again with no defaults)."""
    saved = [(a, a.default) for a in parser._actions]
    for a, _ in saved:
        a.default = argparse.SUPPRESS
    try:
        return set(vars(parser.parse_args(argv)))
    finally:
        for a, default in saved:
            a.default = default


class Job:
    """What one invocation renders: the renderer (fresh or restored) and where it writes."""

    def __init__(self, loaded, renderer, output: Path, scene_spec: str, previous: str | None, start: int):
        self.loaded, self.renderer, self.output = loaded, renderer, output
        self.scene_spec, self.previous, self.start = scene_spec, previous, start
        self.saved_passes: int | None = None  # passes in the output on disk, once written


def _budget(args: argparse.Namespace, start: int) -> tuple[int | None, float | None]:
    """(total passes or None, time budget or None) from --passes/--time/--snapshots."""
    if args.time is not None:
        return (None, args.time)
    if args.passes is not None:
        total = start + args.passes
        if args.snapshots and args.snapshots[-1] > total:
            raise UsageError(f"--snapshots {args.snapshots[-1]} lies beyond the {total} passes this render "
                             f"ends at (--passes {args.passes}{f' after {start}' if start else ''})")
        return (total, None)
    later = [n for n in (args.snapshots or ()) if n > start]
    return ((later[-1] if later else start + DEFAULT_PASSES), None)


def _new_job(args: argparse.Namespace) -> Job:
    from ..api import render_settings
    from .integrator import Renderer, RenderSettings
    from .scene import builtin_scenes, load_scene

    if not 0.0 < args.alpha < 1.0:
        raise UsageError(f"--alpha must lie in (0, 1), got {args.alpha}")
    params = method_params(args)
    if args.single and args.shared_hit_point:
        raise UsageError("--single and --shared-hit-point exclude each other")
    if args.single_knn is not None and not args.single:
        raise UsageError("--single-knn applies to --single renders only")
    loaded = load_scene(args.scene, resolution=args.resolution)
    layout = "single" if args.single else ("shared" if args.shared_hit_point else "multi")
    passes, time_budget = _budget(args, 0)
    settings = render_settings(
        loaded, max_depth=args.max_depth, rr_depth=args.rr_depth, method=args.method, passes=passes,
        time_budget=time_budget, photons=args.photons, seed=args.seed, kernel=args.kernel, alpha=args.alpha,
        knn=args.knn, single_knn=args.single_knn or RenderSettings.single_knn, direct=args.direct, layout=layout,
        method_params=params)
    output = args.output or _default_output(loaded.name, args.method, args.single)
    builtin = args.scene is None or args.scene in builtin_scenes()
    spec = loaded.name if builtin else str(Path(args.scene).resolve())
    return Job(loaded, Renderer(loaded.scene, settings, scene_name=loaded.name), output, spec, None, 0)


def _resume_job(parser: argparse.ArgumentParser, argv: Sequence[str] | None, args: argparse.Namespace) -> Job:
    from .integrator import Renderer, RenderSettings
    from .scene import load_scene
    from .state import StateError, check_output, check_scene, read_state, state_path

    src: Path = args.resume
    if src.suffix.lower() != ".exr":
        raise UsageError(f"--resume {src}: expected the .exr file a render wrote")
    if not src.is_file():
        raise UsageError(f"--resume {src}: no such file")
    sp = state_path(src)
    if not sp.is_file():
        raise UsageError(f"--resume {src}: no render state beside it ({sp.name}); only a file written by "
                         f"{PROG} together with its state can be continued")
    fixed = sorted(set(RESUME_FIXED) & _explicit_options(parser, argv))
    if fixed:
        flags = ", ".join("--" + f.replace("_", "-") for f in fixed)
        raise UsageError(f"{flags} cannot be given with --resume: a continued render keeps the settings it "
                         f"started with (recorded in {sp.name})")
    saved = read_state(sp)
    digest = check_output(src, saved, sp)
    start = saved.passes
    passes, time_budget = _budget(args, start)
    try:
        settings = RenderSettings(**saved.settings, passes=passes, time_budget=time_budget)
        settings.validate()
    except (TypeError, ValueError) as exc:
        raise StateError(sp, f"unusable settings record ({exc})") from None
    scene = saved.meta["scene"]
    spec = args.scene or scene.get("spec")
    loaded = load_scene(spec, resolution=(int(scene.get("width", 0)), int(scene.get("height", 0))))
    check_scene(loaded, saved, sp)
    renderer = Renderer(loaded.scene, settings, scene_name=str(scene.get("name", loaded.name)))
    try:
        renderer.import_state(saved.counters, saved.arrays)
    except (KeyError, TypeError, ValueError) as exc:
        raise StateError(sp, f"does not fit the render it names: {exc}") from None
    output = args.output or src
    same = output.resolve() == src.resolve()
    if args.scene is not None:
        spec = str(Path(args.scene).resolve()) if Path(args.scene).is_file() else args.scene
    job = Job(loaded, renderer, output, spec, digest if same else None, start)
    job.saved_passes = start if same else None
    return job


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from .scene import DEFAULT_SCENE, builtin_scenes

    if args.list_scenes:
        for name, path in builtin_scenes().items():
            mark = " (default)" if name == DEFAULT_SCENE else ""
            print(f"{name}{mark}\t{path}")
        return 0
    if args.output is not None:
        if args.output.suffix.lower() != ".exr":
            raise UsageError(f"--output {args.output}: the output must be an .exr file")
        if not args.output.parent.exists():
            raise UsageError(f"--output {args.output}: folder '{args.output.parent}' does not exist")

    if args.no_state and args.checkpoint_every:
        raise UsageError("--checkpoint-every needs the state file that --no-state leaves out")
    variant = choose_variant(args.variant)
    if args.check:
        from ..scene.loader import check_report
        from .scene import load_scene

        sys.stdout.write(check_report(load_scene(args.scene, resolution=args.resolution, warn=False)))
        return 0
    job = _resume_job(parser, argv, args) if args.resume is not None else _new_job(args)
    renderer, output, settings = job.renderer, job.output, job.renderer.settings
    single = settings.layout == "single"
    if args.snapshots and args.snapshots[0] <= job.start:
        early = [n for n in args.snapshots if n <= job.start]
        sys.stderr.write(f"{PROG}: note: no snapshot at {', '.join(map(str, early))}: the render already has "
                         f"{job.start} passes\n")

    from ..api import stamp_header
    from .state import save_with_state, scene_record, settings_record, state_path

    def write_file(path: str | Path, result) -> None:
        stamp_header(result.header, variant, job.loaded.notes)
        if single:
            B.write_rgb(path, result.estimates[0], header=result.header)
        else:
            B.write_buffers(path, result.buffer_file())

    def save(stopped: str, result=None):
        """Write the output and its state (the pair a later --resume continues)."""
        result = result or renderer.result(stopped)
        if args.no_state:
            write_file(output, result)
            state_path(output).unlink(missing_ok=True)  # a stale state would not fit anyway
            return result
        counters, arrays = renderer.export_state()
        meta = {"scene": scene_record(job.loaded, job.scene_spec), "settings": settings_record(settings),
                "variant": variant, "counters": counters}
        job.previous = save_with_state(output, lambda tmp: write_file(tmp, result), meta, arrays, job.previous)
        job.saved_passes = renderer.passes_done
        return result

    method = settings.method
    progress = Progress(f"{PROG} {job.loaded.name} {renderer.width}x{renderer.height} {method}",
                        total=settings.passes, quiet=args.quiet)
    snapshots = set(args.snapshots or ())

    def on_pass(r) -> None:
        rate = r.passes_done * settings.photons / max(r.seconds, 1e-9)  # seconds: all sessions
        progress.update(r.passes_done, force=r.passes_done == settings.passes,
                        photons_per_s=f"{rate / 1e6:.2f}M")
        if r.passes_done in snapshots:
            write_file(snapshot_path(output, r.passes_done), r.result("complete"))
        every = args.checkpoint_every
        if every and r.passes_done % every == 0 and r.passes_done != settings.passes:
            save("checkpoint")

    def on_interrupt(pass_index: int) -> None:
        progress.close()
        sys.stderr.write(f"{PROG}: Ctrl-C: finishing pass {pass_index}, then writing {output} "
                         f"(Ctrl-C again to stop at once)\n")

    try:
        result = renderer.run(on_pass, on_interrupt)
    except KeyboardInterrupt:
        progress.close()
        kept = (f"{output} and its state hold {job.saved_passes} passes" if job.saved_passes
                else "nothing was written")
        sys.stderr.write(f"{PROG}: interrupted during pass {renderer.passes_done + 1}; {kept}\n")
        return 130
    progress.close()
    result = save(result.stopped, result)
    if result.nonfinite:
        where = ", ".join(f"{result.header[f'ppmrecon.nonfinite.{k}']} {k}" for k in renderer.nonfinite)
        sys.stderr.write(f"{PROG}: warning: dropped {result.nonfinite} non-finite terms ({where}; "
                         f"recorded as ppmrecon.nonfinite.*)\n")
    note = ""
    if result.stopped != "complete":
        note = f" ({result.stopped} after {result.passes} passes)"
    if not args.quiet:
        stages = ", ".join(f"{k} {v:.2f}s" for k, v in result.stage_seconds.items())
        resumed = f" (continued from {job.start})" if job.start else ""
        sys.stderr.write(f"{PROG}: wrote {output}: {result.passes} passes{resumed} in {result.seconds:.2f}s"
                         f"{note} [{stages}]\n")
    return 130 if result.stopped == "interrupted" else 0


def entry() -> None:
    """Console-script entry point."""
    raise SystemExit(run_main(PROG, main))


if __name__ == "__main__":  # pragma: no cover
    entry()
