"""A Lightning callback for tests that train: no NaN or Inf may appear."""

from __future__ import annotations

import lightning as L
import torch


class AssertFinite(L.Callback):
    """Fails on the first step whose loss, gradients or parameters hold NaN or Inf."""

    def on_before_optimizer_step(self, trainer, pl_module, optimizer):
        for name, p in pl_module.named_parameters():
            assert p.grad is None or torch.isfinite(p.grad).all(), f"grad of {name}"

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx):
        assert torch.isfinite(outputs["loss"] if isinstance(outputs, dict) else outputs)
        for name, p in pl_module.named_parameters():
            assert torch.isfinite(p).all(), name
