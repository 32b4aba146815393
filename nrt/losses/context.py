"""What an objective reads at a step besides the ray batch (:class:`StepContext`): the
step's (medium, light) pairs, the training environment's illumination, and the sources of
in-scattered light the stage supplies. Objectives never see the stage itself.

Radiance is linear RGB and environment maps follow docs/conventions.md (``E(d)`` is the
radiance seen looking along d).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from nrt.errors import ConfigError
from nrt.losses.samplers import DensityPointSampler, EnvironmentDirectionSampler
from nrt.modules.renderers.volume import DirectSource
from nrt.physics.direct_light import DirectLights
from nrt.physics.envmap import EnvironmentMap

Scenes = Sequence[tuple[Any, Any]]
"""The (medium, light) pairs an objective is taken over: one for a single scene under one
sky; one per family member in the generative mode; one per training environment when the
split stage trains on several (one medium, a light field each). With more than one, the
batch's ``scene`` (B,) says which each ray belongs to."""

@dataclass
class Illumination:
    """One training environment E as stage 2 lights the medium with it: ``index`` (its
    position in the dataset's environments), E's sun-less part ``rest`` (the inflow of the
    light field; the sky's first scattering), the sun's part ``sun`` (``E - rest``; None
    without a sun), the known ``lights`` (E's suns and the scene's emitters), a ``sampler``
    of directions like ``rest``, and ``scale``, E's mean luminance (the light field's
    ``radiance_scale``)."""

    index: int
    rest: EnvironmentMap
    sun: EnvironmentMap | None
    lights: DirectLights
    sampler: EnvironmentDirectionSampler
    scale: float

    def sunless(self, dirs: torch.Tensor) -> torch.Tensor:
        """Mask (N,) of view directions ``dirs`` (N, 3) that do not look into the sun's
        texels (all without one)."""
        if self.sun is None:
            return torch.ones(dirs.shape[0], dtype=torch.bool, device=dirs.device)
        return self.sun.lookup(dirs).sum(-1) <= 0


@dataclass
class StepContext:
    """What the objectives of one step read:

    - ``scenes``: the step's (medium, light) pairs (:data:`Scenes`);
    - ``illumination``: the first training environment (the paper's stage trains on one);
    - ``photo_source(medium, light)``: the in-scattering of all light for the camera rays'
      VRE in that scene, ``source(x, w, props)`` (..., 3) (the split stage's; else None);
    - ``direct_source``: the known lights' first scattering in the stage's medium (the
      paper's stage; None without known lights);
    - ``voxels()``: the learned voxel media composed anew, a graph of their own (None: the
      stage has no voxel medium);
    - ``density_sampler()``: collocation points drawn like the current extinction (the
      paper's stage; None elsewhere)."""

    scenes: Scenes
    illumination: Illumination | None = None
    photo_source: Callable[[Any, Any], DirectSource] | None = None
    direct_source: DirectSource | None = None
    voxels: Callable[[], list] | None = None
    density_sampler: Callable[[], DensityPointSampler] | None = None

    def voxel_media(self, name: str) -> list:
        """:attr:`voxels` composed anew, for the priors on them; a stage without voxels (the
        paper's formulation) is refused naming ``losses.weights.<name>``."""
        if self.voxels is None:
            raise ConfigError(f"losses.weights.{name}: this prior reads a voxel medium, which "
                              "the split stage 2 has (stage=rte without experiment=rte_paper); "
                              "remove it from this stage's objectives.")
        return self.voxels()
