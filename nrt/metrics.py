"""Image and medium metrics shared by training callbacks and evaluation."""

from __future__ import annotations

import torch
from torchmetrics.functional import peak_signal_noise_ratio

from nrt.physics.tonemap import log_tonemap


def psnr(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR (dB) of log-tonemapped images, peak = the tonemapped reference's range."""
    y_pred, y_ref = log_tonemap(pred), log_tonemap(ref)
    data_range = (y_ref.max() - y_ref.min()).clamp_min(1e-8)
    return peak_signal_noise_ratio(y_pred, y_ref, data_range=float(data_range))


def density_agreement(pred: torch.Tensor, ref: torch.Tensor) -> dict[str, torch.Tensor]:
    """Pearson correlation and relative L2 error ``|pred - ref| / |ref|`` of two fields."""
    p, r = pred.flatten().double(), ref.flatten().double()
    pc, rc = p - p.mean(), r - r.mean()
    corr = (pc @ rc) / (pc.norm() * rc.norm()).clamp_min(1e-30)
    rel = (p - r).norm() / r.norm().clamp_min(1e-30)
    return {"corr": corr.float(), "rel_err": rel.float()}
