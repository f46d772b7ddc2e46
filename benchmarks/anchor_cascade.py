"""A candidate, not shipped: the anchor's aim (and optionally the guide's source) chosen per pixel
by a cascade ~z^4 -> ~z^3 -> ~z^2 (issue 12, sixteenth session).

    .venv/bin/python benchmarks/anchor_cascade.py SET [--k K,...] [--speckle R] [--out DIR]

SET is ``study`` (the renders of ``benchmarks/results/guide_s16_far/cache`` against the 1024-pass
references of ``docs/cache``), ``study_n1024`` (``guide_s16_far_n1024/cache``, 4096-pass
references) or a generated data set folder. Why: on ``holdout_n1024_s16``'s ``0001_caustic_paths``
the wide estimates carry a bandwidth bias beside a bright caustic far above their noise, and the
shipped aim (``guide.anchor_target``: ~z^4, or ~z^3 where ~z^4's low-pass departs from ~z^3's)
follows them. The cascade takes one more step on the same test:

    t34, V34 = the shipped aim and its variance
    w = |D|^2 / (|D|^2 + k Var(G_sigma * ~z^2)),   D = G_sigma * (t34 - ~z^2)
        (Var with ~z^2's neighbour correlation, as the shipped anchor; w = 0 in a speckle field,
        :func:`ppmrecon.model.guide.speckle_field` at ratio R, where the guard's energy loss
        makes ~z^2's low-pass dark)
    t = t34 + w (~z^2 - t34),  V_t = V34 + w (V_2 - V34)

and the envelope anchors to t (``anchor``); ``both`` also gives OIDN the composite t (with V_t)
in place of ~z^4 as the guide's source. Consistent: t lies between estimates that converge to
the pixel's truth. Per set: relMSE / 8x8-block relMSE over the best single input (geometric
means), images worse than it, by N.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from ppmrecon import buffers as B  # noqa: E402
from ppmrecon.fileio import write_text  # noqa: E402
from ppmrecon.metrics import relmse, relmse_blocks  # noqa: E402
from range_oracle import data_renders, geomean, study_renders  # noqa: E402


def cascade(z: torch.Tensor, var: torch.Tensor, radii: torch.Tensor, t: torch.Tensor, vt: torch.Tensor,
            free: torch.Tensor | None, k: float, down: int, sigma: float, window: float, excess: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The aim t (B, 3, H, W) with variance vt stepped down ~z^2, ..., ~z^down, and the ~z^j with
    each pulled towards the final t by the weight the steps below it gave (the range's wide
    ends a biased estimate set). z (B, 4, 3, H, W); var, radii (B, 5, H, W) in schema order."""
    from ppmrecon.model.guard import correlated_lowpass_variance, gaussian_lowpass, noise_correlation

    pulled = torch.zeros_like(z[:, :, :1])
    for j in range(1, down - 2, -1):                        # z index: 1 = ~z^2, 0 = ~z^1
        vj = var[:, j + 1:j + 2].clamp(min=0.0)
        # a narrower kernel's variance of the mean grows as 1 / its area (a Poisson photon
        # density): where its passes missed the rare bright photons its sample variance reads low
        floor = vj
        for i in range(j + 2, var.shape[1]):
            ratio = (radii[:, i:i + 1] / radii[:, j + 1:j + 2].clamp(min=1e-30)).square()
            floor = torch.maximum(floor, torch.where(radii[:, j + 1:j + 2] > 0, var[:, i:i + 1].clamp(min=0.0) * ratio,
                                                     torch.zeros_like(vj)))
        noise = correlated_lowpass_variance(floor, noise_correlation(z[:, j], floor, window), sigma)
        d2 = gaussian_lowpass(t - z[:, j], sigma).square().mean(1, keepdim=True)
        tiny = torch.finfo(d2.dtype).tiny
        if excess:          # the share of the gap beyond k times its noise: 0 for a gap within the noise
            w = ((d2 - k * noise) / d2.clamp(min=tiny)).clamp(0.0, 1.0)
        else:               # the shipped anchor's soft weight: 1 / (1 + k) for a gap the size of the noise
            w = torch.where(d2 > 0, d2 / (d2 + k * noise).clamp(min=tiny), torch.zeros_like(d2))
        if free is not None:
            w = torch.where(free, torch.zeros_like(w), w)
        t, vt = torch.lerp(t, z[:, j], w), torch.lerp(vt, vj, w)
        pulled[:, j + 1:] = 1.0 - (1.0 - pulled[:, j + 1:]) * (1.0 - w[:, None])
    return t, vt, torch.lerp(z, t[:, None], pulled), pulled


