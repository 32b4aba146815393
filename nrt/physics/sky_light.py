"""The environment's uncollided light inside the medium, and its first scattering.

Light from look direction ``d`` travels along ``-d``; it reaches a point ``x`` of the box
attenuated by the transmittance ``T(x, d)`` from ``x`` to the box along ``d``, so the
uncollided radiance is ``L_u(x, -d) = T(x, d) E(d)``. Its first scattering toward travel
direction ``w`` is

    S_u(x, w) = int f(-d . w) T(x, d) E(d) dd,

estimated here by multiple importance sampling (balance heuristic) of the environment
(:class:`~nrt.physics.envmap.EnvironmentDirectionSampler`) and of the phase function, each
sample a shadow ray through the medium. Only the sun-less part of the sky goes through
this estimator: suns and emitters are the :mod:`~nrt.physics.direct_light` sources. The
estimate is differentiable in the medium (through ``T``) and in ``g``; its directions and
proposal densities are not (samples are fixed proposals, which keeps the gradient
unbiased).

:func:`uncollided_sh` projects ``L_u`` (sky and known lights) onto spherical harmonics
(:mod:`nrt.physics.sh`), the form in which the scattered-light field uses it;
:func:`uncollided_sh_skies` does it for several skies with one set of shadow rays.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch.profiler import record_function

from nrt.physics.direct_light import DirectLights, direct_arrivals
from nrt.physics.envmap import EnvironmentDirectionSampler, EnvironmentMap
from nrt.physics.phase import hg_phase, isotropic_phase, sample_phase
from nrt.physics.sh import num_coefficients, sh_basis
from nrt.physics.volume import optical_depth, ray_box_intersect

SigmaT = Callable[[torch.Tensor], torch.Tensor]
"""Extinction at points (..., 3) -> (..., C), C = 3 or 1."""


def sky_transmittance(x: torch.Tensor, d: torch.Tensor, sigma_t: SigmaT, bbox: torch.Tensor,
                      n_steps: int, jitter: bool = True) -> torch.Tensor:
    """``T(x, d)`` (..., C): the transmittance from ``x`` to the box along look directions
    ``d`` (``n_steps`` strata, jittered)."""
    _, t_exit, _ = ray_box_intersect(x, d, bbox)
    tau = optical_depth(sigma_t, x, d, torch.zeros_like(t_exit), t_exit, n_steps, jitter)
    return torch.exp(-tau)


def shadowed_sky(x: torch.Tensor, d: torch.Tensor, sigma_t: SigmaT, bbox: torch.Tensor,
                 envmap: EnvironmentMap, n_steps: int, jitter: bool = True) -> torch.Tensor:
    """``T(x, d) E(d)`` (..., 3): the sky seen from ``x`` along look directions ``d``."""
    return sky_transmittance(x, d, sigma_t, bbox, n_steps, jitter) * \
        envmap.lookup(d).to(x.dtype)


def sky_inscatter(x: torch.Tensor, w: torch.Tensor, g: torch.Tensor | None, sigma_t: SigmaT,
                  bbox: torch.Tensor, envmap: EnvironmentMap,
                  sampler: EnvironmentDirectionSampler, n_env: int, n_phase: int,
                  n_steps: int) -> torch.Tensor:
    """MIS estimate of ``S_u(x, w)`` (..., 3) at points ``x`` for travel directions ``w``
    (..., 3) with ``n_env`` environment and ``n_phase`` phase samples per point; ``g``
    (...,) or None (isotropic)."""
    with record_function("nrt/sky_light"):  # a profiler scope (benchmarks.profile_step)
        lead = x.shape[:-1]
        looks = []
        if n_env:
            looks.append(sampler.sample(x[..., 0].numel() * n_env).to(x).reshape(
                *lead, n_env, 3))
        if n_phase:
            xi = torch.rand(*lead, n_phase, 2, dtype=x.dtype, device=x.device)
            g_k = None if g is None else g.detach().unsqueeze(-1).expand(*lead, n_phase)
            looks.append(-sample_phase(w.unsqueeze(-2).expand(*lead, n_phase, 3), g_k, xi))
        d = torch.cat(looks, -2).detach()
        cos = -(d * w.unsqueeze(-2)).sum(-1)
        if g is None:
            phase = proposal = isotropic_phase(cos)
        else:
            g_k = g.unsqueeze(-1).expand(cos.shape)
            phase, proposal = hg_phase(cos, g_k), hg_phase(cos, g_k.detach())
        mixture = n_env * sampler.pdf(d) + n_phase * proposal  # balance heuristic, summed
        radiance = shadowed_sky(x.unsqueeze(-2).expand_as(d), d, sigma_t, bbox, envmap, n_steps)
        return ((phase / mixture.clamp_min(1e-20)).unsqueeze(-1) * radiance).sum(-2)


@torch.no_grad()
def uncollided_sh(x: torch.Tensor, sigma_t: SigmaT, bbox: torch.Tensor, envmap: EnvironmentMap,
                  sampler: EnvironmentDirectionSampler, lights: DirectLights | None,
                  degree: int, n_dirs: int, n_steps: int) -> torch.Tensor:
    """SH coefficients (N, 3, (degree + 1)^2) of the uncollided radiance at points ``x``
    (N, 3), as a function of the travel direction: the sky by ``n_dirs`` environment
    samples (``c = mean T E Y(-d) / pdf(d)``), the known lights exactly."""
    d = sampler.sample(x.shape[0] * n_dirs).to(x).reshape(x.shape[0], n_dirs, 3)
    sky = shadowed_sky(x.unsqueeze(1).expand_as(d), d, sigma_t, bbox, envmap, n_steps)
    weighted = sky / sampler.pdf(d).clamp_min(1e-20).unsqueeze(-1)
    coef = torch.einsum("nkc,nkj->ncj", weighted, sh_basis(-d, degree)) / n_dirs
    return with_known_lights(coef, x, sigma_t, bbox, lights, degree, n_steps)


@torch.no_grad()
def uncollided_sh_skies(x: torch.Tensor, sigma_t: SigmaT, bbox: torch.Tensor,
                        envmaps: Sequence[EnvironmentMap],
                        samplers: Sequence[EnvironmentDirectionSampler],
                        lights: Sequence[DirectLights | None], degree: int, n_dirs: int,
                        n_steps: int) -> list[torch.Tensor]:
    """:func:`uncollided_sh` of K skies in one medium from one set of shadow rays: the
    ``n_dirs`` directions of a point are drawn from the K samplers in equal shares (the
    first ``n_dirs % K`` one more) and serve every sky, each weighted by the balance
    heuristic ``E_k(d) / sum_m n_m pdf_m(d)`` (multi-sample MIS: unbiased for each sky).
    The shadow rays of one sky light all K; each sky's estimate has ``n_dirs`` samples, about
    ``n_dirs / K`` of them drawn like itself. With K = 1 it is :func:`uncollided_sh`."""
    k = len(samplers)
    counts = [n_dirs // k + (i < n_dirs % k) for i in range(k)]
    n = x.shape[0]
    d = torch.cat([s.sample(n * c).to(x).reshape(n, c, 3)
                   for s, c in zip(samplers, counts, strict=True) if c], 1)
    mixture = sum(c * s.pdf(d) for s, c in zip(samplers, counts, strict=True))
    weight = sky_transmittance(x.unsqueeze(1).expand_as(d), d, sigma_t, bbox, n_steps) / \
        mixture.clamp_min(1e-20).unsqueeze(-1)
    basis = sh_basis(-d, degree)
    return [with_known_lights(torch.einsum("nkc,nkj->ncj", weight * e.lookup(d).to(x.dtype),
                                           basis), x, sigma_t, bbox, known, degree, n_steps)
            for e, known in zip(envmaps, lights, strict=True)]


def with_known_lights(coef: torch.Tensor, x: torch.Tensor, sigma_t: SigmaT, bbox: torch.Tensor,
                      lights: DirectLights | None, degree: int, n_steps: int) -> torch.Tensor:
    """The sky's SH coefficients ``coef`` (N, 3, (degree + 1)^2) plus the known lights'
    shadowed arrivals at ``x``, projected exactly."""
    if lights is not None and len(lights):
        for toward, power in direct_arrivals(x, lights, sigma_t, bbox, n_steps, jitter=True):
            coef = coef + power.unsqueeze(-1) * sh_basis(-toward, degree).unsqueeze(-2)
    return coef.reshape(x.shape[0], 3, num_coefficients(degree))
