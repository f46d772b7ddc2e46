"""Ship a trained run as the package's default model, with its model card.

    .venv/bin/python scripts/ship_model.py runs/cpu_tiny [--checkpoint best.pt]

Copies the run's checkpoint to ``ppmrecon/data/models/default.pt`` and writes
``default.md`` (the model card) and ``default_validation.png`` from the run's
``history.json``, its checkpoint metadata and the data set's manifest: every figure in
the card comes from those files.

    .venv/bin/python scripts/ship_model.py --guide-y-weight 2 --bench guide.json
    .venv/bin/python scripts/ship_model.py --chooser runs/chooser/chooser.pt --bench guide.json

Without a run: re-ships the current ``default.pt`` with changed guide settings (same
network weights); its card keeps what came from the training run and gets the new
shipped-reconstruction row, the command, and the held-out figures of ``--bench``.
``--chooser`` attaches the chooser of a ``ppmrecon-train chooser`` run (trained on this
default's guard and guide) and sets the guide to mode "chooser" (unless ``--guide-mode`` says
otherwise: ``--guide-mode envelope`` ships it opt-in); the card gets its row.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ppmrecon.fileio import write_text  # noqa: E402
from ppmrecon.model.checkpoint import DEFAULT_MODEL, load_checkpoint, save_checkpoint  # noqa: E402
from ppmrecon.model.chooser import CANDIDATES  # noqa: E402
from ppmrecon.model.guard import GuardConfig  # noqa: E402
from ppmrecon.model.guide import ALBEDO_CHANNELS, DENOISERS, ENVELOPE_MODES, GUIDE_MODES, GuideConfig  # noqa: E402
from ppmrecon.model.kpn import parameter_count  # noqa: E402


#: The numeric settings a reship may change: (option, metavar, help, config ("guide" or
#: "guard"), that config's key).
RESHIP_NUMBERS = (
    ("--guide-y-weight", "F", "ship with this weight of OIDN's image of ~y in the guide (GuideConfig.y_weight)",
     "guide", "y_weight"),
    ("--guide-cross", "C", "ship with the guide's cross rule at C (GuideConfig.cross; 0 = off)", "guide", "cross"),
    ("--guide-y-spike", "R", "ship with ~y left out of the envelope's range where it is a lone spike R x above "
                             "every ~z^j and its 3 x 3 median (GuideConfig.y_spike; 0 = off)", "guide", "y_spike"),
    ("--guide-z-spike", "R", "ship with a pixel held at ~y where its four ~z^j are a lone spike over a settled ~y, "
                             "each R x above it (GuideConfig.z_spike; 0 = off)", "guide", "z_spike"),
    ("--guide-anchor-free", "R", "ship with the anchored value of a pixel whose five estimates are all unsettled at R "
                                 "held in the range widened to its neighbourhood's (GuideConfig.anchor_free; 0 = off)",
     "guide", "anchor_free"),
    ("--guide-anchor-window", "W", "ship with the anchor's noise correlation estimated over a W px window "
                                   "(GuideConfig.anchor_window; 0 = independent pixels)", "guide", "anchor_window"),
    ("--guide-anchor-settled", "R", "ship with the anchor acting only where its low-pass is settled, its "
                                    "standard deviation below R x its level (GuideConfig.anchor_settled; 0 = off)",
     "guide", "anchor_settled"),
    ("--guide-anchor-source", "M", "ship with the envelope's low-frequency anchor aimed at ~z^M, M = 1..4 "
                                   "(GuideConfig.anchor_source)", "guide", "anchor_source"),
    ("--guide-anchor-select", "K", "ship with the envelope's anchor aimed per pixel between ~z^m and the wider "
                                   "~z^(m+1), at the wider one where their low-passes agree within K x ~z^m's "
                                   "noise (GuideConfig.anchor_select; 0 = off)", "guide", "anchor_select"),
    ("--guide-terms-passes", "M", "ship with the envelope's range widened towards Eq. 6's terms over a 3 x 3 "
                                  "window by the share 1 / (1 + N / M) for N passes (GuideConfig.terms_passes; "
                                  "0 = off)", "guide", "terms_passes"),
    ("--guide-anchor-spikes", "R", "ship with the envelope's anchor kept from spreading the gap of an isolated "
                                   "bright pixel of its aim (R x above its 3 x 3 median), that pixel set to the "
                                   "inverse-variance mean of ~y and ~z^4 (GuideConfig.anchor_spikes; 0 = off)",
     "guide", "anchor_spikes"),
    ("--guide-y-found", "S", "ship with ~y's share in the guide scaled by the share of pixels, over a Gaussian "
                             "of S px, where ~y is not sparser than ~z^4 (GuideConfig.y_found; 0 = off)", "guide", "y_found"),
    ("--guide-redistribute", "S", "ship with what the envelope's final clamp took given back to the pixels around, "
                                  "over a Gaussian of S px, within their ranges (GuideConfig.redistribute; 0 = off)",
     "guide", "redistribute"),
    ("--guide-y-empty", "S", "ship with ~y's share in the guide scaled by the share of pixels, over a Gaussian "
                             "of S px, where ~y did not read 0 while ~z^4 rests on more than one event "
                             "(GuideConfig.y_empty; 0 = off)", "guide", "y_empty"),
    ("--guide-cascade", "K", "ship with the envelope's anchor aim stepped on down to ~z^2 and ~z^1 where the wider "
                             "estimates' bandwidth bias shows beyond K x the narrower one's noise, the range's wide "
                             "ends pulled to it and OIDN given it in place of ~z^4 (GuideConfig.cascade; 0 = off)",
     "guide", "cascade"),
    ("--guide-cascade-passes", "N", "ship with renders of fewer than N passes run without the cascade "
                                    "(GuideConfig.cascade_passes; 0 = every N)", "guide", "cascade_passes"),
    ("--guide-cascade-y", "K", "ship with the cascade's aim taken one step further, to ~y, where their "
                               "low-passes differ by more than K x ~y's noise and ~z^1 departs the same way "
                               "(GuideConfig.cascade_y; 0 = off)", "guide", "cascade_y"),
    ("--guide-cascade-y-up", "M", "ship with renders of fewer than M passes taking the cascade's step to ~y "
                                  "down only (GuideConfig.cascade_y_up; 0 = up and down at every N)",
     "guide", "cascade_y_up"),
    ("--guide-nlm-k", "K", "ship with NL-means' tolerance K for the source (GuideConfig.nlm_k: renders below "
                           "nlm_joint_passes and from nlm_y_passes)", "guide", "nlm_k"),
    ("--guide-nlm-y-passes", "M", "ship with renders of at least M passes denoising ~y by NL-means too "
                                  "(GuideConfig.nlm_y_passes, with denoiser nlm_source; 0 = never)",
     "guide", "nlm_y_passes"),
    ("--guide-nlm-y-k", "K", "ship with NL-means' tolerance K for ~y (GuideConfig.nlm_y_k; 0 = nlm_k)",
     "guide", "nlm_y_k"),
    ("--guide-nlm-joint-passes", "M", "ship with renders of at least M passes (and fewer than nlm_y_passes) "
                                      "denoising the source and ~y by one NL-means with joint weights "
                                      "(GuideConfig.nlm_joint_passes; 0 = never)",
     "guide", "nlm_joint_passes"),
    ("--guide-nlm-joint-k", "K", "ship with the joint NL-means' tolerance K (GuideConfig.nlm_joint_k; 0 = nlm_k)",
     "guide", "nlm_joint_k"),
    ("--guide-nlm-albedo", "F", "ship with NL-means also measuring each pair on the albedo-demodulated images, "
                                "counted F times, and keeping the smaller distance (GuideConfig.nlm_albedo; "
                                "0 = off)", "guide", "nlm_albedo"),
    ("--guide-nlm-albedo-eps", "E", "ship with E added to the albedo before the demodulation divides by it "
                                    "(GuideConfig.nlm_albedo_eps)", "guide", "nlm_albedo_eps"),
    ("--guide-range-sigma", "K", "ship with each pixel's envelope range widened to every estimate +- K times its "
                                 "standard deviation of the mean (GuideConfig.range_sigma; 0 = off)",
     "guide", "range_sigma"),
    ("--guide-range-sigma-rel", "R", "ship with only estimates of standard deviation <= R x their level widened "
                                     "(GuideConfig.range_sigma_rel; 0 = every estimate)", "guide", "range_sigma_rel"),
    ("--guide-range-sigma-width", "W", "ship with only pixels whose bare range is <= W x the widest estimate's "
                                       "standard deviation widened (GuideConfig.range_sigma_width; 0 = every "
                                       "pixel)", "guide", "range_sigma_width"),
    ("--guide-range-sigma-isolated", "F", "ship with no widening where the widest estimate is above F x its own "
                                          "3 x 3 median (GuideConfig.range_sigma_isolated; 0 = no test)",
     "guide", "range_sigma_isolated"),
    ("--guide-anchor-free-dark", "D", "ship with a pixel whose ~z^4 reads at most D x the guard's floor x the "
                                      "image's scale counted dark, not a speckle (GuideConfig.anchor_free_dark; "
                                      "0 = only an empty ~z^4)", "guide", "anchor_free_dark"),
    ("--guard-confirm", "C", "ship with the guard's confirmation by hit point B at factor C "
                             "(GuardConfig.confirm; 0 = off)", "guard", "confirm"),
    ("--guard-peers", "M", "ship with the guard's speckle-field test: no outlier where M unsettled pixels of "
                           "its 5 x 5 window are within 4x of it (GuardConfig.peers; 0 = off)", "guard", "peers"),
    ("--guard-mutual", "R", "ship with the guard's mutual confirmation: no outlier where ~y and a ~z^j of the "
                            "pixel each have sqrt(V)/mean < R and lie within the confirm factor of each other "
                            "(GuardConfig.mutual; 0 = off)", "guard", "mutual"),
    ("--guard-edge", "E", "ship with the guard's light-edge rule: no outlier where a settled pixel of its 3 x 3 "
                          "window is at least E x its value (GuardConfig.edge; 0 = off)", "guard", "edge"),
    ("--guard-events", "K", "ship with the guard's confirmation by events: no outlier where ~y and a ~z^j of the "
                            "pixel both saw the light, lie within the confirm factor of each other and rest on K "
                            "passes' events together (GuardConfig.events; 0 = off)", "guard", "events"),
)

#: Settings of :data:`RESHIP_NUMBERS` that are indices, not numbers: parsed as integers.
INTEGER_KEYS = frozenset({"anchor_source"})


def reship_values(args: argparse.Namespace, config: str) -> list[tuple[str, float, str]]:
    """(key, value, option) of the numeric settings this command changes in ``config``."""
    return [(key, getattr(args, _dest(flag)), flag) for flag, _, _, cfg, key in RESHIP_NUMBERS
            if cfg == config and getattr(args, _dest(flag)) is not None]


def changed(cfg, values: list[tuple[str, float, str]]):
    """``cfg`` (a guide or guard config) with ``values`` (:func:`reship_values`); a value the
    config refuses is one line naming the option."""
    for key, value, option in values:
        try:
            cfg = replace(cfg, **{key: value})
        except ValueError as exc:
            sys.exit(f"ship_model: {option}: {exc}")
    return cfg


def _dest(flag: str) -> str:
    """argparse's attribute name of an option: --guide-y-weight -> guide_y_weight."""
    return flag[2:].replace("-", "_")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path, nargs="?", default=None,
                    help="run folder of `ppmrecon-train fit` (omit to re-ship the current default with "
                         "changed guide settings)")
    ap.add_argument("--checkpoint", default="best.pt")
    ap.add_argument("--guide-mode", choices=GUIDE_MODES, default=None,
                    help="ship with the denoiser guide in this mode (default: as trained); the choice "
                         "should come from held-out figures: give them with --bench")
    ap.add_argument("--guide-denoiser", choices=DENOISERS, default=None,
                    help="ship with this denoiser for the guide's images (GuideConfig.denoiser: oidn, nlm, "
                         "nlm_source); the choice should come from held-out figures: give them with --bench")
    ap.add_argument("--guide-nlm-albedo-channels", choices=ALBEDO_CHANNELS, default=None,
                    help="ship with NL-means' albedo demodulation dividing by the albedo's RGB mean or each "
                         "channel by its own (GuideConfig.nlm_albedo_channels)")
    ap.add_argument("--bench", type=Path, action="append", default=None,
                    help="a benchmarks/bench_guide.py result (guide.json) whose summary rows go into the card "
                         "(repeatable: one table each, e.g. the training data and a hold-out set)")
    ap.add_argument("--chooser", type=Path, default=None, metavar="CKPT",
                    help="attach the chooser of this `ppmrecon-train chooser` result (its chooser.pt) and "
                         "ship in guide mode 'chooser'")
    for flag, metavar, text, _, key in RESHIP_NUMBERS:
        ap.add_argument(flag, type=int if key in INTEGER_KEYS else float, default=None, metavar=metavar, help=text)
    args = ap.parse_args()
    for path in args.bench or ():              # checked before anything is written
        try:
            bench = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            sys.exit(f"ship_model: --bench {path}: not a readable bench_guide.py result ({exc.__class__.__name__})")
        if not isinstance(bench, dict) or "summary_validation" not in bench:
            sys.exit(f"ship_model: --bench {path}: not a bench_guide.py result (no summary rows)")
    if args.run is None:
        reship(args)
        return
    if reship_values(args, "guard"):
        sys.exit(f"ship_model: {reship_values(args, 'guard')[0][2]} changes a shipped default: ship {args.run} "
                 "first, then re-ship with it (no run folder)")
    ckpt_path = args.run / args.checkpoint
    ckpt = load_checkpoint(ckpt_path)
    history = json.loads((args.run / "history.json").read_text())
    meta = ckpt.meta
    data = Path(meta["data"])
    manifest = json.loads((data / "manifest.json").read_text())
    cfg = manifest["config"]
    planned = manifest["scenes"]
    scenes = [s for s in planned if (data / s["id"] / "reference.exr").is_file()]   # complete ones
    n_train = sum(s["split"] == "train" for s in scenes)
    n_val = len(scenes) - n_train
    families = sorted({s["family"] for s in scenes})
    worker_seconds = sum(s.get("seconds", 0.0) for s in scenes)
    agreements = sorted(s["agreement"]["relmse"] for s in scenes if s.get("agreement"))
    epochs = meta["epochs"]
    train_seconds = sum(h["seconds"] for h in history[:epochs])
    v = meta["val"]

    DEFAULT_MODEL.parent.mkdir(parents=True, exist_ok=True)
    trained_guide = ckpt.model.guide
    shipped_guide = changed_guide(trained_guide, args, ckpt_path)
    if shipped_guide != trained_guide:
        ckpt.model.guide = shipped_guide
        save_checkpoint(DEFAULT_MODEL, ckpt.model, {**meta, "trained_guide": trained_guide.to_dict()})
    else:
        shutil.copyfile(ckpt_path, DEFAULT_MODEL)

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 3.4))
    ep = [h["epoch"] for h in history]
    ax.plot(ep, [h["val"]["output"] for h in history], "o-", ms=3, label="model (validation relMSE)")
    ax.plot(ep, [h["val"]["best_single"] for h in history], "--", label="best single input")
    ax.set_yscale("log")
    ax.set_xlabel("epoch")
    ax.legend(fontsize=8)
    val_n = history[-1]["val_passes"] or "every N"
    ax.set_title(f"{meta['preset']} on {data.name}: validation at N = {val_n}", fontsize=9)
    fig.tight_layout()
    fig.savefig(DEFAULT_MODEL.with_name("default_validation.png"), dpi=110)

    tc = meta["train_config"]
    bound = tc.get("max_reference_disagreement")
    dropped = [f"{s['id']} ({s['agreement']['relmse_trimmed']:.2g})" for s in scenes
               if bound is not None and s.get("agreement") and s["agreement"]["relmse_trimmed"] > bound]
    lines = [
        "# Model card: `default.pt`", "",
        f"The model `ppmrecon-denoise` uses when `--model` is not given. Written by "
        f"`scripts/ship_model.py {args.run}"
        + (f" --checkpoint {args.checkpoint}" if args.checkpoint != "best.pt" else "")
        + command_flags(args) + "` from the run's files.", "",
        "| | |", "|---|---|",
        f"| architecture | preset `{meta['preset']}`: {ckpt.model.preset.layers} conv layers, "
        f"{ckpt.model.preset.filters} filters {ckpt.model.preset.kernel}x{ckpt.model.preset.kernel}, "
        f"window K = {ckpt.model.preset.window}, {parameter_count(ckpt.model)} parameters |",
        f"| inputs | {ckpt.model.features.n_channels} channels (5 estimates, 5 variances, albedo, normal, depth; "
        f"optional features {ckpt.model.features.to_dict()}), SPPM buffer files |",
        f"| firefly guard | {ckpt.model.guard.to_dict()} (ppmrecon/model/guard.py; applied in training as at inference) |",
        (f"| denoiser guide | {trained_guide.to_dict()} in training (ppmrecon/model/guide.py: OIDN of "
         f"~z^{trained_guide.source} sets prior logits; the network's logits are a correction to them) |"
         if trained_guide.enabled else "| denoiser guide | off |"),
        *shipped_row(ckpt.model.guide),
        f"| data set | `{data}`: {len(scenes)} complete generated scenes of {len(planned)} planned "
        f"({', '.join(families)}), {n_train} train / {n_val} validation (split by scene), "
        f"{cfg['resolution'][0]}x{cfg['resolution'][1]} px |",
        f"| left out | {', '.join(dropped) or 'nothing'} (`max_reference_disagreement` = "
        f"{tc.get('max_reference_disagreement')}: references not converged) |",
        f"| inputs per scene | N = {', '.join(map(str, cfg['input_passes']))} passes x seeds {cfg['seeds']}, "
        f"{cfg['photons']} photons/pass; {meta['train_images']} training images |",
        f"| references | single-bandwidth SPPM, {cfg.get('references', 1)} independent render(s) of "
        f"{cfg['reference_passes']} passes x {cfg['reference_photons']} photons"
        + (f"; agreement of the two (relMSE of one against the other; the mean's own error is about a quarter): "
           f"median {agreements[len(agreements) // 2]:.2g}, worst {agreements[-1]:.2g}" if agreements else "") + " |",
        f"| data generation | {worker_seconds / 3600:.1f} worker-hours on a shared 2-core CPU "
        f"(sum of the complete scenes' render times) |",
        f"| training | Adam lr {tc['lr']}, batch {tc['batch']} x {tc['patch']}x{tc['patch']} patches, "
        f"{tc['steps_per_epoch']} steps/epoch, {epochs} epochs (checkpoint `{args.checkpoint}`), "
        f"{train_seconds / 60:.1f} min wall on 2 shared CPU cores, D4 augmentation |",
        f"| validation (N = {val_n}) | mean relMSE {v['output']:.4f} vs best single input "
        f"{v['best_single']:.4f} (~{v['best_single_name']}): {v['ratio']:.2f}x"
        + (f"; per image (geometric mean of ours / that image's best input): {v['image_ratio']:.3f}x"
           if "image_ratio" in v else "") + f"; `best.pt` picked by `{tc.get('select', 'relmse')}` |", "",
        "![validation curve](default_validation.png)", "",
        "| epoch | train loss (Eq. 8) | validation relMSE | best single input |", "|---|---|---|---|",
    ]
    alone = args.run / "guide_alone.json"
    if alone.is_file():
        a = json.loads(alone.read_text())["val"]
        lines.append(f"| 0 (the guide alone, untrained head) | - | {a['output']:.4f} | {a['best_single']:.4f} |")
    sets = []
    for h in history:
        lines.append(f"| {h['epoch']} | {h['loss']:.4f} | {h['val']['output']:.4f} | {h['val']['best_single']:.4f} |")
        key = tuple(h.get("val_images") or ())
        if not sets or sets[-1][1] != key:
            sets.append((h["epoch"], key))
    if len(sets) > 1:
        lines += ["", "The validation set changed during training (the run was resumed on a data set that had "
                  "grown): from epoch " + ", from epoch ".join(f"{e}: {len(k) or 'unrecorded'} images" for e, k in sets)
                  + "; `best.pt` compares only epochs validated on the same images."]
    for path in args.bench or ():
        lines += ["", *bench_lines(path)]
    lines += ["", f"Limits: trained on SPPM inputs only, on generated scenes at {cfg['resolution'][0]}x"
              f"{cfg['resolution'][1]}; the literature scenes of ../shared were never seen. Held-out numbers: "
              "benchmarks/results/guide/guide.md, quality.md, curves.md, guard.md, anchor.md."]
    write_text(DEFAULT_MODEL.with_name("default.md"), "\n".join(lines) + "\n")
    print(f"shipped {ckpt_path} -> {DEFAULT_MODEL} ({DEFAULT_MODEL.stat().st_size / 1024:.0f} KB)")