def variants(buf: B.BufferFile, net, ks: list[float], downs: list[int], speckle: float,
             excess: bool = False, pull: bool = False) -> dict[str, np.ndarray]:
    """The shipped image and the cascade's (``k=K z^D``) for one render."""
    from ppmrecon.model.guard import guard_buffer, passes_of
    from ppmrecon.model.guide import anchor_target, envelope, speckle_field
    from ppmrecon.model.infer import _scale, buffer_envelope, buffer_guide

    guard, guide = net.guard, net.guide
    g = guard_buffer(buf, guard)
    scale = _scale(g)
    est = torch.from_numpy(np.ascontiguousarray(g.estimates, np.float32)).permute(0, 3, 1, 2)[None]
    var = torch.from_numpy(np.ascontiguousarray(g.variances, np.float32))[None]
    radii = torch.from_numpy(np.ascontiguousarray(g.radii, np.float32))[None]
    y, z = est[:, 0], est[:, 1:]
    t34, v34 = anchor_target(z, var[:, 3:4], var[:, 4:5], guide, guard.anchor)
    free = speckle_field(y, z, var, speckle) if speckle else None
    shipped_planes = buffer_guide(g, guide, guard, scale)
    out = {"shipped": buffer_envelope(g, shipped_planes, guard, guide, scale=scale).rgb}
    passes = passes_of(g)
    spikes = (var[:, :1], var[:, 4:5]) if guide.anchor_spikes else None
    for down in downs:
        for k in ks:
            t, vt, zr, pw = cascade(z, var, radii, t34, v34, free, k, down, guard.anchor, guide.anchor_window, excess)
            # OIDN's source is the aim t in place of ~z^4; the envelope's range is that of the
            # pulled estimates; its anchor aims at t
            e2, var2 = g.estimates.copy(), g.variances.copy()
            e2[4], var2[4] = t[0].permute(1, 2, 0).numpy(), vt[0, 0].numpy()
            planes = buffer_guide(replace(g, estimates=e2, variances=var2), guide, guard, scale)
            with _aim(t, vt):
                img = envelope(planes, y, zr, v34, guard, guide, scale, var[:, 4:5], passes, spikes, var)
            out[f"k={k:g} z^{down}"] = img[0].permute(1, 2, 0).numpy()
            if pull:        # the shipped guide and envelope on the buffer with the pulled ~z^j
                e3, var3 = g.estimates.copy(), g.variances.copy()
                e3[1:] = zr[0].permute(0, 2, 3, 1).numpy()
                var3[1:] = torch.lerp(var[0, 1:], vt[0], pw[0, :, 0]).numpy()
                pulled = replace(g, estimates=e3, variances=var3)
                out[f"k={k:g} z^{down} pull"] = buffer_envelope(pulled, buffer_guide(pulled, guide, guard, scale), guard,
                                                                guide, scale=scale).rgb
                with _aim(t, vt):       # the shipped guide (OIDN of ~z^4), the cascade's range and aim
                    img = envelope(shipped_planes, y, zr, v34, guard, guide, scale, var[:, 4:5], passes, spikes, var)
                out[f"k={k:g} z^{down} keep"] = img[0].permute(1, 2, 0).numpy()
    return out


