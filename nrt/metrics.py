"""Image and medium metrics shared by training callbacks and evaluation.

Images are compared after the log tonemap ``y = log1p(x)`` (DESIGN.md section 2): PSNR
uses the tonemapped reference's range; SSIM and LPIPS take ``y`` divided by the
reference's maximum and clamped to [0, 1]. Images are (H, W, 3) linear radiance.
"""

from __future__ import annotations

from pathlib import Path

import torch
from torchmetrics.functional.image import (
    peak_signal_noise_ratio,
    structural_similarity_index_measure,
)

from nrt.errors import NrtError
from nrt.physics.tonemap import log_tonemap


def psnr(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """PSNR (dB) of log-tonemapped images, peak = the tonemapped reference's range."""
    y_pred, y_ref = log_tonemap(pred), log_tonemap(ref)
    data_range = (y_ref.max() - y_ref.min()).clamp_min(1e-8)
    return peak_signal_noise_ratio(y_pred, y_ref, data_range=float(data_range))


def unit_range(pred: torch.Tensor, ref: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Log-tonemapped (H, W, 3) images as (1, 3, H, W) in [0, 1], scaled by the reference."""
    y_pred, y_ref = log_tonemap(pred.float()), log_tonemap(ref.float())
    scale = y_ref.max().clamp_min(1e-8)
    return tuple((y / scale).clamp(0, 1).permute(2, 0, 1).unsqueeze(0) for y in (y_pred, y_ref))


def ssim(pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """SSIM (Gaussian window 11, sigma 1.5) of (H, W, 3) images, log-tonemapped."""
    a, b = unit_range(pred, ref)
    return structural_similarity_index_measure(a, b, data_range=1.0)


LPIPS_BACKBONES = {"alex": ("alexnet", "AlexNet_Weights"), "vgg": ("vgg16", "VGG16_Weights"),
                   "squeeze": ("squeezenet1_1", "SqueezeNet1_1_Weights")}


def _backbone_url(net: str) -> str:
    import torchvision

    if net not in LPIPS_BACKBONES:
        raise NrtError(f"metrics.lpips_net must be one of {sorted(LPIPS_BACKBONES)}, got "
                       f"'{net}'.")
    return getattr(torchvision.models, LPIPS_BACKBONES[net][1]).DEFAULT.url


def lpips_backbone_file(net: str = "alex") -> Path:
    """Where torchvision looks for LPIPS's pretrained backbone: the torch hub cache
    (``$TORCH_HOME/hub/checkpoints/<file>``), the file named by the weights' URL."""
    return Path(torch.hub.get_dir()) / "checkpoints" / Path(_backbone_url(net)).name


class LPIPS:
    """LPIPS (torchmetrics, lower is better) of (H, W, 3) images, log-tonemapped.

    The ImageNet backbone is loaded from the torch hub cache and never downloaded here:
    when its file is missing, the error names it and where to put it. The linear
    calibration layers ship with torchmetrics.
    """

    def __init__(self, net: str = "alex", device: torch.device | str = "cpu"):
        from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

        path = lpips_backbone_file(net)
        if not path.is_file():
            raise NrtError(f"LPIPS needs the pretrained {LPIPS_BACKBONES[net][0]} backbone at "
                           f"'{path}', which is missing (this machine cannot download it). "
                           f"Copy the file from {_backbone_url(net)} there (the folder is "
                           "$TORCH_HOME/hub/checkpoints, default ~/.cache/torch), or skip "
                           "LPIPS with "
                           "metrics.lpips=false.")
        self.metric = LearnedPerceptualImagePatchSimilarity(net_type=net, normalize=True)
        self.metric = self.metric.to(device)

    @torch.no_grad()
    def __call__(self, pred: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
        a, b = unit_range(pred, ref)
        dev = next(self.metric.parameters(), torch.empty(0)).device
        self.metric.reset()
        return self.metric(a.to(dev), b.to(dev))


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
