"""The split stage 2's light fields, one per training environment (:class:`SkyLights`):
the medium is one, the scattered light differs by sky. Each light field gets its sky's
box and mean luminance (``radiance_scale``), and each ray of a batch the light field of
its environment.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import nn

from nrt.losses.context import Illumination


class SkyLights:
    """The light fields of the training environments: ``first`` (the stage's ``light``) and
    ``more`` (a ``ModuleList`` the stage registers, so that checkpoints hold them), grown by
    ``make()`` (a new light field) to one per environment."""

    def __init__(self, first: nn.Module, more: nn.ModuleList, make: Callable[[], nn.Module]):
        self.first, self.more, self.make = first, more, make
        self.illuminations: list[Illumination] = []
        self._scene_of_env = torch.zeros(0, dtype=torch.long)  # dataset env -> its light

    @property
    def fields(self) -> list[nn.Module]:
        """The light field of each environment, in the order of :attr:`illuminations`."""
        return [self.first, *self.more]

    def grow(self, count: int, device: torch.device | str = "cpu") -> None:
        """Build light fields until there are ``count``."""
        while len(self.fields) < count:
            self.more.append(self.make().to(device))

    def attach(self, illuminations: Sequence[Illumination], bbox: torch.Tensor,
               device: torch.device | str = "cpu") -> None:
        """One light field per environment of ``illuminations`` (the dataset's training
        environments, in order), each over ``bbox`` (2, 3) at its sky's ``scale``."""
        self.illuminations = list(illuminations)
        self.grow(len(self.illuminations), device)
        for light, sky in zip(self.fields, self.illuminations, strict=True):
            light.bbox.copy_(bbox)
            light.radiance_scale.fill_(sky.scale)
        indices = [sky.index for sky in self.illuminations]
        self._scene_of_env = torch.full((max(indices) + 1,), -1, dtype=torch.long)
        self._scene_of_env[indices] = torch.arange(len(indices))

    def illumination_of(self, light: nn.Module) -> Illumination:
        """The environment ``light`` is the scattered light of. A light that is not one of
        :attr:`fields` (a family member's, the adjoint's read of the first) is lit by the
        first environment."""
        for field, sky in zip(self.fields, self.illuminations, strict=True):
            if light is field:
                return sky
        return self.illuminations[0]

    def scenes_of(self, env: torch.Tensor) -> torch.Tensor:
        """Each ray's position among the training environments (its light field in
        :attr:`fields`), from its position ``env`` (B,) among the dataset's."""
        return self._scene_of_env[env.cpu()]

    def of_env(self, env: int) -> nn.Module:
        """The light field of the dataset's environment ``env``."""
        return self.fields[int(self._scene_of_env[int(env)])]
