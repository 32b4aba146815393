"""A training environment as stage 2 lights the medium with it (an
:class:`~nrt.losses.context.Illumination`):
its sun-less sky, its suns split off as known lights with the scene's emitters, and its
mean luminance. Environment maps follow docs/conventions.md (Mitsuba's ``envmap``:
``E(d)`` is the radiance seen looking along d); radiance is linear RGB."""

from __future__ import annotations

import logging

import torch

from nrt.losses.context import Illumination
from nrt.losses.samplers import EnvironmentDirectionSampler
from nrt.physics.direct_light import DirectLights, split_sun
from nrt.physics.envmap import EnvironmentMap, texel_directions
from nrt.physics.tonemap import luminance

log = logging.getLogger(__name__)


def mean_radiance(envmap: EnvironmentMap) -> float:
    """Mean luminance of an environment over the sphere (rows weighted by solid angle)."""
    d = texel_directions(envmap.height, envmap.width)
    solid = torch.sqrt((1 - d[..., 1] ** 2).clamp_min(0.0))
    lum = luminance(envmap.radiance.double())
    return float((lum * solid).sum() / solid.sum().clamp_min(1e-30))


def make_illumination(index: int, env: EnvironmentMap, sun: dict | None, emitters: list[dict],
                      device: torch.device | str = "cpu") -> Illumination:
    """:class:`Illumination` of ``env`` (the dataset's environment ``index``) with the point
    ``emitters`` (``{position, intensity}``) and, when ``sun.threshold`` is set, E's texels
    brighter than ``threshold x scale`` split off as at most ``sun.max_suns`` suns."""
    scale = max(mean_radiance(env), 1e-6)
    sun = sun or {}
    if sun.get("threshold") is not None:
        rest, sun_dirs, sun_irr = split_sun(env, float(sun["threshold"]) * scale,
                                            int(sun.get("max_suns", 4)))
    else:
        rest, sun_dirs, sun_irr = env, torch.zeros(0, 3), torch.zeros(0, 3)
    lights = DirectLights(
        torch.tensor([e["position"] for e in emitters], dtype=torch.float32).reshape(-1, 3),
        torch.tensor([e["intensity"] for e in emitters], dtype=torch.float32).reshape(-1, 3),
        sun_dirs, sun_irr).to(device)
    if sun_dirs.shape[0]:
        log.info("Sun(s) of environment %d scattered explicitly: directions %s, irradiance %s",
                 index, sun_dirs.tolist(), sun_irr.tolist())
    part_of_sun = EnvironmentMap(env.radiance - rest.radiance).to(device) \
        if sun_dirs.shape[0] else None
    return Illumination(index, rest.to(device), part_of_sun, lights,
                        EnvironmentDirectionSampler(rest), scale)
