"""``ppmrecon-compare``: score RGB or buffer EXRs against a reference (SPEC section 7).

    ppmrecon-compare REF.exr FILE.exr ['PATTERN*.exr' ...] [--layers y,z1,...]
                     [--json [OUT.json]] [--plot OUT.png] [--crop X,Y,W,H] [--target RELMSE]

For every file (an R,G,B image such as a denoised output or a ``--single`` render, or a
buffer file, whose five estimates are scored one by one unless ``--layers`` picks some)
it reports

* ``relmse``: relMSE, :func:`.metrics.relmse`;
* ``relmse_8x8``: the same on 8x8 block means, the low-frequency error;
* ``relmse_trimmed``: relMSE without the 0.1% largest per-pixel errors (fireflies);
* ``luminance_ratio``: mean luminance of the file over that of the reference;

as a table on stdout, as JSON with ``--json`` (on stdout instead of the table, or into a
file), and with ``--plot`` as a PNG of relMSE against passes (``ppmrecon.passes`` of
each file's header) on log-log axes with the least-squares slope of each series (one
series per method and layer), plus ``OUT_crops.png``, the same crop of the reference
and of every scored image side by side. ``--target X`` answers "how many passes for
relMSE X": per series the fewest measured passes that reach it and where the fitted
line crosses it. A reference at an integer multiple of a file's
resolution is area-averaged down to it; other sizes (another aspect ratio, a fractional
factor, a smaller reference) are refused in one line.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from . import buffers as B
from ._callable import CallableModule
from .cli_common import ArgumentParser, expand_paths, positive_float, run_main
from .errors import UsageError
from .fileio import atomic_write, write_text
from .metrics import block_means, luminance, luminance_ratio, relmse, relmse_blocks, relmse_trimmed

PROG = "ppmrecon-compare"
BLOCK = 8
TRIM = 1e-3
H_DENOISER = "ppmrecon.denoiser"  # written by ppmrecon-denoise

# ``ppmrecon.compare(image, reference)`` is also the API function (see ppmrecon._callable).
sys.modules[__name__].__class__ = CallableModule


@dataclass
class Score:
    """The scores of one image (one file, or one estimate layer of a buffer file)."""

    file: str
    layer: str
    passes: int | None
    method: str | None
    relmse: float
    relmse_8x8: float | None
    relmse_trimmed: float
    luminance_ratio: float | None

    @property
    def series(self) -> str:
        """What the plot draws as one line: method and layer."""
        return f"{self.method or '?'} {self.layer}"


def _finite_or_none(x: float) -> float | None:
    return x if math.isfinite(x) else None


def load_images(path: Path, layers: Sequence[str] | None) -> tuple[list[tuple[str, np.ndarray]], dict[str, Any]]:
    """[(layer, (H, W, 3) image)], header of an R,G,B image or a buffer file."""
    channels, _ = B.read_channels(path)
    if all(c in channels for c in B.RGB):
        rgb, header = B.read_rgb(path)
        kind = ("denoised" if H_DENOISER in header else
                "single" if header.get("ppmrecon.layout") == "single" else "rgb")
        return [(kind, rgb)], header
    if not all(f"{e}.{c}" in channels for e in B.ESTIMATES for c in B.RGB):
        raise UsageError(f"{path}: neither an R,G,B image nor a buffer file (no R,G,B and no y/z1..z4 layers)")
    buf = B.read_buffers(path)
    wanted = layers or B.ESTIMATES
    return [(name, buf.estimates[B.ESTIMATES.index(name)]) for name in wanted], buf.header


def fit_reference(ref: np.ndarray, shape: tuple[int, int], ref_path: Path, path: Path) -> np.ndarray:
    """The reference at ``shape``: itself, or area-averaged from an integer multiple."""
    (h, w), (rh, rw) = shape, ref.shape[:2]
    if (rh, rw) == (h, w):
        return ref
    if rh * w != rw * h:
        raise UsageError(f"{ref_path}: reference is {rw}x{rh}, {path} is {w}x{h}: the aspect ratios differ")
    if rh < h or rh % h:
        raise UsageError(f"{ref_path}: reference is {rw}x{rh}, not an integer multiple of {path}'s {w}x{h}")
    return block_means(ref, rh // h)


def score(path: Path, layer: str, img: np.ndarray, ref: np.ndarray, header: dict[str, Any]) -> Score:
    """All scores of one image against its (same-size) reference."""
    small = min(img.shape[:2]) < BLOCK
    passes = header.get(B.H_PASSES)
    return Score(
        file=str(path), layer=layer, passes=int(passes) if passes is not None else None,
        method=header.get(B.H_METHOD), relmse=relmse(img, ref),
        relmse_8x8=None if small else relmse_blocks(img, ref, BLOCK),
        relmse_trimmed=relmse_trimmed(img, ref, TRIM),
        luminance_ratio=_finite_or_none(luminance_ratio(img, ref)))


def fit_slopes(scores: Sequence[Score], target: float | None = None) -> list[dict[str, Any]]:
    """Per series with at least two pass counts: the least-squares slope of log relMSE
    against log passes (-1 is the Monte Carlo rate; PPM's bias makes it shallower).
    With ``target``: ``reached_at``, the fewest measured passes whose relMSE is at most
    the target, and ``passes_for_target``, where the fitted line crosses it (None if the
    error does not fall)."""
    fits = []
    for series in dict.fromkeys(s.series for s in scores):
        pts = [(s.passes, s.relmse) for s in scores if s.series == series and s.passes and s.relmse > 0]
        if len({p for p, _ in pts}) < 2:
            continue
        x, y = np.log([p for p, _ in pts]), np.log([e for _, e in pts])
        slope, intercept = np.polyfit(x, y, 1)
        fit = {"series": series, "slope": float(slope), "intercept": float(intercept),
               "points": len(pts), "passes": [int(min(p for p, _ in pts)), int(max(p for p, _ in pts))]}
        if target is not None:
            fit["target"] = target
            fit["reached_at"] = min((p for p, e in pts if e <= target), default=None)
            fit["passes_for_target"] = (float(np.exp((np.log(target) - intercept) / slope))
                                        if slope < 0 else None)
        fits.append(fit)
    return fits


def _fmt(x: float | None, spec: str = ".4e") -> str:
    return "-" if x is None else format(x, spec)


def table(scores: Sequence[Score], fits: Sequence[dict[str, Any]]) -> str:
    """The plain-text table printed on stdout."""
    width = max([len("file")] + [len(s.file) for s in scores])
    lines = [f"{'file':<{width}}  {'layer':<8} {'passes':>6}  {'relMSE':>10}  {'8x8':>10}  {'trimmed':>10}  "
             f"{'lum.ratio':>9}"]
    for s in scores:
        lines.append(f"{s.file:<{width}}  {s.layer:<8} {s.passes if s.passes is not None else '-':>6}  "
                     f"{_fmt(s.relmse):>10}  {_fmt(s.relmse_8x8):>10}  {_fmt(s.relmse_trimmed):>10}  "
                     f"{_fmt(s.luminance_ratio, '.4f'):>9}")
    for f in fits:
        lines.append(f"slope of log relMSE vs log passes, {f['series']}: {f['slope']:.3f} "
                     f"({f['points']} files, passes {f['passes'][0]}..{f['passes'][1]})")
        if "target" in f:
            need = f["passes_for_target"]
            fitted = f"fit: ~{need:.0f} passes" if need is not None else "fit: never (the error does not fall)"
            beyond = " (extrapolated)" if need is not None and need > f["passes"][1] else ""
            measured = f"measured: {f['reached_at']} passes" if f["reached_at"] else "not reached in the files"
            lines.append(f"  relMSE {f['target']:g}: {measured}; {fitted}{beyond}")
    return "\n".join(lines)


# ------------------------------------------------------------------------------- plots

def _crop_box(text: str | None, shape: tuple[int, int]) -> tuple[int, int, int, int]:
    h, w = shape
    if text is None:  # the central square of half the shorter side
        side = max(1, min(h, w) // 2)
        return (w - side) // 2, (h - side) // 2, side, side
    m = re.fullmatch(r"\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*,\s*(\d+)\s*", text)
    if not m:
        raise UsageError(f"--crop '{text}': expected X,Y,W,H in pixels")
    x, y, cw, ch = map(int, m.groups())
    if cw <= 0 or ch <= 0 or x + cw > w or y + ch > h:
        raise UsageError(f"--crop {text}: outside the {w}x{h} image")
    return x, y, cw, ch


def _display(img: np.ndarray, scale: float) -> np.ndarray:
    """Linear radiance -> sRGB-ish display values in [0, 1] (exposure ``scale``)."""
    return np.clip(img * scale, 0.0, 1.0) ** (1.0 / 2.2)


def _save_figure(fig: Any, path: Path) -> None:
    atomic_write(path, lambda tmp: fig.savefig(tmp, format="png", dpi=110))


def plot(scores: Sequence[Score], fits: Sequence[dict[str, Any]], images: Sequence[np.ndarray],
         refs: Sequence[np.ndarray], out: Path, crop: str | None, ref_name: str) -> Path:
    """Write the error-vs-passes plot to ``out`` and the crop sheet beside it; returns
    the crop sheet's path."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise UsageError("--plot needs matplotlib (pip install 'ppmrecon[bench]')") from None

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    slope_of = {f["series"]: f for f in fits}
    for series in dict.fromkeys(s.series for s in scores):
        pts = sorted((s.passes, s.relmse) for s in scores if s.series == series and s.passes and s.relmse > 0)
        label = series
        line = ax.plot([p for p, _ in pts], [e for _, e in pts], "o-", label=label)[0]
        if series in slope_of:
            f = slope_of[series]
            xs = np.array(f["passes"], float)
            ax.plot(xs, np.exp(f["intercept"]) * xs ** f["slope"], "--", color=line.get_color(), alpha=0.6)
            line.set_label(f"{series}: slope {f['slope']:.2f}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("passes")
    ax.set_ylabel("relMSE")
    ax.set_title(f"relMSE against {ref_name}")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save_figure(fig, out)
    plt.close(fig)

    x, y, cw, ch = _crop_box(crop, images[0].shape[:2])
    panels = [(f"reference {ref_name}", refs[0])] + [
        (f"{Path(s.file).name} {s.layer}\nrelMSE {s.relmse:.3g}", img) for s, img in zip(scores, images)]
    ref_crop = refs[0][y:y + ch, x:x + cw]
    peak = float(np.percentile(luminance(ref_crop), 99)) if ref_crop.size else 0.0
    scale = 1.0 / peak if peak > 0 else 1.0  # one exposure for every panel
    cols = min(6, len(panels))
    rows = -(-len(panels) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(2.2 * cols, 2.8 * rows), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, (title, img) in zip(axes.ravel(), panels):
        if img.shape[:2] == images[0].shape[:2]:
            ax.imshow(_display(img[y:y + ch, x:x + cw], scale), interpolation="nearest")
        else:  # a file of another size: its own central crop
            bx, by, bw, bh = _crop_box(None, img.shape[:2])
            ax.imshow(_display(img[by:by + bh, bx:bx + bw], scale), interpolation="nearest")
        ax.set_title(title, fontsize=7)
    fig.suptitle(f"crop x={x} y={y} {cw}x{ch}", fontsize=8)
    fig.tight_layout()
    sheet = out.with_name(f"{out.stem}_crops{out.suffix}")
    _save_figure(fig, sheet)
    plt.close(fig)
    return sheet


# --------------------------------------------------------------------------------- CLI

def _layers(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    bad = [n for n in names if n not in B.ESTIMATES]
    if not names or bad:
        raise argparse.ArgumentTypeError(f"'{text}': choose from {', '.join(B.ESTIMATES)}")
    return names


def build_parser() -> ArgumentParser:
    p = ArgumentParser(
        prog=PROG, formatter_class=argparse.RawDescriptionHelpFormatter,
        description="Score RGB or buffer EXRs against a reference: relMSE, relMSE of 8x8 block means,\n"
                    "relMSE without the 0.1% largest pixel errors, and the mean luminance ratio.",
        epilog="examples:\n"
               "  ppmrecon-compare ref.exr out_denoised.exr\n"
               "  ppmrecon-compare ref.exr 'out_p*.exr' --layers z1 --plot errors.png --json errors.json\n"
               "  ppmrecon-compare ref.exr 'out_p*_denoised.exr' --target 0.01   # passes for relMSE 0.01")
    p.add_argument("reference", type=Path, metavar="REF.exr",
                   help="reference R,G,B EXR, the files' size or an integer multiple of it")
    p.add_argument("files", nargs="+", metavar="FILE.exr",
                   help="R,G,B images or buffer files; quoted glob patterns are expanded")
    p.add_argument("--layers", type=_layers, default=None, metavar="y,z1,...",
                   help="estimates of buffer files to score (default: all five)")
    p.add_argument("--json", nargs="?", const="-", default=None, metavar="OUT.json",
                   help="JSON instead of the table on stdout, or (with a file name) into that file as well")
    p.add_argument("--plot", type=Path, default=None, metavar="OUT.png",
                   help="PNG of relMSE against passes (log-log, fitted slopes) and OUT_crops.png")
    p.add_argument("--target", type=positive_float, default=None, metavar="RELMSE",
                   help="also say how many passes each series needs for this relMSE: the fewest measured, "
                        "and where the fitted log-log line crosses it")
    p.add_argument("--crop", default=None, metavar="X,Y,W,H",
                   help="crop of the sheet in pixels (default: the central square of half the shorter side)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    for out, suffix in ((args.plot, ".png"), (None if args.json in (None, "-") else Path(args.json), ".json")):
        if out is not None and (out.suffix.lower() != suffix or not out.parent.exists()):
            raise UsageError(f"{out}: expected a {suffix} file in an existing folder")
    ref_raw, _ = B.read_rgb(args.reference)
    files = [f for f in expand_paths(args.files, "EXR file") if f.resolve() != args.reference.resolve()]
    if not files:
        raise UsageError("no file to compare besides the reference")
    scores: list[Score] = []
    images: list[np.ndarray] = []
    refs: list[np.ndarray] = []
    fitted: dict[tuple[int, int], np.ndarray] = {}
    for path in files:  # everything is read and checked before anything is written
        layers, header = load_images(path, args.layers)
        shape = layers[0][1].shape[:2]
        if shape not in fitted:
            fitted[shape] = fit_reference(ref_raw, shape, args.reference, path)
        for layer, img in layers:
            scores.append(score(path, layer, img, fitted[shape], header))
            images.append(img)
            refs.append(fitted[shape])
    fits = fit_slopes(scores, args.target)
    if args.plot is not None:
        _crop_box(args.crop, images[0].shape[:2])  # a bad --crop fails before anything is written
        if not any(s.passes for s in scores):
            raise UsageError(f"--plot {args.plot}: no file records its pass count (ppmrecon.passes)")
    report = {"reference": str(args.reference), "block": BLOCK, "trim": TRIM,
              "scores": [asdict(s) for s in scores], "fits": fits}
    if args.json not in (None, "-"):
        write_text(args.json, json.dumps(report, indent=1))
    if args.plot is not None:
        sheet = plot(scores, fits, images, refs, args.plot, args.crop, args.reference.name)
        sys.stderr.write(f"{PROG}: wrote {args.plot} and {sheet}\n")
    print(json.dumps(report, indent=1) if args.json == "-" else table(scores, fits))
    return 0


def entry() -> None:
    """Console-script entry point."""
    raise SystemExit(run_main(PROG, main))


if __name__ == "__main__":  # pragma: no cover
    entry()
