"""Image and medium metrics shared by training callbacks and evaluation."""

from __future__ import annotations

import torch
from torchmetrics.functional.image import peak_signal_noise_ratio

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


def property_mse(pred: dict[str, torch.Tensor], ref: dict[str, torch.Tensor],
                 with_g: bool = True) -> dict[str, torch.Tensor]:
    """MSE x 10^2 (the paper's unit) of sigma_a, sigma_s, sigma_t (over cells and RGB) and,
    when ``with_g``, of g weighted by the reference sigma_s (its channel mean, normalised),
    between grids of the same layout (``sigma_a``, ``sigma_s`` (..., 3), ``g`` (...))."""
    out = {}
    for key in ("sigma_a", "sigma_s"):
        out[key] = torch.mean((pred[key].double() - ref[key].double()) ** 2)
    sigma_t = (pred["sigma_a"] + pred["sigma_s"]).double()
    out["sigma_t"] = torch.mean((sigma_t - (ref["sigma_a"] + ref["sigma_s"]).double()) ** 2)
    if with_g:
        weight = ref["sigma_s"].double().mean(-1)
        err = (pred["g"].double() - ref["g"].double()) ** 2
        out["g"] = (weight * err).sum() / weight.sum().clamp_min(1e-30)
    return {k: (100 * v).float() for k, v in out.items()}
