"""Known light sources whose first scattering is computed explicitly (next-event style).

Point emitters (Mitsuba ``point``, intensity ``I`` in W/sr) and the sun of an environment
deliver uncollided radiance along single directions, which no smooth light field can
hold. Their first scattering is a known source added to the Monte Carlo in-scattering:

    S_direct(x, w) = sum_lights f(-l . w) P T(x -> light)

with ``l`` the unit direction from ``x`` toward the light, ``P = I / |p - x|^2`` for a point
light and ``P = `` the sun's irradiance for a directional one, and ``T`` the transmittance
inside the box (midpoint rule, ``n_steps``). The light field then carries everything else:
light scattered at least once and the smooth rest of the sky. Built only when a scene has
emitters or a sun (:func:`split_sun`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch.profiler import record_function

from nrt.physics.envmap import EnvironmentMap, texel_directions
from nrt.physics.phase import hg_phase, isotropic_phase
from nrt.physics.tonemap import luminance
from nrt.physics.volume import optical_depth, ray_box_intersect


@dataclass
class DirectLights:
    """Point lights (``positions``, ``intensities`` (P, 3)) and directional suns
    (``sun_directions`` (K, 3) unit look directions toward the sun, ``sun_irradiance``
    (K, 3) W/m^2 on a surface facing it)."""

    positions: torch.Tensor
    intensities: torch.Tensor
    sun_directions: torch.Tensor
    sun_irradiance: torch.Tensor

    def __len__(self) -> int:
        return self.positions.shape[0] + self.sun_directions.shape[0]

    def to(self, *args, **kwargs) -> DirectLights:
        return DirectLights(*(t.to(*args, **kwargs) for t in (
            self.positions, self.intensities, self.sun_directions, self.sun_irradiance)))


def split_sun(envmap: EnvironmentMap, threshold: float, max_suns: int = 4,
              cluster_deg: float = 20.0) -> tuple[EnvironmentMap, torch.Tensor, torch.Tensor]:
    """Split ``E = E_rest + E_sun``: texels brighter than ``threshold`` (luminance) keep
    ``threshold`` in ``E_rest`` (same colour) and give the excess to ``E_sun``, which is
    merged into at most ``max_suns`` directional lights (texels within ``cluster_deg`` of a
    cluster's brightest texel join it; direction = power-weighted mean).

    Returns ``(E_rest, sun_directions (K, 3), sun_irradiance (K, 3))``; K = 0 when no
    texel exceeds the threshold. Texel solid angles follow Mitsuba's row placement.
    """
    rad = envmap.radiance.double()
    h, w = envmap.height, envmap.width
    lum = luminance(rad)
    factor = torch.where(lum > threshold, threshold / lum.clamp_min(1e-30), torch.ones_like(lum))
    rest = rad * factor.unsqueeze(-1)
    excess = rad - rest
    dirs = texel_directions(h, w)
    theta_step, phi_step = math.pi / (h - 1), 2 * math.pi / w
    sin = torch.sin(torch.arange(h, dtype=torch.float64) * theta_step)
    solid = (sin.clamp_min(theta_step / 4) * theta_step * phi_step)[:, None].expand(h, w)
    power = (excess * solid.unsqueeze(-1)).reshape(-1, 3)
    dirs, lum_power = dirs.reshape(-1, 3), luminance(power)
    remaining = lum_power > 0
    suns_d, suns_e = [], []
    cos_join = math.cos(math.radians(cluster_deg))
    while remaining.any() and len(suns_d) < max_suns:
        seed = torch.where(remaining, lum_power, torch.zeros_like(lum_power)).argmax()
        member = remaining & (dirs @ dirs[seed] >= cos_join)
        p = power[member]
        mean_dir = (dirs[member] * luminance(p).unsqueeze(-1)).sum(0)
        suns_d.append(mean_dir / mean_dir.norm())
        suns_e.append(p.sum(0))
        remaining &= ~member
    if remaining.any():  # more bright spots than max_suns: keep them in E_rest
        back = (remaining.reshape(h, w).unsqueeze(-1)) * excess
        rest = rest + back
    out = EnvironmentMap(rest.to(envmap.radiance.dtype))
    d = torch.stack(suns_d).float() if suns_d else torch.zeros(0, 3)
    e = torch.stack(suns_e).float() if suns_e else torch.zeros(0, 3)
    return out, d, e


def direct_arrivals(x: torch.Tensor, lights: DirectLights,
                    sigma_t: Callable[[torch.Tensor], torch.Tensor], bbox: torch.Tensor,
                    n_steps: int = 16, jitter: bool = False
                    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """What each known light delivers at points ``x`` (..., 3): a list of ``(toward,
    power)``, the unit direction (..., 3) from ``x`` toward the light and the attenuated
    irradiance ``P T(x -> light)`` (..., 3) arriving from it (light travels along
    ``-toward``). ``sigma_t`` maps points (..., 3) to extinction (..., C)."""
    arrivals = []

    def attenuated(toward: torch.Tensor, power: torch.Tensor, t_max: torch.Tensor | None):
        _, t_exit, _ = ray_box_intersect(x, toward, bbox)
        t_end = t_exit if t_max is None else torch.minimum(t_exit, t_max)
        tau = optical_depth(sigma_t, x, toward, torch.zeros_like(t_end), t_end, n_steps, jitter)
        arrivals.append((toward, power * torch.exp(-tau)))

    for p, intensity in zip(lights.positions, lights.intensities, strict=True):
        to_light = p - x
        dist2 = (to_light * to_light).sum(-1, keepdim=True).clamp_min(1e-6)
        dist = torch.sqrt(dist2)
        attenuated(to_light / dist, intensity / dist2, dist.squeeze(-1))
    for d, irradiance in zip(lights.sun_directions, lights.sun_irradiance, strict=True):
        attenuated(d.expand_as(x), irradiance, None)
    return arrivals


def direct_inscatter(x: torch.Tensor, w: torch.Tensor, g: torch.Tensor | None,
                     lights: DirectLights, sigma_t: Callable[[torch.Tensor], torch.Tensor],
                     bbox: torch.Tensor, n_steps: int = 16, jitter: bool = False
                     ) -> torch.Tensor:
    """``S_direct`` (..., 3) at points ``x`` for travel directions ``w`` (..., 3).

    ``sigma_t`` maps points (..., 3) to extinction (..., C); ``g`` (...,) or None.
    """
    with record_function("nrt/direct_light"):  # a profiler scope (benchmarks.profile_step)
        total = torch.zeros_like(x)
        for toward, power in direct_arrivals(x, lights, sigma_t, bbox, n_steps, jitter):
            cos = -(toward * w).sum(-1)
            phase = isotropic_phase(cos) if g is None else hg_phase(cos, g)
            total = total + phase.unsqueeze(-1) * power
        return total
