"""Emission-absorption rendering of view rays through an
:class:`~nrt.modules.fields.ea_field.EAField` (stage 1): stratified jittered samples between
the ray's entry and exit of the box, alpha-composited in front of the known background
``E(v)``."""

from __future__ import annotations

import torch

from nrt.modules.fields.ea_field import EAField
from nrt.modules.renderers.volume import march_view_rays
from nrt.physics.compositing import alpha_composite


def render_rays(field: EAField, origins: torch.Tensor, dirs: torch.Tensor,
                background: torch.Tensor, n_samples: int, jitter: bool,
                chunk: int | None = None, latent: torch.Tensor | None = None) -> torch.Tensor:
    """EA radiance ``L(o, -v)`` (R, 3) of view rays; rays missing the box see ``E(v)``.
    ``latent`` (R, d_z): each ray's code, for a conditioned field (``mode=generative``)."""
    if chunk and origins.shape[0] > chunk:
        return torch.cat([render_rays(field, origins[i:i + chunk], dirs[i:i + chunk],
                                      background[i:i + chunk], n_samples, jitter,
                                      latent=None if latent is None else latent[i:i + chunk])
                          for i in range(0, origins.shape[0], chunk)])
    hit, pts, delta = march_view_rays(field.bbox, origins, dirs, n_samples, jitter)
    out = background.clone()
    if pts is not None:
        d = dirs[hit]
        z = None if latent is None else latent[hit].unsqueeze(1)  # one code per ray
        sigma, rgb = field(pts, d.unsqueeze(1).expand_as(pts), z)
        out[hit], _ = alpha_composite(sigma, delta, rgb, background[hit])
    return out