def changed_guide(guide: GuideConfig, args: argparse.Namespace, source: Path,
                  mode: str | None = None) -> GuideConfig:
    """``guide`` with the settings the command line changes (the mode and the guide's
    numeric settings of :data:`RESHIP_NUMBERS`); ``mode``: the mode when --guide-mode does
    not give one."""
    mode = args.guide_mode or mode
    values = reship_values(args, "guide")
    if args.guide_denoiser is not None:
        values.append(("denoiser", args.guide_denoiser, "--guide-denoiser"))
    if args.guide_nlm_albedo_channels is not None:
        values.append(("nlm_albedo_channels", args.guide_nlm_albedo_channels, "--guide-nlm-albedo-channels"))
    if (mode or values) and not guide.enabled:
        sys.exit(f"ship_model: {source} was trained without the guide: no guide setting to change")
    if mode and mode != guide.mode:
        guide = guide.in_mode(mode)
    return changed(guide, values)


def command_flags(args: argparse.Namespace) -> str:
    """The guide and bench flags of this command, as the card quotes them."""
    numbers = "".join(f" {flag} {getattr(args, _dest(flag)):g}" for flag, *_ in RESHIP_NUMBERS
                      if getattr(args, _dest(flag)) is not None)
    return ((f" --guide-mode {args.guide_mode}" if args.guide_mode else "")
            + (f" --guide-denoiser {args.guide_denoiser}" if args.guide_denoiser else "")
            + (f" --guide-nlm-albedo-channels {args.guide_nlm_albedo_channels}"
               if args.guide_nlm_albedo_channels else "") + numbers
            + (f" --chooser {args.chooser}" if args.chooser is not None else "")
            + "".join(f" --bench {path}" for path in args.bench or ()))


