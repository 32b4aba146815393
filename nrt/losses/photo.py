"""Photo objective of split stage 2: the camera rays rendered by the VRE (the stage's
in-scattering: the sky's and the known lights' first scattering and the scattered light's)
against the photographs.

Compared after ``log1p(x / radiance_scale)``, as stage 1 and the evaluation compare images
(a linear MSE lets the few brightest pixels, the sun's glow through thin medium, decide
the medium's gradient). The rendering is Monte Carlo (the sky's first scattering), so the
square of one estimate is biased by its variance; with the presets' 32 samples per ray and
4 shadow directions per sample that variance is small against the photos' own noise.
"""

from __future__ import annotations

import torch

from nrt.errors import ConfigError
from nrt.losses.objective import Objective, Scenes, scene_mean
from nrt.modules.renderers.volume import render_view_rays

TONEMAPS = ("log", "linear")

RAY_KEYS = ("origins", "dirs", "background", "rgb")
"""What the photo objective reads of a ray batch."""


def check_tonemap(tonemap: str) -> None:
    """Refuse a ``losses.photo_tonemap`` other than :data:`TONEMAPS`."""
    if tonemap not in TONEMAPS:
        raise ConfigError(f"losses.photo_tonemap must be 'log' or 'linear', got '{tonemap}'.")


def photo_loss(rendered: torch.Tensor, photos: torch.Tensor, scale: torch.Tensor | float,
               tonemap: str = "log") -> torch.Tensor:
    """Mean squared difference of pixels (R, 3) after ``log1p(x / scale)`` (``tonemap=log``)
    or of ``x / scale`` (``linear``)."""
    if tonemap == "log":
        return torch.mean((torch.log1p(rendered.clamp_min(0) / scale)
                           - torch.log1p(photos.clamp_min(0) / scale)) ** 2)
    check_tonemap(tonemap)
    return torch.mean(((rendered - photos) / scale) ** 2)


class PhotoObjective(Objective):
    """``photo``: the first ``samples.photo_rays`` rays of the batch rendered with
    ``vre_samples`` jittered strata through the medium, with the stage's in-scattering
    (``stage.inscatter``) of the light as the stage lets the photos read it
    (``stage.photo_light``: through the adjoint's leaf when that is on), against their
    pixels (:func:`photo_loss`, ``photo_tonemap``). Over several scenes (a family's members,
    or the training environments), each ray through its ``scene``'s, the mean over all
    rays. It trains the medium only."""

    families = True
    medium_only = True

    def loss(self, stage, batch: dict, scenes: Scenes) -> torch.Tensor:
        n = int(stage.hparams.samples["photo_rays"])
        rays = {key: batch[key][:n] for key in RAY_KEYS}
        if len(scenes) == 1:
            return self.scene_loss(stage, *scenes[0], rays)
        return scene_mean(batch["scene"][:n].cpu(), lambda k, mask: self.scene_loss(
            stage, *scenes[k], {key: v[mask.to(v.device)] for key, v in rays.items()}))

    @staticmethod
    def scene_loss(stage, medium, light, rays: dict) -> torch.Tensor:
        """The loss of the camera ``rays`` (``origins``, ``dirs``, ``background``, ``rgb``)
        through ``medium`` lit by ``light``."""
        read, coefficients_grad = stage.photo_light(light)
        source = stage.inscatter(medium, read, coefficients_grad)
        pred = render_view_rays(medium, rays["origins"], rays["dirs"], rays["background"],
                                int(stage.hparams.samples["vre_samples"]), source)
        return photo_loss(pred, rays["rgb"], light.radiance_scale, stage.hparams.photo_tonemap)
