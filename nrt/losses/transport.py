"""Transport objective of split stage 2: the scattered light in integral form.

The light scattered at least once obeys the RTE with zero inflow and the in-scattering of
all light as its source, so at any point ``x`` and travel direction ``w``

    L_s(x, w) = int_0^l T(x - t w, x) sigma_s S(x - t w, w) dt,

marched backward from ``x`` along ``-w`` to the box (length ``l``) in alpha-compositing
form, with ``S`` the exact SH in-scattering of the cached uncollided light and of ``L_s``
itself (:meth:`~nrt.modules.fields.sh_light_field.SHGridLightField.inscatter`). The right-hand
side is evaluated without gradient, a fixed-point (source-iteration) step as neural
radiosity does: each step carries light across the whole box and adds one scattering
order, where a differential residual moves information one collocation spacing at a time.
The medium gets no gradient here; it learns from the photos.
"""

from __future__ import annotations

import torch

from nrt.losses.objective import Objective, Scenes, member_mean
from nrt.modules.fields.sh_light_field import SHGridLightField
from nrt.physics.compositing import alpha_composite, stratified_samples
from nrt.physics.volume import ray_box_intersect


@torch.no_grad()
def scattered_target(light: SHGridLightField, medium, points: torch.Tensor, dirs: torch.Tensor,
                     n_samples: int) -> torch.Tensor:
    """The right-hand side above (N, 3) at ``points`` for travel directions ``dirs`` (N, 3),
    with ``n_samples`` jittered strata; ``medium(x)`` gives :class:`MediumProperties`."""
    back = -dirs
    _, t_exit, _ = ray_box_intersect(points, back, light.bbox)
    t, delta = stratified_samples(torch.zeros_like(t_exit), t_exit, n_samples, jitter=True)
    x = points.unsqueeze(1) + t.unsqueeze(-1) * back.unsqueeze(1)
    w = dirs.unsqueeze(1).expand_as(x)
    props = medium(x)
    source = props.albedo * light.inscatter(x, w, props.g, with_uncollided=True)
    color, _ = alpha_composite(props.sigma_t, delta, source, torch.zeros_like(points))
    return color


def transport_loss(light: SHGridLightField, medium, points: torch.Tensor, dirs: torch.Tensor,
                   n_samples: int) -> torch.Tensor:
    """Mean squared difference (units of ``radiance_scale``) of ``L_s`` and its target."""
    target = scattered_target(light, medium, points, dirs, n_samples)
    return torch.mean(((light(points, dirs) - target) / light.radiance_scale) ** 2)


class TransportObjective(Objective):
    """``transport``: ``stage.transport_objective(medium, light, n)`` at
    ``samples.transport_points`` points; over a family, point i belongs to member i mod K
    (split evenly), the mean over all points."""

    name = "transport"

    def loss(self, stage, batch: dict, scenes: Scenes) -> torch.Tensor:
        n = int(stage.hparams.samples["transport_points"])
        if len(scenes) == 1:
            return stage.transport_objective(*scenes[0], n)
        return member_mean(torch.arange(n) % len(scenes), lambda k, mask:
                           stage.transport_objective(*scenes[k], int(mask.sum())))
