"""Photo objective of split stage 2: the camera rays rendered by the VRE (the stage's
in-scattering: the sky's and the known lights' first scattering and the scattered light's)
against the photographs.

Compared after ``log1p(x / radiance_scale)``, as stage 1 and the evaluation compare images
(a linear MSE lets the few brightest pixels, the sun's glow through thin medium, decide
the medium's gradient). A photographed pixel is the mean of the radiance over its footprint
(box filter), and one jittered ray is a Monte Carlo estimate of that mean (so is the VRE's
march: the sky's first scattering is sampled). The square of one estimate's error is biased
by its variance, and so is its gradient: it rewards media whose radiance varies less inside
a pixel, a pull toward blur at the pixel's scale that the data never asked for. With
``photo_twins`` > 0 the first rays of the batch carry a twin through the same pixel
(jittered and marched independently), and their error is the product of the two rays'
errors (Azinovic et al. 2019's estimator, nrt/losses/unbiased.py, with both rays
differentiated): unbiased for the square of the mean tonemapped estimate's error. With the
linear tonemap that is the box-filtered pixel's error exactly; with ``log`` the tonemap of
a mean is not the mean of the tonemap, a second-order remainder (tests/losses/test_photo_loss.py
measures it at 2 % of the single ray's pull). Noise shared by both rays (the scattered
light's cached uncollided part, the light field itself) is not removed.
"""

from __future__ import annotations

import torch

from nrt.errors import ConfigError
from nrt.losses.context import StepContext
from nrt.losses.objective import Objective, WeightSchedule, scene_mean
from nrt.modules.renderers.volume import render_view_rays
from nrt.physics.tonemap import log_tonemap

TONEMAPS = ("log", "linear")

RAY_KEYS = ("origins", "dirs", "background", "rgb")
"""What the photo objective reads of a ray batch."""
TWIN_KEYS = ("twin_origins", "twin_dirs", "twin_background")
"""The twin rays of a batch's first rays (nrt/data/datamodule.py), when it has them."""


def check_tonemap(tonemap: str) -> None:
    """Refuse a ``losses.photo_tonemap`` other than :data:`TONEMAPS`."""
    if tonemap not in TONEMAPS:
        raise ConfigError(f"losses.photo_tonemap must be 'log' or 'linear', got '{tonemap}'.")


def tonemapped(x: torch.Tensor, scale: torch.Tensor | float, tonemap: str) -> torch.Tensor:
    """``log1p(x / scale)`` (``tonemap=log``, negative radiance clamped to 0) or ``x / scale``
    (``linear``)."""
    if tonemap == "log":
        return log_tonemap(x / scale)
    check_tonemap(tonemap)
    return x / scale


def photo_loss(rendered: torch.Tensor, photos: torch.Tensor, scale: torch.Tensor | float,
               tonemap: str = "log", twins: torch.Tensor | None = None) -> torch.Tensor:
    """Mean squared difference of pixels (R, 3) after the tonemap (:func:`tonemapped`).
    ``twins`` (T, 3), T <= R: a second, independent estimate of the first T pixels; their
    squares become the product of the two estimates' differences (unbiased for the square
    of the mean tonemapped estimate's difference; it can be negative)."""
    reference = tonemapped(photos, scale, tonemap)
    error = tonemapped(rendered, scale, tonemap) - reference
    if twins is None or len(twins) == 0:
        return torch.mean(error ** 2)
    t = len(twins)
    twin_error = tonemapped(twins, scale, tonemap) - reference[:t]
    return (torch.sum(error[:t] * twin_error) + torch.sum(error[t:] ** 2)) / error.numel()


class PhotoObjective(Objective):
    """``photo``: the first ``rays`` rays of the batch rendered with ``vre_samples``
    jittered strata through the medium, with the stage's in-scattering of all light
    (``context.photo_source``), against their pixels (:func:`photo_loss` after
    ``tonemap``); the batch's twin rays, when it has them (``photo_twins``), rendered too
    and paired with their first rays. Over several scenes (a family's members, or the
    training environments), each ray through its ``scene``'s, the mean over all rays. It
    trains the medium only."""

    families = True
    medium_only = True

    def __init__(self, name: str, schedule: WeightSchedule, rays: int, vre_samples: int,
                 tonemap: str = "log"):
        super().__init__(name, schedule)
        check_tonemap(tonemap)
        self.rays, self.vre_samples, self.tonemap = int(rays), int(vre_samples), tonemap

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        n, scenes = self.rays, context.scenes
        rays = {key: batch[key][:n] for key in RAY_KEYS}
        twins = {key: batch[key][:n] for key in TWIN_KEYS if key in batch}
        if len(scenes) == 1:
            return self.scene_loss(context, *scenes[0], rays, twins)
        t = len(twins["twin_dirs"]) if twins else 0
        # a mask keeps the rays' order, so the twinned rays stay the first of each scene's
        return scene_mean(batch["scene"][:n].cpu(), lambda k, mask: self.scene_loss(
            context, *scenes[k], {key: v[mask.to(v.device)] for key, v in rays.items()},
            {key: v[mask[:t].to(v.device)] for key, v in twins.items()}))

    def scene_loss(self, context: StepContext, medium, light, rays: dict,
                   twins: dict | None = None) -> torch.Tensor:
        """The loss of the camera ``rays`` (``origins``, ``dirs``, ``background``, ``rgb``)
        through ``medium`` lit by ``light``; ``twins`` (``twin_origins``, ``twin_dirs``,
        ``twin_background``): second rays through the pixels of the first of ``rays``."""
        source = context.photo_source(medium, light)
        samples = self.vre_samples
        pred = render_view_rays(medium, rays["origins"], rays["dirs"], rays["background"],
                                samples, source)
        twin_pred = None
        if twins and len(twins["twin_dirs"]):  # a scene's share may hold no twinned ray
            twin_pred = render_view_rays(medium, twins["twin_origins"], twins["twin_dirs"],
                                         twins["twin_background"], samples, source)
        return photo_loss(pred, rays["rgb"], light.radiance_scale, self.tonemap, twin_pred)
