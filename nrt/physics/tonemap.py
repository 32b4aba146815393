"""Tonemaps for comparing HDR images (docs/conventions.md, "Image comparison")."""

from __future__ import annotations

import torch

LUMINANCE_WEIGHTS = (0.2126, 0.7152, 0.0722)
"""Rec. 709 / sRGB luminance of linear RGB (Mitsuba's ``luminance``)."""


def log_tonemap(x: torch.Tensor) -> torch.Tensor:
    """``log(1 + x)`` of non-negative linear radiance."""
    return torch.log1p(x.clamp_min(0.0))


def luminance(rgb: torch.Tensor) -> torch.Tensor:
    """Luminance (...,) of linear RGB (..., 3)."""
    w = torch.tensor(LUMINANCE_WEIGHTS, dtype=rgb.dtype, device=rgb.device)
    return rgb @ w
