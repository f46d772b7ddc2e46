"""The kernel-predicting network (paper 002 Sec. 4.3, after KPCN) and its presets.

A plain stack of ``layers`` convolutions (``layers - 1`` hidden ones with ``filters``
channels, ``kernel`` x ``kernel``, ReLU; then an output convolution of
``final_kernel`` x ``final_kernel``) maps the network features to ``4 K^2`` logits per
pixel, the un-normalised combination weights of Eq. 6 (softmax in the combiner).
Initialisation is Glorot uniform with zero biases, as in the paper.

Presets are JSON files named ``<name>.json`` in the package's ``ppmrecon/data/models/``
(package data, so an installed package finds them), or given as a path to a JSON file.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, fields
from pathlib import Path
from typing import Any, Mapping

import torch
import torch.nn as nn

from ..data import MODELS
from ..errors import UsageError
from ..fileio import unknown_keys
from .features import FeatureConfig
from .guard import GuardConfig
from .chooser import Chooser
from .guide import GuideConfig, net_channels

PRESETS_DIR: Path = MODELS
#: The CPU default: the only preset within a few times OIDN's time at 720p on 2 cores
#: (benchmarks/results/denoise.md); ``small`` and ``paper`` are for better hardware.
DEFAULT_PRESET = "tiny"


@dataclass(frozen=True)
class Preset:
    """Architecture of a kernel-predicting network."""

    name: str
    layers: int          # convolutions in total, the output one included
    filters: int         # channels of each hidden layer
    kernel: int          # hidden convolution size (odd)
    window: int          # K: the combiner's K x K window (odd)
    final_kernel: int    # output convolution size (odd); 1 makes the head a per-pixel matmul
    description: str = ""

    def __post_init__(self) -> None:
        for key in ("layers", "filters", "kernel", "window", "final_kernel"):
            value = getattr(self, key)
            if not isinstance(value, int) or isinstance(value, bool) or value < 1:
                raise ValueError(f"preset '{self.name}': {key} must be a positive integer, got {value!r}")
        for key in ("kernel", "window", "final_kernel"):
            if getattr(self, key) % 2 == 0:
                raise ValueError(f"preset '{self.name}': {key} must be odd, got {getattr(self, key)}")

    @property
    def receptive_radius(self) -> int:
        """Pixels of context the logits of one pixel depend on, per side."""
        return (self.layers - 1) * (self.kernel // 2) + self.final_kernel // 2

    @property
    def halo(self) -> int:
        """Tile overlap for exact tiled inference: network context + the window's K//2."""
        return self.receptive_radius + self.window // 2

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "Preset":
        unknown = unknown_keys(cls, data)
        if unknown:
            raise ValueError(f"unknown preset key(s) {', '.join(unknown)}")
        missing = sorted(f.name for f in fields(cls)
                         if f.name not in ("description", "final_kernel") and f.name not in data)
        if missing:
            raise ValueError(f"preset lacks {', '.join(missing)}")
        data = dict(data)
        data.setdefault("final_kernel", data.get("kernel"))
        return cls(**data)


def preset_names() -> list[str]:
    """Names of the presets found on disk."""
    return sorted(p.stem for p in PRESETS_DIR.glob("*.json"))


def load_preset(name_or_path: str | os.PathLike) -> Preset:
    """A preset by name (``paper``, ``small``, ``tiny``, ...) or from a JSON file path."""
    text = str(name_or_path)
    path = Path(text) if text.endswith(".json") or os.sep in text else PRESETS_DIR / f"{text}.json"
    if path.is_file():
        try:
            return Preset.from_dict(json.loads(path.read_text()))
        except (ValueError, TypeError) as exc:  # JSONDecodeError is a ValueError
            raise UsageError(f"{path}: invalid model preset ({exc})") from None
    known = ", ".join(preset_names()) or "none found"
    raise UsageError(f"unknown model preset '{text}' (known: {known}; or give a .json path)")


