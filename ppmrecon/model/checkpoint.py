"""Model checkpoints: weights + everything needed to rebuild and feed the network.

A checkpoint is a ``torch.save`` dict of plain types and tensors only, so it loads with
``torch.load(weights_only=True)`` (no pickled code is ever executed):

    format          "ppmrecon-kpn"
    format_version  FORMAT_VERSION
    schema_version  the buffer-file schema the features were built from (buffers.SCHEMA_VERSION)
    preset          the full architecture (Preset.to_dict())
    features        the feature settings (FeatureConfig.to_dict())
    guard           the firefly guard settings (GuardConfig.to_dict()); absent before
                    format 2, read as the guard off (those models never saw it)
    guide           the denoiser-guide settings (GuideConfig.to_dict()); absent before
                    format 3, read as the guide off
    chooser         the chooser's architecture (ChooserConfig.to_dict()), when the model has one
                    (format 4; its weights are the state_dict's ``chooser.*``)
    state_dict      the weights
    meta            free-form training information (epochs, validation relMSE, ...)

Every problem on load (missing, corrupt, not a checkpoint, newer format, other schema,
weights that do not fit the architecture) is one :class:`UsageError` naming the file.
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import torch

from ..buffers import SCHEMA_VERSION
from ..data import MODELS
from ..errors import UsageError
from ..fileio import atomic_write
from .chooser import Chooser, ChooserConfig
from .features import FeatureConfig
from .guard import GuardConfig
from .guide import GuideConfig
from .kpn import DEFAULT_PRESET, KPN, Preset, build

FORMAT = "ppmrecon-kpn"
#: 2: adds "guard" (an older ppmrecon must not run a guard-trained model without it)
#: 3: adds "guide" (likewise: a guide-trained network's logits are a correction to the prior)
#: 4: adds "chooser" (the learned choice on top of the envelope, guide mode "chooser")
FORMAT_VERSION = 4
#: A shipped default model is picked up from here when it exists.
DEFAULT_MODEL = MODELS / "default.pt"
_ZIP_MAGIC = b"PK\x03\x04"   # torch.save's archive format
NO_MODEL_HINT = ("no model given and no default model is installed; pass --model CKPT "
                 "(train one with `ppmrecon-train`, or make an untrained one with "
                 "`ppmrecon-denoise --init-checkpoint CKPT`)")


class Checkpoint(NamedTuple):
    model: KPN
    meta: dict[str, Any]


def save_checkpoint(path: str | os.PathLike, model: KPN, meta: Mapping[str, Any] | None = None) -> None:
    """Write ``model`` (and ``meta``: str/int/float/bool/list/dict values) atomically."""
    path = Path(path)
    payload = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "schema_version": SCHEMA_VERSION,
        "preset": model.preset.to_dict(),
        "features": model.features.to_dict(),
        "guard": model.guard.to_dict(),
        "guide": model.guide.to_dict(),
        **({"chooser": model.chooser.cfg.to_dict()} if model.chooser is not None else {}),
        "state_dict": {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
        "meta": dict(meta or {}),
    }
    atomic_write(path, lambda tmp: torch.save(payload, tmp))


def init_checkpoint(path: str | os.PathLike, preset: Preset | str = DEFAULT_PRESET,
                    features: FeatureConfig = FeatureConfig(), seed: int = 0,
                    guard: GuardConfig = GuardConfig(), guide: GuideConfig = GuideConfig()) -> KPN:
    """Write a freshly initialised (untrained) model to ``path`` and return it."""
    torch.manual_seed(seed)
    model = build(preset, features, guard, guide)
    save_checkpoint(path, model, {"trained": False, "seed": seed})
    return model


def model_path(arg: str | os.PathLike | None) -> Path:
    """The checkpoint to load: ``arg``, or the shipped default model when it is None."""
    if arg:
        return Path(arg)
    if DEFAULT_MODEL.is_file():
        return DEFAULT_MODEL
    raise UsageError(NO_MODEL_HINT)


def load_checkpoint(path: str | os.PathLike, map_location: str | torch.device = "cpu") -> Checkpoint:
    """Load and validate a checkpoint written by :func:`save_checkpoint`."""
    path = Path(path)

    def fail(problem: str) -> UsageError:
        return UsageError(f"{path}: {problem}")

    if not path.exists():
        raise fail("no such model checkpoint")
    if path.is_dir():
        raise fail("is a folder, expected a model checkpoint (.pt)")
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != _ZIP_MAGIC:
        raise fail("not a model checkpoint (not a PyTorch zip archive)")
    try:
        data = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError:
        raise fail("holds objects other than tensors and plain values; refusing to unpickle it "
                   "(not a ppmrecon model checkpoint)") from None
    except Exception as exc:  # zip/stream errors: truncated or damaged file
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise fail(f"corrupt or truncated model checkpoint ({reason.split(':')[0][:100]})") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise fail("not a ppmrecon model checkpoint (no 'ppmrecon-kpn' format marker)")
    version = data.get("format_version")
    if not isinstance(version, int):
        raise fail(f"unreadable checkpoint format version {version!r}")
    if version > FORMAT_VERSION:
        raise fail(f"checkpoint format {version} is newer than this ppmrecon understands ({FORMAT_VERSION}); upgrade ppmrecon")
    schema = data.get("schema_version")
    if schema != SCHEMA_VERSION:
        raise fail(f"model was trained on buffer schema {schema!r}, this ppmrecon writes schema {SCHEMA_VERSION}; "
                   "retrain it with ppmrecon-train")
    for key, kind in (("preset", dict), ("features", dict), ("state_dict", dict)):
        if not isinstance(data.get(key), kind):
            raise fail(f"checkpoint lacks '{key}'")
    guard_data, guide_data, chooser_data = data.get("guard", {}), data.get("guide", {}), data.get("chooser")
    if not isinstance(guard_data, dict):
        raise fail("checkpoint has an unreadable 'guard'")
    if not isinstance(guide_data, dict):
        raise fail("checkpoint has an unreadable 'guide'")
    if chooser_data is not None and not isinstance(chooser_data, dict):
        raise fail("checkpoint has an unreadable 'chooser'")
    try:
        preset = Preset.from_dict(data["preset"])
        features = FeatureConfig.from_dict(data["features"])
        guard = GuardConfig.from_dict(guard_data)
        guide = GuideConfig.from_dict(guide_data)
        chooser = ChooserConfig.from_dict(chooser_data) if chooser_data is not None else None
    except (TypeError, ValueError) as exc:
        raise fail(f"invalid architecture in checkpoint ({exc})") from None
    if guide.enabled and guide.mode == "chooser" and chooser is None:
        raise fail("guide mode 'chooser' but the checkpoint has no chooser")
    model = KPN(preset, features, guard, guide)
    if chooser is not None:
        model.chooser = Chooser(chooser)
    try:
        model.load_state_dict(data["state_dict"], strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = " ".join(line.strip() for line in first[:3])
        raise fail(f"weights do not match the '{preset.name}' architecture ({detail[:200]})") from None
    if not all(torch.isfinite(p).all() for p in model.parameters()):
        raise fail("weights contain NaN/Inf")
    meta = data.get("meta") if isinstance(data.get("meta"), dict) else {}
    return Checkpoint(model.eval(), meta)
