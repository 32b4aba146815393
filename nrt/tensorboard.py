"""Images for TensorBoard, shared by every stage's LightningModule."""

from __future__ import annotations

import lightning as L
import torch

from nrt.physics.tonemap import log_tonemap


def log_image(module: L.LightningModule, tag: str, img: torch.Tensor, tonemap: bool = True
              ) -> None:
    """Log an (H, W, 3) image to every logger that takes images: log tonemap (HDR) unless
    ``tonemap=False``, then scaled so its maximum is 1."""
    y = img.detach().float().cpu()
    y = log_tonemap(y) if tonemap else y
    y = (y / y.max().clamp_min(1e-8)).clamp(0, 1)
    for logger in module.loggers:
        writer = getattr(logger, "experiment", None)
        if hasattr(writer, "add_image"):
            writer.add_image(tag, y.numpy(), module.global_step, dataformats="HWC")