class KPN(nn.Module):
    """Features (B, C, H, W) -> combination logits (B, 4 K^2, H, W) (paper 002 Fig. 4);
    with the guide's ``temperature``, one more channel: the prior's log-temperature
    (:func:`.guide.guided_logits`).

    ``guard`` and ``guide`` are not part of the network: they are the firefly guard
    (:mod:`.guard`) and the denoiser guide (:mod:`.guide`) the model was trained with,
    kept here so that they travel with the checkpoint. With the guide on, the logits are
    a correction added to the guide's prior, and the head starts at zero (an untrained
    model is the guide alone).
    """

    def __init__(self, preset: Preset, features: FeatureConfig = FeatureConfig(),
                 guard: GuardConfig = GuardConfig(), guide: GuideConfig = GuideConfig()):
        super().__init__()
        if features.guide and not guide.enabled:
            raise ValueError("feature 'guide' (the guide as input) needs the denoiser guide enabled")
        self.preset = preset
        self.features = features
        self.guard = guard
        self.guide = guide
        body: list[nn.Module] = []
        channels = features.n_channels
        for _ in range(preset.layers - 1):
            body += [nn.Conv2d(channels, preset.filters, preset.kernel, padding=preset.kernel // 2),
                     nn.ReLU(inplace=True)]
            channels = preset.filters
        self.body = nn.Sequential(*body)
        fk = preset.final_kernel
        self.head = nn.Conv2d(channels, net_channels(guide, preset.window), fk, padding=fk // 2)
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.xavier_uniform_(m.weight)   # Glorot uniform (paper 002 Sec. 4.3)
                nn.init.zeros_(m.bias)
        if guide.enabled:
            nn.init.zeros_(self.head.weight)   # residual on the prior: start from the guide
        #: the learned choice on top of the envelope (:mod:`.chooser`), when the checkpoint has one
        self.chooser: Chooser | None = None

    @property
    def window(self) -> int:
        return self.preset.window

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(x))

    @torch.no_grad()
    def predict(self, x: torch.Tensor, precision: str = "float32") -> torch.Tensor:
        """Inference-only forward pass returning float32 NCHW-contiguous logits.

        ``precision="bfloat16"`` runs the hidden layers in bfloat16, channels-last (fast
        on CPUs with AMX/AVX512-BF16 and on GPUs); the head always runs in float32.
        Only the weights are affected: the combiner stays float32 and consistent.
        """
        if precision == "bfloat16":
            # one conversion of the input (autocast would copy it to channels-last, then to bf16)
            x = x.to(torch.bfloat16, memory_format=torch.channels_last)
            with torch.autocast(x.device.type, dtype=torch.bfloat16):
                h = self.body(x)
            h = h.float()
        elif precision == "float32":
            h = self.body(x)
        else:
            raise ValueError(f"precision must be 'float32' or 'bfloat16', got {precision!r}")
        if self.head.kernel_size == (1, 1):
            return self._head_matmul(h)
        return self.head(h.contiguous()).contiguous()

    def _head_matmul(self, h: torch.Tensor) -> torch.Tensor:
        # A 1x1 convolution is W @ h per pixel; as one GEMM on the pixel-major view of
        # a channels-last h it writes planar (NCHW) logits without a layout conversion.
        b, c, hh, ww = h.shape
        pixels = h.permute(0, 2, 3, 1).reshape(b, hh * ww, c)
        n = self.head.out_channels
        weight = self.head.weight.view(1, n, c).expand(b, n, c)
        bias = self.head.bias.view(1, n, 1).expand(b, n, hh * ww)
        return torch.baddbmm(bias, weight, pixels.transpose(1, 2)).view(b, n, hh, ww)


def parameter_count(model: nn.Module) -> int:
    """Number of trainable parameters."""
    return sum(p.numel() for p in model.parameters() if p.requires_grad)


def build(preset: Preset | str, features: FeatureConfig = FeatureConfig(),
          guard: GuardConfig = GuardConfig(), guide: GuideConfig = GuideConfig()) -> KPN:
    """A freshly initialised network for a preset (name, path or :class:`Preset`)."""
    if not isinstance(preset, Preset):
        preset = load_preset(preset)
    return KPN(preset, features, guard, guide)
