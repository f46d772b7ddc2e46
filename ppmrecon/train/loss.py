"""Training loss: the relative L1 of log-compressed radiance (paper 002 Eq. 8; SPEC 5).

    L = 1/(3 N) sum_c sum_l |log(yhat_{c,l} + 1) - log(y_{c,l} + 1)| / (ybar_c + 0.01),
    ybar_c = 1/3 sum_l log(y_{c,l} + 1)

``yhat`` is clipped at 0 before the log (a combination of noisy terms may dip below 0).

:func:`block_log_l1` applies the same terms to ``block`` x ``block`` means of prediction
and target: zero-mean noise averages out inside a block, a smooth bias does not (SPEC 7,
low-frequency error). Weights that correlate with the noise of the terms they weight
darken the output (benchmarks/bias_probe.py); Eq. 8 alone barely sees that, this term
does. Its share in training is ``TrainConfig.lowfreq_weight``.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

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


def block_log_l1(pred: torch.Tensor, target: torch.Tensor, block: int = 8) -> torch.Tensor:
    """Eq. 8 on ``block`` x ``block`` means of (B, C, H, W) images (a 0-d tensor); the
    prediction is clipped at 0 before averaging, as Eq. 8 clips it before the log."""
    if pred.shape[-2] < block or pred.shape[-1] < block:
        raise ValueError(f"images {tuple(pred.shape[-2:])} are smaller than one {block}x{block} block")
    return relative_log_l1(F.avg_pool2d(pred.clamp(min=0), block), F.avg_pool2d(target, block))