@contextlib.contextmanager
def _aim(t: torch.Tensor, vt: torch.Tensor):
    """:func:`ppmrecon.model.guide.envelope` with its anchor aim replaced by (t, vt)."""
    import ppmrecon.model.guide as G

    shipped = G.anchor_target
    G.anchor_target = lambda *args, **kw: (t, vt)
    try:
        yield
    finally:
        G.anchor_target = shipped


def renders(which: str):
    """(label, passes, buffer, reference) of a set (see the module docstring)."""
    if which in ("study", "study_n1024"):
        cache, ref_passes = ("guide_s16_far", 1024) if which == "study" else ("guide_s16_far_n1024", 4096)
        return study_renders(ROOT / "benchmarks" / "results" / cache / "cache", ROOT / "docs" / "cache", ref_passes)
    return data_renders(Path(which))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("set", help="study, study_n1024, or a generated data set folder")
    ap.add_argument("--k", default="4", help="comma-separated noise multiples k (default 4)")
    ap.add_argument("--speckle", type=float, default=0.5, help="speckle-field ratio R (0: no exclusion)")
    ap.add_argument("--down", default="2", help="comma-separated lowest steps D of the cascade, ~z^D (default 2)")
    ap.add_argument("--excess", action="store_true", help="weigh only the gap beyond k times its noise")
    ap.add_argument("--pull", action="store_true", help="also the shipped pipeline on the pulled estimates")
    ap.add_argument("--out", type=Path, default=ROOT / "benchmarks" / "results" / "anchor_cascade")
    args = ap.parse_args()
    from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint

    net = load_checkpoint(DEFAULT_MODEL).model
    ks = [float(k) for k in args.k.split(",")]
    downs = [int(d) for d in args.down.split(",")]
    rows: dict[int, dict[str, list[tuple[float, float]]]] = {}
    per_image = []
    for label, n, buf, ref in renders(args.set):
        best = min(relmse(e, ref) for e in buf.estimates)
        best8 = min(relmse_blocks(e, ref) for e in buf.estimates)
        scores = {k: (relmse(img, ref) / best, relmse_blocks(img, ref) / best8)
                  for k, img in variants(buf, net, ks, downs, args.speckle, args.excess, args.pull).items()}
        for k, v in scores.items():
            rows.setdefault(n, {}).setdefault(k, []).append(v)
        per_image.append(f"| {label} | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in scores.values()) + " |")

    def cell(v: list[tuple[float, float]]) -> str:
        return f"{geomean([a for a, _ in v]):.3f} / {geomean([b for _, b in v]):.3f}, {sum(a > 1 for a, _ in v)} worse"

    names = list(next(iter(rows.values())))
    both = {k: [x for n in rows for x in rows[n][k]] for k in names}
    name = Path(args.set).name
    lines = [f"# The anchor's aim by a cascade ~z^4 -> ~z^3 -> ~z^2: `{name}` (issue 12, not shipped)", "",
             f"Generated by `benchmarks/anchor_cascade.py {args.set} --k {args.k} --speckle {args.speckle:g} --down {args.down}"
             + (" --excess" if args.excess else "") + "`. "
             "relMSE / 8x8-block relMSE over the best single input, geometric means, and images worse than it.", "",
             "| N | " + " | ".join(names) + " |", "|---|" + "---|" * len(names),
             "| all | " + " | ".join(cell(both[k]) for k in names) + " |"]
    lines += [f"| {n} | " + " | ".join(cell(rows[n][k]) for k in names) + " |" for n in sorted(rows)]
    lines += ["", "| image | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)] + per_image
    args.out.mkdir(parents=True, exist_ok=True)
    write_text(args.out / f"{name}.md", "\n".join(lines) + "\n")
    print("\n".join(lines[:6 + len(rows) + 1]))


if __name__ == "__main__":
    from ppmrecon.errors import UsageError

    try:
        main()
    except UsageError as exc:                               # a missing data set or manifest: one line
        sys.exit(f"anchor_cascade: {exc}")