def chooser_row(model, meta: dict) -> list[str]:
    """The card's "chooser" row: its architecture, data, training and validation figures;
    whether it runs by default or only with ``--guide-mode chooser``."""
    if model.chooser is None or not model.guide.enabled:
        return []
    info = meta.get("chooser", {})
    cfg, val = info.get("config", {}), info.get("validation") or {}
    params = sum(p.numel() for p in model.chooser.parameters())
    how = "runs by default" if model.guide.mode == "chooser" else "opt-in: `ppmrecon-denoise --guide-mode chooser`"
    row = (f"| chooser | {how}; {model.chooser.cfg.to_dict()}, {params} parameters (ppmrecon/model/chooser.py: softmax "
           f"weights per pixel over {', '.join(CANDIDATES)}, each held in the five estimates' range); trained by "
           f"`ppmrecon-train chooser` on `{info.get('data', '?')}` ({info.get('train_images', '?')} training images, "
           f"{cfg.get('steps', '?')} steps of {cfg.get('batch', '?')} x {cfg.get('crop', '?')} px crops, "
           f"{info.get('seconds', 0) / 60:.1f} min)")
    if val:
        c, e = val["chooser"], val["envelope"]
        row += (f"; validation split ({val['images']} images, never trained on): {c['ratio']:.3f} of the best "
                f"input (envelope {e['ratio']:.3f}), 8x8 {c['ratio_8x8']:.3f} ({e['ratio_8x8']:.3f}), worse than "
                f"the best input {c['worse']} ({e['worse']})")
    return [row + "; on other scenes: the held-out table below (`NAME chooser` rows) |"]


