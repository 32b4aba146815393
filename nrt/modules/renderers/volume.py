"""Volume rendering equation along primary rays, in alpha-compositing form.

``I = sum_i T_i (1 - exp(-sigma_t,i d_i)) albedo_i S_i + T_N E(v)`` between the ray's entry
and exit of the box, stratified jittered samples, per-channel extinction; ``S_i`` is the
in-scattered radiance toward the camera (travel direction ``-v``) estimated from the light
field, plus the first scattering of known lights (emitters, sun) when the scene has them. The
transmitted background ``T_N E(v)`` is part of the sum (docs/conventions.md, "Transport equations").
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch.profiler import record_function

from nrt.modules.fields.light_field import LightField
from nrt.modules.fields.medium import Medium, MediumProperties
from nrt.physics.compositing import alpha_composite
from nrt.physics.inscatter import inscattered_radiance
from nrt.physics.volume import march, ray_box_intersect

DirectSource = Callable[[torch.Tensor, torch.Tensor, MediumProperties], torch.Tensor]
"""``(x, w, properties) -> S_direct`` (..., 3): first scattering of the known lights."""

InScatter = Callable[[torch.Tensor, torch.Tensor, MediumProperties], torch.Tensor]
"""``(x, w, properties) -> S`` (..., 3): in-scattered radiance at points ``x`` toward
travel directions ``w``, given the medium's properties there."""


def march_view_rays(bbox: torch.Tensor, origins: torch.Tensor, dirs: torch.Tensor,
                    n_samples: int, jitter: bool
                    ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
    """Samples of view rays inside the box: ``hit`` (R,), and for the rays that hit,
    points (H, n, 3) in ``n_samples`` strata between entry and exit and the strata's
    lengths (H, n); None for both when no ray hits."""
    with record_function("nrt/ray_marching"):  # a profiler scope (benchmarks.profile_step)
        t0, t1, hit = ray_box_intersect(origins, dirs, bbox)
        if not hit.any():
            return hit, None, None
        x, delta = march(origins[hit], dirs[hit], t0[hit], t1[hit], n_samples, jitter)
        return hit, x, delta


def render_view_rays(medium, origins: torch.Tensor, dirs: torch.Tensor,
                     background: torch.Tensor, n_samples: int, inscatter: InScatter,
                     jitter: bool = True) -> torch.Tensor:
    """Pixels ``I`` (R, 3) of view rays by the VRE with the in-scattering ``inscatter``
    (travel direction ``-v`` at every sample); ``medium(x)`` gives the properties."""
    hit, x, delta = march_view_rays(medium.bbox, origins, dirs, n_samples, jitter)
    if x is None:
        return background.clone()
    w = (-dirs[hit]).unsqueeze(1).expand_as(x)
    props = medium(x)
    color, _ = alpha_composite(props.sigma_t, delta, props.albedo * inscatter(x, w, props),
                               background[hit])
    return background.index_put((hit,), color.to(background.dtype))


def vre_render(light: LightField, medium: Medium, origins: torch.Tensor, dirs: torch.Tensor,
               background: torch.Tensor, n_samples: int, n_dirs: int, jitter: bool = True,
               detach_inscatter: bool = False, direct_source: DirectSource | None = None,
               estimates: int = 1) -> list[torch.Tensor]:
    """Pixels ``I`` (R, 3) of view rays (``origins``, unit ``dirs`` v, ``background``
    E(v)), one per in-scattering estimate; the first of several carries no graph (the
    value of :func:`~nrt.losses.unbiased.unbiased_square`). The estimates draw independent
    in-scattering directions and share everything else: the jittered positions, the
    medium and the known lights' first scattering there."""
    hit, x, delta = march_view_rays(medium.bbox, origins, dirs, n_samples, jitter)
    outs = [background.clone() for _ in range(estimates)]
    if x is None:
        return outs
    w = (-dirs[hit]).unsqueeze(1).expand_as(x)
    props = medium(x)
    s_direct = direct_source(x, w, props) if direct_source is not None else 0.0
    for k in range(estimates):
        value_only = estimates > 1 and k == 0
        with torch.set_grad_enabled(torch.is_grad_enabled() and not value_only):
            g = props.g.detach() if value_only and props.g is not None else props.g
            s_mc = inscattered_radiance(light, x, w, g, n_dirs,
                                        detach=detach_inscatter or value_only)
            color, _ = alpha_composite(props.sigma_t, delta, props.albedo * (s_mc + s_direct),
                                       background[hit])
            outs[k][hit] = color.to(outs[k].dtype)
    return outs


def transmitted_background(medium: Medium, origins: torch.Tensor, dirs: torch.Tensor,
                           background: torch.Tensor, n_samples: int) -> torch.Tensor:
    """The no-scattering prediction ``T E(v)`` (R, 3): the background seen through the
    medium's extinction, with nothing scattered into the ray."""
    hit, x, delta = march_view_rays(medium.bbox, origins, dirs, n_samples, jitter=False)
    out = background.clone()
    if x is not None:
        sigma_t = medium(x).sigma_t
        _, t_final = alpha_composite(sigma_t, delta, torch.zeros_like(sigma_t), background[hit])
        out[hit] = t_final * background[hit]
    return out
