"""What the stages need of the density field, the light field and the medium that Hydra
builds for them (``model/density_field=<name>``, ``model/light_field=<name>``,
``model/medium=<name>``; see
:mod:`nrt.stages.components`). Each protocol lists the members a stage, its objectives and
its renderers use; a stage builds its components through :func:`build`, which checks them.

Common to every light field: the buffers ``bbox`` (2, 3), the medium box, and
``radiance_scale`` (), the training environment's mean radiance, both registered by the
field (``register_buffer``) and filled by the stage in ``setup``. Directions are directions
of travel (docs/conventions.md, "Directions and radiance"); radiance is linear RGB, (..., 3).
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from typing import Protocol

import torch

from nrt.errors import ConfigError


class DensityField(Protocol):
    """Stage 1's density, which stage 2 bakes and modulates (``model/density_field=<name>``;
    by default :class:`~nrt.modules.fields.ea_field.EAField`). Built as ``factory()``, or
    ``factory(latent_dim=d_z)`` in generative mode; stage 1 also renders it as a module,
    ``field(x, d, latent) -> (density (...,), rgb (..., 3))`` along view directions ``d``."""

    bbox: torch.Tensor

    def density(self, x: torch.Tensor, latent: torch.Tensor | None = None) -> torch.Tensor:
        """Density per unit length (...,) at world points ``x`` (..., 3). ``latent`` (..., d_z)
        is the scene's code in generative mode (required exactly when the field is
        conditioned on one), None for a single scene."""


class ScatteredLightField(Protocol):
    """The light field of the split stage (``stage=rte``): the light scattered at least once,
    ``L_s(x, w)``, and the SH in-scattering of it and of the uncollided light. Built as
    ``factory(effects=scene.effects)``; its trainable parameters are all of
    ``parameters()``."""

    bbox: torch.Tensor
    radiance_scale: torch.Tensor
    degree: int
    """SH degree of the uncollided light's projection (:meth:`set_uncollided`)."""

    def __call__(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """``L_s(x, w)`` (..., 3) at points (..., 3) along travel directions (..., 3)."""

    def inscatter(self, x: torch.Tensor, w: torch.Tensor, g: torch.Tensor | None,
                  with_uncollided: bool = False, trainable: bool = True) -> torch.Tensor:
        """``int f(w' . w) L(x, w') dw'`` (..., 3) for HG of ``g`` (...,) or isotropic (None):
        of ``L_s``, plus the cached uncollided light with ``with_uncollided``; no gradient to
        the field's parameters with ``trainable=False``."""

    def cache_points(self) -> torch.Tensor:
        """Points (N, 3) at which the stage projects the uncollided light for the cache."""

    def set_uncollided(self, coefficients: torch.Tensor, blend: float = 1.0) -> None:
        """Store the uncollided light's SH coefficients (N, 3, (degree + 1)^2) at
        :meth:`cache_points`, averaged with the cache by weight ``blend``."""


class RadianceField(Protocol):
    """The light field of the paper's formulation (``experiment=rte_paper``): the full
    radiance ``L(x, w)`` and its directional derivative. Built as ``factory()``."""

    bbox: torch.Tensor
    radiance_scale: torch.Tensor

    def __call__(self, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """``L(x, w)`` (..., 3)."""

    def with_derivative(self, x: torch.Tensor, w: torch.Tensor
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """``L(x, w)`` and ``(w . grad_x) L(x, w)``, both (..., 3)."""


class VoxelisedMedium(Protocol):
    """The learned medium of the split stage: properties composed on cells once per step,
    a density baked from stage 1, a grid that may change resolution during the run. Built as
    ``factory(effects)``; a :class:`~nrt.modules.fields.medium.Medium` (``grids``, ``bbox``)."""

    bbox: torch.Tensor

    def voxels(self):
        """The properties on cells (:class:`~nrt.modules.fields.voxel_medium.Voxels`),
        differentiable in the parameters."""

    def set_density(self, density) -> None:
        """Bake ``density(points (N, 3)) -> (N,)``, the EA field's, into the medium."""

    def follow_schedule(self, progress: float, optimizer: torch.optim.Optimizer) -> bool:
        """Adapt to the run's ``progress`` in [0, 1] (coarse to fine); True if it changed."""

    def grids(self, resolution: int) -> dict[str, torch.Tensor]:
        """Properties on ``resolution``^3 cells in the ground truth's layout."""


class LatentScatteredLightField(Protocol):
    """The light field of generative stage 2 (``stage=rte mode=generative``): the scattered
    light of every family member, decoded from its latent code. Built as
    ``factory(effects=scene.effects)`` (members and d_z are its config's keywords)."""

    bbox: torch.Tensor
    radiance_scale: torch.Tensor
    degree: int

    def member(self, index: int, code: torch.Tensor) -> ScatteredLightField:
        """Member ``index``'s light under ``code`` (d_z,), with the member's uncollided
        cache: a :class:`ScatteredLightField` for the objectives."""

    def member_blocks(self) -> list[torch.nn.Parameter]:
        """Its parameters that hold one block per member along their last axis (the members'
        feature offsets); [] for none."""


class LatentVoxelisedMedium(Protocol):
    """The medium of generative stage 2: a member's density on cells (the stage's, from the
    EA field under the member's code) modulated under a latent code. Built as
    ``factory(effects)`` (d_z is its config's keyword)."""

    bbox: torch.Tensor
    density_resolution: int
    """Cells per axis of the densities it modulates."""

    member_offsets: int
    """How many members hold their own feature offset (0: none)."""

    def voxels_for(self, density: torch.Tensor, code: torch.Tensor, member: int | None = None):
        """The properties on cells (:class:`~nrt.modules.fields.voxel_medium.Voxels`) of a density
        (R, R, R, 1) under ``code`` (d_z,), with member ``member``'s offset when given,
        differentiable in all of them."""

    def offset_square(self, members: torch.Tensor | None = None) -> torch.Tensor:
        """The members' offsets' mean square (their prior, before its weight)."""

    def member_blocks(self) -> list[torch.nn.Parameter]:
        """Its parameters that hold one block per member along their last axis (the members'
        feature offsets); [] for none."""

    def fold_offsets(self, densities: torch.Tensor, codes: torch.Tensor, steps: int,
                     lr: float, kernel: Callable[[torch.Tensor, torch.Generator], torch.Tensor]
                     | None = None) -> tuple[float, float]:
        """Fit what a new code reads to the members' media (offsets included), at their
        codes and around them where a ``kernel`` draws codes near each member, and zero the
        offsets; the fit's objective before and after."""

    def follow_schedule(self, progress: float, optimizer: torch.optim.Optimizer) -> bool:
        """Adapt to the run's ``progress`` in [0, 1] (coarse to fine); True if it changed."""


class ModulatedMedium(Protocol):
    """The learned medium of the paper's formulation: a
    :class:`~nrt.modules.fields.medium.NeuralMedium`-like field modulating the EA density field.
    Built as ``factory(effects, density_field)`` (``density_field`` None with ``init=none``)."""

    bbox: torch.Tensor
    density_field: DensityField | None

    def __call__(self, x: torch.Tensor):
        """:class:`~nrt.modules.fields.medium.MediumProperties` at points (..., 3)."""

    def grids(self, resolution: int) -> dict[str, torch.Tensor]:
        """Properties on ``resolution``^3 cells in the ground truth's layout."""


def members(protocol: type) -> tuple[str, ...]:
    """The attributes and methods a protocol class declares (``__call__`` included)."""
    names = list(getattr(protocol, "__annotations__", {}))
    names += [n for n, v in vars(protocol).items()
              if callable(v) and (not n.startswith("_") or n == "__call__")]
    return tuple(dict.fromkeys(names))


def build(factory: Callable, protocol: type, group: str, needs: str, *args, **kwargs):
    """``factory(*args, **kwargs)``, refused with a :class:`~nrt.errors.ConfigError` naming
    ``model/<group>`` (plus ``needs``: which options fit) when the factory does not take
    these arguments or what it builds lacks a member of ``protocol``."""
    where = f"The protocol: {protocol.__name__} in nrt/modules/fields/protocols.py."
    try:
        inspect.signature(factory).bind(*args, **kwargs)
    except (TypeError, ValueError) as exc:  # ValueError: a partial's own keywords misfit
        raise ConfigError(f"model/{group}: {_name(factory)} cannot be built as this stage "
                          f"builds its {group} ({exc}). {needs}. {where}") from None
    component = factory(*args, **kwargs)
    missing = [m for m in members(protocol) if not hasattr(component, m)]
    if missing:
        raise ConfigError(f"model/{group}: {type(component).__name__} lacks {missing}. {needs}. "
                          f"{where}")
    return component


def _name(factory: Callable) -> str:
    return getattr(getattr(factory, "func", factory), "__name__", repr(factory))