def shipped_row(guide: GuideConfig) -> list[str]:
    """The card's "shipped reconstruction" row (envelope and chooser modes)."""
    if not (guide.enabled and guide.mode in ENVELOPE_MODES):
        return []
    nlm = (f"the variance-normalised NL-means (Rousselle et al. 2012; k = {guide.nlm_k:g}, a "
           f"{2 * int(guide.nlm_radius) + 1} x {2 * int(guide.nlm_radius) + 1} px window)")
    images = {"oidn": f"OIDN's images of ~z^{guide.source} and ~y",
              "nlm": f"{nlm}'s images of ~z^{guide.source} and ~y",
              "nlm_source": f"{nlm}'s image of ~z^{guide.source} and OIDN's of ~y"
              + (f" (NL-means' of ~y too from N = {guide.nlm_y_passes:g} passes)" if guide.nlm_y_passes else "")
              }[guide.denoiser] + (f"; NL-means' k for ~y {guide.nlm_y_k:g}" if guide.nlm_y_k else "")
    if guide.nlm_joint_passes and guide.denoiser != "oidn":
        images += (f"; from N = {guide.nlm_joint_passes:g} passes"
                   + (f" to N = {guide.nlm_y_passes:g}" if guide.nlm_y_passes else "")
                   + " the source and ~y denoised together by one NL-means with joint weights (k = "
                   f"{guide.nlm_joint_k or guide.nlm_k:g})")
    if guide.nlm_albedo and guide.denoiser != "oidn":
        images += (f"; each NL-means pair also measured on the images divided by the albedo (its RGB mean + "
                   f"{guide.nlm_albedo_eps:g}), counted {guide.nlm_albedo:g} times, the smaller distance kept")
    mixed = (f"{images} mixed by the inverse of their inputs' local variances, "
             f"~y's times {guide.y_weight:g}"
             + (f" (and by the share of pixels, over {guide.y_empty:g} px, where ~y did not read 0 while "
                f"~z^{guide.source} rests on more than one photon event)" if guide.y_empty else "")
             if guide.y_weight else f"OIDN's image of ~z^{guide.source}")
    chooser = ("; then the chooser (row below) mixes that envelope per pixel with other images held in the "
               "same range (`--guide-mode envelope`: the envelope alone)" if guide.mode == "chooser" else "")
    return [f"| shipped reconstruction | guide mode `{guide.mode}` ({guide.to_dict()}): {mixed}, held inside the "
            "range of each pixel's five estimates"
            + (f" (of its four ~z^j alone where ~y is a lone spike, {guide.y_spike:g}x above them and its 3 x 3 median)"
               if guide.y_spike else "")
            + (f" (of ~y alone where the four ~z^j are a lone spike over a settled ~y, each {guide.z_spike:g}x above "
               "it, none settled)" if guide.z_spike else "")
            + (f", widened towards the range of Eq. 6's terms over its 3 x 3 window by the share 1 / (1 + N / "
               f"{guide.terms_passes:g}) for N passes (each end by at most the range's width)"
               if guide.terms_passes else "")
            + (f", and to hold each estimate +- {guide.range_sigma:g} x its standard deviation of the mean"
               + (f" (of the estimates whose standard deviation is at most {guide.range_sigma_rel:g} x their level)"
                  if guide.range_sigma_rel else "")
               + (f", where the bare range is at most {guide.range_sigma_width:g} x the widest estimate's standard "
                  "deviation" if guide.range_sigma_width else "")
               + (f", not where the widest estimate is above {guide.range_sigma_isolated:g} x its own 3 x 3 median "
                  "(an isolated sparkle)" if guide.range_sigma_isolated else "") if guide.range_sigma else "")
            + ", anchored at low frequencies to "
            + (f"~z^{guide.anchor_source + 1} where its low-pass agrees with ~z^{guide.anchor_source}'s within "
               f"{guide.anchor_select:g} x the latter's noise, else to ~z^{guide.anchor_source} (per pixel),"
               if guide.anchor_select and guide.anchor_source < 4 else f"~z^{guide.anchor_source}")
            + (f" and on down to ~z^{guide.anchor_source - 1}..~z^1 where that aim's low-pass departs from the "
               f"narrower estimate's by more than {guide.cascade:g} x the latter's noise (a wide kernel's bandwidth "
               "bias beside a bright caustic), the wider ~z^j of the range pulled to that aim by as much and "
               f"OIDN given it in place of ~z^{guide.source}"
               + (f", and on to ~y where ~z^1 departs the same way and their low-passes differ by more than "
                  f"{guide.cascade_y:g} x ~y's noise (floored by what the ~z^j predict for it)"
                  + (f" (below N = {guide.cascade_y_up:g} passes only where ~y lies below the aim)"
                     if guide.cascade_y_up else "") if guide.cascade_y else "")
               + (f" (from N = {guide.cascade_passes:g} passes)" if guide.cascade_passes else "") + ","
               if guide.cascade else "")
            + " where they differ by more than its noise"
            + (f" (its neighbour correlation estimated over {guide.anchor_window:g} px)" if guide.anchor_window else "")
            + (f" where its low-pass is settled (standard deviation < {guide.anchor_settled:g} x its level)"
               if guide.anchor_settled else "")
            + (f", isolated bright pixels of the anchor's aim ({guide.anchor_spikes:g}x above its 3 x 3 median) "
               "left out of its low-pass and set to the inverse-variance mean of ~y and ~z^4"
               if guide.anchor_spikes else "")
            + (f", held where all five estimates are unsettled at {guide.anchor_free:g} (a photon speckle field) "
               "in its range widened to the 5 x 5 medians of its ends"
               + (f" (not where ~z^4 reads at most {guide.anchor_free_dark:g} x the guard's floor x the image's "
                  "scale: a dark pixel)" if guide.anchor_free_dark else "") if guide.anchor_free else "")
            + (f", what the final clamp took given back to the pixels around over a Gaussian of "
               f"{guide.redistribute:g} px, each within its own range" if guide.redistribute else "")
            + f"{chooser}; the Eq. 6 network is "
            "not run (`ppmrecon-denoise --guide-mode weights` runs it, with this guide as the prior of Eq. 6) |"]


