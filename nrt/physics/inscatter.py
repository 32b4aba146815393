"""Monte Carlo in-scattered radiance from a light field.

``S(x, w) = int f(w' . w) L(x, w') dw'``: the radiance scattered at ``x`` into the travel
direction ``w``. Directions ``w'`` are drawn from the phase function itself (uniform for
isotropic media, HG importance sampling otherwise, reparameterised so the estimate is
differentiable in g), so every sample weighs exactly 1.
"""

from __future__ import annotations

import torch
from torch import nn
from torch.func import functional_call

from nrt.physics.phase import sample_phase


def inscattered_radiance(light: nn.Module, x: torch.Tensor, w: torch.Tensor,
                         g: torch.Tensor | None, n_dirs: int, detach: bool = False,
                         generator: torch.Generator | None = None) -> torch.Tensor:
    """Estimate of ``S(x, w)`` (..., 3) from ``n_dirs`` phase samples at each point.

    ``light(x, w)`` evaluates radiance; ``x``, ``w`` (..., 3); ``g`` (...,) or None.
    ``detach`` stops gradients into the light field's parameters through this estimate
    (the neural-radiosity habit, cheaper); gradients to g through the sampled directions
    remain, so g still learns from the in-scattering it shapes.
    """
    xi = torch.rand(*x.shape[:-1], n_dirs, 2, dtype=x.dtype, device=x.device,
                    generator=generator)
    g_k = None if g is None else g.unsqueeze(-1).expand(xi.shape[:-1])
    w_in = sample_phase(w.unsqueeze(-2).expand(*xi.shape[:-1], 3), g_k, xi)
    x_k = x.unsqueeze(-2).expand_as(w_in)
    if not detach:
        return light(x_k, w_in).mean(-2)
    if not w_in.requires_grad:
        with torch.no_grad():
            return light(x_k, w_in).mean(-2)
    frozen = {name: p.detach() for name, p in light.named_parameters()}
    return functional_call(light, frozen, (x_k, w_in)).mean(-2)
