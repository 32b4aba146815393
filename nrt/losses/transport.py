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
The medium gets no gradient here; it learns from the photos (and, with
``model.coupling``, through :func:`unrolled_inscatter` or :mod:`~nrt.losses.adjoint`).
"""

from __future__ import annotations

import torch
from torch.profiler import record_function

from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, WeightSchedule, scene_mean
from nrt.losses.samplers import uniform_box_points
from nrt.modules.fields.sh_light_field import SHGridLightField
from nrt.modules.fields.voxel_medium import detached
from nrt.physics.compositing import alpha_composite
from nrt.physics.phase import sample_phase, sample_uniform_sphere
from nrt.physics.volume import march_to_exit


def scattered_target(light: SHGridLightField, medium, points: torch.Tensor, dirs: torch.Tensor,
                     n_samples: int, medium_grad: bool = False) -> torch.Tensor:
    """The right-hand side above (N, 3) at ``points`` for travel directions ``dirs`` (N, 3),
    with ``n_samples`` jittered strata; ``medium(x)`` gives :class:`MediumProperties`.
    Without gradient, or with gradient to the medium only (``medium_grad``)."""
    with torch.set_grad_enabled(medium_grad and torch.is_grad_enabled()):
        back = -dirs
        x, delta = march_to_exit(points, back, light.bbox, n_samples, jitter=True)
        w = dirs.unsqueeze(1).expand_as(x)
        props = medium(x)
        source = props.albedo * light.inscatter(x, w, props.g, with_uncollided=True,
                                                trainable=False)
        color, _ = alpha_composite(props.sigma_t, delta, source, torch.zeros_like(points))
        return color


def transport_loss(light: SHGridLightField, medium, points: torch.Tensor, dirs: torch.Tensor,
                   n_samples: int) -> torch.Tensor:
    """Mean squared difference (units of ``radiance_scale``) of ``L_s`` and its target."""
    target = scattered_target(light, medium, points, dirs, n_samples)
    return torch.mean(((light(points, dirs) - target) / light.radiance_scale) ** 2)


def unrolled_inscatter(light: SHGridLightField, medium, x: torch.Tensor, w: torch.Tensor,
                       g: torch.Tensor | None, n_dirs: int, n_samples: int) -> torch.Tensor:
    """A gradient path from the scattered light to the medium, zero in value (..., 3).

    The scattered light's in-scattering at ``x`` for travel directions ``w`` is estimated
    from ``n_dirs`` phase-sampled directions ``w'`` with ``L_s(x, w')`` unrolled by one
    source-iteration step (:func:`scattered_target` with gradient to the medium): the first
    term of the Neumann series of ``dL_s / d medium``. Added to the exact SH in-scattering,
    whose coefficients carry no gradient, it lets the photos see how the medium shapes the
    light scattered more than once.
    """
    lead = x.shape[:-1]
    pts = x.reshape(-1, 1, 3).expand(-1, n_dirs, 3).reshape(-1, 3)
    travel = w.reshape(-1, 1, 3).expand(-1, n_dirs, 3).reshape(-1, 3)
    g_k = None if g is None else g.detach().reshape(-1, 1).expand(-1, n_dirs).reshape(-1)
    dirs = sample_phase(travel, g_k, torch.rand(len(pts), 2, device=x.device))
    est = scattered_target(light, medium, pts, dirs, n_samples, medium_grad=True)
    est = est.reshape(*lead, n_dirs, 3).mean(-2)
    return est - est.detach()


def uniform_samples(n: int, bbox: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` points (n, 3) uniform in the box ``bbox`` and as many travel directions (n, 3)
    uniform on the sphere, drawn in that order."""
    with record_function("nrt/ray_marching"):  # a profiler scope (benchmarks.profile_step)
        points = uniform_box_points(n, bbox)
        return points, sample_uniform_sphere(torch.rand(n, 2, device=bbox.device))


class TransportObjective(Objective):
    """``transport``: :func:`transport_loss` of the light in the medium (without gradient
    to it) at ``points`` uniform points and travel directions, with ``samples`` strata per
    march; over K scenes (a family's members, or the
    training environments' light fields), point i belongs to scene i mod K (split evenly),
    the mean over all points."""

    families = True

    def __init__(self, name: str, schedule: WeightSchedule, points: int, samples: int):
        super().__init__(name, schedule)
        self.points, self.samples = int(points), int(samples)

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        n, strata, scenes = self.points, self.samples, context.scenes
        if len(scenes) == 1:
            return self.scene_loss(*scenes[0], n, strata)
        return scene_mean(torch.arange(n) % len(scenes), lambda k, mask:
                           self.scene_loss(*scenes[k], int(mask.sum()), strata))

    @staticmethod
    def scene_loss(medium, light: SHGridLightField, n: int, n_samples: int) -> torch.Tensor:
        """The loss of ``light`` in ``medium`` at ``n`` fresh samples."""
        points, dirs = uniform_samples(n, light.bbox)
        return transport_loss(light, detached(medium), points, dirs, n_samples)