def bench_lines(path: Path) -> list[str]:
    """The card's held-out table from a ``bench_guide.py`` result: the shipped model's rows
    (its name given with --model) and OIDN's image of ~z^4 beside them."""
    bench = json.loads(path.read_text())
    lines = [f"Held-out figures from `{path}` (`benchmarks/bench_guide.py`; relMSE and 8x8-block "
             "relMSE over each image's best single input, geometric means"
             + ("; every image of the data set is held out for what runs no trained weights: the envelope, "
                "OIDN" if bench.get("split", "val") != "val" else "") + "):", "",
             "| images | variant | relMSE / best | worst | worse than best | <= 0.5x | 8x8 / best | 8x8 <= best |",
             "|---|---|---:|---:|---:|---:|---:|---:|"]
    data_label = {"val": "validation", "train": "training split", "all": "data set, all splits"}[bench.get("split", "val")]
    if bench.get("data"):                       # results before the key: one unnamed data set
        data_label = f"{', '.join(f'`{d}`' for d in bench['data'])} {data_label.replace('data set, ', '')}"
    for label, key in (("study scenes", "summary_scenes"), (data_label, "summary_validation")):
        for row in bench.get(key, []):
            if row["variant"].split(" ")[0] in bench.get("models", {}) or row["variant"] == "oidn(z4)":
                lines.append(f"| {label} ({row['images']}) | {row['variant']} | {row['geomean']:.3f} | "
                             f"{row['worst']:.2f} | {row['worse_than_best']} | {row['at_most_half']} | "
                             f"{row['geomean_8x8']:.3f} | {row['block_not_worse']} |")
    return lines


