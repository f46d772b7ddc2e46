"""Training loss: the relative L1 of log-compressed radiance (paper 002 Eq. 8; SPEC 5).

    L = 1/(3 N) sum_c sum_l |log(yhat_{c,l} + 1) - log(y_{c,l} + 1)| / (ybar_c + 0.01),
    ybar_c = 1/3 sum_l log(y_{c,l} + 1)

``yhat`` is clipped at 0 before the log (a combination of noisy terms may dip below 0).
"""

from __future__ import annotations

import torch

LOSS_EPS = 0.01


def relative_log_l1_map(pred: torch.Tensor, target: torch.Tensor, channel_axis: int = 1) -> torch.Tensor:
    """Per-pixel, per-channel terms of Eq. 8 (same shape as ``pred``)."""
    if pred.shape != target.shape:
        raise ValueError(f"prediction and target shapes differ: {tuple(pred.shape)} vs {tuple(target.shape)}")
    log_target = torch.log1p(target)
    diff = (torch.log1p(pred.clamp(min=0)) - log_target).abs()
    return diff / (log_target.mean(dim=channel_axis, keepdim=True) + LOSS_EPS)


def relative_log_l1(pred: torch.Tensor, target: torch.Tensor, channel_axis: int = 1) -> torch.Tensor:
    """Eq. 8 of paper 002 averaged over pixels and channels (a 0-d tensor)."""
    return relative_log_l1_map(pred, target, channel_axis).mean()
