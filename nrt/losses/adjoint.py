"""Adjoint of the scattered light: the photos' gradient to the medium through ``L_s``.

The photo objective reads the scattered light's SH coefficients ``c`` without gradient,
so on its own it misses how the medium shapes the light scattered more than once, the
light that leaves a dense core. That part of the gradient follows from the adjoint
equation (radiative backpropagation, Nimier-David et al. 2020) solved by a second SH grid
``A`` in the same way the transport objective solves ``L_s``:

    (-w . grad + sigma_t) A = sigma_s K_g A + Q,    A = 0 where w leaves the box,

    A(x, w) = int_0^l T(x, x + t w) [sigma_s K_g A + Q](x + t w, w) dt,

marched *forward* along ``w`` (``K_g`` the HG in-scattering, exact band by band). The source
``Q = d loss / d L_s`` is the photo loss's gradient with respect to the coefficient grid,
spread over each cell's volume (``G / V_cell``, a lumped mass matrix). With ``A`` the
gradient of the photo loss through ``L_s`` is

    sum over colour channels of int sum_lm a_lm (d sigma_s g^l (c + u)_lm - d sigma_t c_lm) dx

(``u`` the uncollided cache; SH are orthonormal), estimated at uniform points in the box by
:func:`medium_sensitivity`. Everything is in the grid's units (radiance over
``radiance_scale``); the source is normalised by ``q_scale`` so that ``A`` is of order one
for the light field's learning rate, and the sensitivity is multiplied back by it. The
uncollided cache's own dependence on the medium (the shadowing of the first scattering
inside it) is left out.
"""

from __future__ import annotations

import torch

from nrt.modules.fields.sh_light_field import SHGrid
from nrt.physics.compositing import segment_transmittance
from nrt.physics.sh import num_coefficients, phase_band_factors
from nrt.physics.volume import march_to_exit, sample_grid


@torch.no_grad()
def adjoint_target(adjoint: SHGrid, source: SHGrid, medium, points: torch.Tensor,
                   dirs: torch.Tensor, n_samples: int) -> torch.Tensor:
    """The right-hand side above (N, 3) at ``points`` for directions ``dirs`` (N, 3), with
    ``n_samples`` jittered strata; ``source`` holds ``Q`` as SH coefficients."""
    x, delta = march_to_exit(points, dirs, adjoint.bbox, n_samples, jitter=True)
    w = dirs.unsqueeze(1).expand_as(x)
    props = medium(x)
    t_before, tau, _ = segment_transmittance(props.sigma_t, delta)
    alpha = -torch.expm1(-tau)
    # int over a stratum of T Q dt = T_before Q (1 - exp(-tau)) / sigma_t = T_before Q d h(tau)
    h = torch.where(tau > 1e-6, alpha / tau.clamp_min(1e-6), 1 - tau / 2)
    scattered = t_before * alpha * props.albedo * adjoint.inscatter(x, w, props.g)
    emitted = t_before * h * delta.unsqueeze(-1) * source(x, w)
    return (scattered + emitted).sum(1)


def adjoint_loss(adjoint: SHGrid, source: SHGrid, medium, points: torch.Tensor,
                 dirs: torch.Tensor, n_samples: int) -> torch.Tensor:
    """Mean squared difference of ``A`` and its target (a fixed-point step, as
    :func:`~nrt.losses.transport.transport_loss`); trains the adjoint grid only."""
    target = adjoint_target(adjoint, source, medium, points, dirs, n_samples)
    return torch.mean((adjoint(points, dirs) - target) ** 2)


def medium_sensitivity(adjoint: SHGrid, light: SHGrid, medium, points: torch.Tensor,
                       q_scale: float) -> torch.Tensor:
    """A surrogate whose gradient with respect to ``medium`` is the photo loss's gradient
    through the scattered light (the integral above, by uniform ``points`` (N, 3) in the
    box); its value means nothing. ``adjoint`` solves the normalised source ``Q / q_scale``."""
    k = num_coefficients(light.degree)
    bbox = light.bbox
    a = sample_grid(adjoint.coefficients.detach(), points, bbox).reshape(-1, 3, k)
    c = sample_grid(light.coefficients.detach(), points, bbox).reshape(-1, 3, k)
    u = sample_grid(light.uncollided, points, bbox).reshape(-1, 3, k)
    props = medium(points)
    bands = phase_band_factors(props.g, light.degree).to(points).unsqueeze(-2)
    gain = props.sigma_s * (a * bands * (c + u)).sum(-1)
    loss = props.sigma_t * (a * c).sum(-1)
    volume = torch.prod(bbox[1] - bbox[0])
    return q_scale * volume * (gain - loss).sum(-1).mean()
