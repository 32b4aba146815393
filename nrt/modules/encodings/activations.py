"""Activations with stable backward passes."""

from __future__ import annotations

import torch

EXP_CLAMP = 15.0
"""Exponents are clamped to +-15 (e^15 ~ 3.3e6 per unit length: far denser than any cloud)."""


class _TruncExp(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x.clamp(max=EXP_CLAMP))

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        return grad * torch.exp(x.clamp(-EXP_CLAMP, EXP_CLAMP))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    """``exp(x)`` whose value and gradient never overflow (instant-ngp's density activation)."""
    return _TruncExp.apply(x)


DENSITY_ACTIVATIONS = {"trunc_exp": trunc_exp, "softplus": torch.nn.functional.softplus}
