"""Training in tests: a callback that fails on NaN or Inf, and a short CPU fit under it."""

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


def fit(model: L.LightningModule, dm: L.LightningDataModule, steps: int,
        *callbacks: L.Callback) -> L.Trainer:
    """``steps`` training steps on the CPU without logging, checkpoints or validation,
    under :class:`AssertFinite` (and ``callbacks``)."""
    trainer = L.Trainer(max_steps=steps, accelerator="cpu", logger=False,
                        enable_checkpointing=False, enable_progress_bar=False,
                        num_sanity_val_steps=0, limit_val_batches=0, inference_mode=False,
                        callbacks=[AssertFinite(), *callbacks])
    trainer.fit(model, datamodule=dm)
    return trainer
