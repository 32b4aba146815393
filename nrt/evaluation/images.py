"""Pictures of evaluations: PNG previews (truth | ours | error heat map) and EXR files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from nrt.physics.tonemap import log_tonemap

ERROR_RANGE = 0.25
"""Heat-map saturation: |log1p(ours) - log1p(truth)| as a fraction of the truth's maximum."""


def display(img: np.ndarray, scale: float) -> np.ndarray:
    """Log-tonemapped (H, W, 3) linear radiance divided by ``scale``, in [0, 1]."""
    return np.clip(log_tonemap(torch.as_tensor(img)).numpy() / max(scale, 1e-8), 0, 1)


def error_heatmap(pred: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Per-pixel log-tonemapped error, mean over RGB, as an 'inferno' heat map (H, W, 3)."""
    from matplotlib import colormaps

    y_pred, y_ref = (log_tonemap(torch.as_tensor(x)).numpy() for x in (pred, ref))
    err = np.abs(y_pred - y_ref).mean(-1) / max(float(y_ref.max()), 1e-8)
    return colormaps["inferno"](np.clip(err / ERROR_RANGE, 0, 1))[..., :3]


def comparison_panel(truth: np.ndarray | None, ours: np.ndarray) -> np.ndarray:
    """``truth | ours | error`` side by side (just ``ours`` without a truth), in [0, 1]."""
    if truth is None:
        return display(ours, float(log_tonemap(torch.as_tensor(ours)).max()))
    scale = float(log_tonemap(torch.as_tensor(truth)).max())
    gap = np.ones((truth.shape[0], 2, 3))
    return np.concatenate([display(truth, scale), gap, display(ours, scale), gap,
                           error_heatmap(ours, truth)], 1)


def save_png(path: str | Path, rgb: np.ndarray) -> Path:
    """Write an (H, W, 3) image in [0, 1] as 8-bit PNG."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)).save(path)
    return path
