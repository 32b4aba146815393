"""Stratified ray marching and emission-absorption compositing in alpha form.

``I = sum_i T_i (1 - exp(-sigma_i d_i)) c_i + T_N E``, ``T_i = exp(-sum_{j<i} sigma_j d_j)``:
the transmittance is accumulated in log space (optical depth) and ``1 - exp(-x)`` is
computed with ``expm1``, so dense media (sigma d >> 1) and near-empty ones (sigma d ~ 1e-8)
stay exact. The transmitted background ``T_N E`` is always part of the sum.
"""

from __future__ import annotations

import torch
from torch.profiler import record_function


def stratified_samples(t_near: torch.Tensor, t_far: torch.Tensor, n: int, jitter: bool,
                       generator: torch.Generator | None = None
                       ) -> tuple[torch.Tensor, torch.Tensor]:
    """Sample distances (R, n) in ``n`` equal strata of ``[t_near, t_far]`` and their
    lengths (R, n); uniform inside each stratum when ``jitter``, else at stratum centres."""
    length = (t_far - t_near).clamp_min(0.0)
    if jitter:
        u = torch.rand(*t_near.shape, n, dtype=t_near.dtype, device=t_near.device,
                       generator=generator)
    else:
        u = torch.full((*t_near.shape, n), 0.5, dtype=t_near.dtype, device=t_near.device)
    strata = torch.arange(n, dtype=t_near.dtype, device=t_near.device)
    step = (length / n).unsqueeze(-1)
    t = t_near.unsqueeze(-1) + (strata + u) * step
    return t, step.expand_as(t)


def segment_transmittance(sigma: torch.Tensor, deltas: torch.Tensor
                          ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """For ``sigma`` (R, S) or per channel (R, S, C) over segment lengths ``deltas`` (R, S):
    the transmittance up to each sample ``T_i``, each segment's optical depth
    ``tau_i = sigma_i d_i`` and their running sum, all shaped like ``sigma``."""
    per_channel = sigma.dim() == deltas.dim() + 1
    tau = sigma.clamp_min(0.0) * (deltas.unsqueeze(-1) if per_channel else deltas)
    cum = torch.cumsum(tau, -2 if per_channel else -1)
    return torch.exp(-(cum - tau)), tau, cum  # exclusive prefix sum


def alpha_composite(sigma: torch.Tensor, deltas: torch.Tensor, values: torch.Tensor,
                    background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Composite per-sample ``values`` (R, S, C) over segment lengths ``deltas`` (R, S) in
    front of ``background`` (R, C), with extinction ``sigma`` (R, S) shared by the channels
    or (R, S, C) per channel (chromatic media; C may be 1 and broadcast).

    Returns the pixel values (R, C) and the transmittance left after the last sample,
    (R,) or (R, C) like ``sigma``.
    """
    with record_function("nrt/compositing"):  # a profiler scope (benchmarks.profile_step)
        per_channel = sigma.dim() == values.dim()
        axis = -2 if per_channel else -1
        t_before, tau, cum = segment_transmittance(sigma, deltas)
        weights = t_before * -torch.expm1(-tau)
        t_final = torch.exp(-cum.select(axis, -1))
        if not per_channel:
            weights, t_final_c = weights.unsqueeze(-1), t_final.unsqueeze(-1)
        else:
            t_final_c = t_final
        color = (weights * values).sum(-2) + t_final_c * background
        return color, t_final