def trained_guard(history: list[dict], current: GuardConfig) -> GuardConfig:
    """The guard the network was trained with: what the first guard change of the reship
    ``history`` changed from (settings it predates read as off), else ``current``."""
    first = next((h["guard_from"] for h in history if "guard_from" in h), None)
    return current if first is None else GuardConfig.from_dict(first)


def reship(args: argparse.Namespace) -> None:
    """The current default with the guide settings of the command line: same weights, its
    card's training part kept, the shipped row, the command and the held-out table new."""
    if args.guide_mode is None and args.chooser is None and args.guide_denoiser is None \
            and args.guide_nlm_albedo_channels is None \
            and all(getattr(args, _dest(flag)) is None for flag, *_ in RESHIP_NUMBERS):
        sys.exit("ship_model: give a run folder, or a guide setting to change (--guide-mode, --guide-denoiser, "
                 "--guide-nlm-albedo-channels, " + ", ".join(flag for flag, *_ in RESHIP_NUMBERS) + ", --chooser)")
    ckpt = load_checkpoint(DEFAULT_MODEL)
    before, guard_before = ckpt.model.guide, ckpt.model.guard
    meta = dict(ckpt.meta)
    guard_values = reship_values(args, "guard")
    if guard_values and not guard_before.enabled:
        sys.exit(f"ship_model: {guard_values[0][2]}: {DEFAULT_MODEL} runs without the guard")
    ckpt.model.guard = changed(guard_before, guard_values)
    if args.chooser is not None:
        trained = load_checkpoint(args.chooser)
        if trained.model.chooser is None:
            sys.exit(f"ship_model: --chooser: {args.chooser} has no chooser")
        if trained.model.guard != ckpt.model.guard or trained.model.guide.in_mode("envelope") != before.in_mode("envelope"):
            sys.exit(f"ship_model: --chooser: {args.chooser} was trained on another guard or guide than "
                     f"{DEFAULT_MODEL}'s; train it again with this default as --base-model")
        ckpt.model.chooser = trained.model.chooser
        meta["chooser"] = trained.meta.get("chooser", {})
    # an attached chooser runs by default, unless --guide-mode says otherwise
    ckpt.model.guide = changed_guide(before, args, DEFAULT_MODEL, "chooser" if args.chooser is not None else None)
    card_path = DEFAULT_MODEL.with_name("default.md")
    card = card_path.read_text().splitlines()
    history = list(meta.get("reshipped", []))
    if ckpt.model.guide != before:
        history.append({"from": before.to_dict(), "to": ckpt.model.guide.to_dict()})
    if ckpt.model.guard != guard_before:
        history.append({"guard_from": guard_before.to_dict(), "guard_to": ckpt.model.guard.to_dict()})
    out, skipping = [], False
    for line in card:
        if line.startswith("The model `ppmrecon-denoise` uses"):
            line = line.split(" Re-shipped by ", 1)[0] + (f" Re-shipped by `scripts/ship_model.py{command_flags(args)}` "
                                                        "with changed guide or guard settings (same weights).")
        elif line.startswith("| shipped reconstruction |") or line.startswith("| chooser |"):
            continue
        elif line.startswith("| firefly guard |") and ckpt.model.guard != guard_before:
            line = (f"| firefly guard | {ckpt.model.guard.to_dict()} (ppmrecon/model/guard.py; trained with "
                    f"{trained_guard(history, guard_before).to_dict()}, the same but for the settings changed "
                    "at reshipping) |")
        elif line.startswith("| data set |"):
            out += shipped_row(ckpt.model.guide) + chooser_row(ckpt.model, meta)
        elif line.startswith("Held-out figures from") and args.bench and not skipping:
            for i, path in enumerate(args.bench):
                out += ([""] if i else []) + bench_lines(path)
            skipping = True
            continue
        elif skipping and line.startswith("Limits:"):
            out.append("")
            skipping = False
        if not skipping:
            out.append(line)
    save_checkpoint(DEFAULT_MODEL, ckpt.model, {**meta, "reshipped": history})
    write_text(card_path, "\n".join(out) + "\n")
    print(f"re-shipped {DEFAULT_MODEL}: guide {before.to_dict()} -> {ckpt.model.guide.to_dict()}"
          + (f"; guard {guard_before.to_dict()} -> {ckpt.model.guard.to_dict()}"
             if ckpt.model.guard != guard_before else ""))


if __name__ == "__main__":
    main()
