"""Objectives as units: a name, a weight schedule and a loss (threestudio's ``lambda_*``).

A stage's objectives are components chosen by config: ``losses.objectives`` names each by
the key it goes by (``photo: {_target_: nrt.losses.photo.PhotoObjective, _partial_: true}``)
and ``losses.weights`` gives each its weight under the same key. The stage builds them
(:func:`build_objectives`) and each step backpropagates ``weight(step, progress) * loss``
of those whose weight is positive; the others are not evaluated (nor their samples drawn)
that step. A weight is a number or ``[start, end, ramp_steps]`` (linear over the first
``ramp_steps`` steps, then constant), and may be off until a share of the run has passed
(``starts_at``: the split stage's objectives of the medium wait for ``light_warmup``).

An objective takes its sample counts as constructor keywords (the entry's keywords in
``losses.objectives``), and its :meth:`Objective.loss` reads the ray batch and the step's
:class:`~nrt.losses.context.StepContext` (the (medium, light) pairs it is taken over, the
illumination, the in-scattering the stage supplies), never the stage.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from numbers import Real
from typing import Any

import torch

from nrt.errors import ConfigError
from nrt.losses.context import StepContext


class WeightSchedule:
    """An objective's weight at a step and a point of the run's progress in [0, 1]:
    ``value`` constant, or ``[start, end, ramp_steps]`` linear from start to end over the
    first ``ramp_steps`` steps, then constant; 0 while ``progress < starts_at``."""

    def __init__(self, value: float | Sequence[float], starts_at: float = 0.0,
                 key: str = "losses.weights"):
        ramp = isinstance(value, Sequence) and not isinstance(value, str)
        items = list(value) if ramp else [value]
        if (ramp and len(items) != 3) or not all(
                isinstance(v, Real) and not isinstance(v, bool) and math.isfinite(v)
                for v in items):
            raise ConfigError(f"{key}={value}: a weight is a finite number or [start, end, "
                              "ramp_steps] (linear from start to end over ramp_steps steps).")
        self.value = tuple(float(v) for v in items) if ramp else float(value)
        self.starts_at = float(starts_at)

    def __call__(self, step: int, progress: float) -> float:
        if progress < self.starts_at:
            return 0.0
        if isinstance(self.value, tuple):
            start, end, steps = self.value
            return float(start + (end - start) * min(step / max(steps, 1), 1.0))
        return self.value

    def __repr__(self) -> str:
        value = list(self.value) if isinstance(self.value, tuple) else self.value
        late = f", starts_at={self.starts_at}" if self.starts_at else ""
        return f"WeightSchedule({value}{late})"


class Objective:
    """One objective of a stage: :attr:`name` (its key in ``losses.objectives`` and
    ``losses.weights``, and its metrics ``train/loss_<name>``, ``time/step_<name>_s``), a
    :class:`WeightSchedule` and :meth:`loss`. Subclasses implement :meth:`loss` and say
    where they apply (:attr:`families`, :attr:`medium_only`)."""

    families: bool = False
    """Whether :meth:`loss` takes a family's scenes (the generative stage), not one alone."""
    medium_only: bool = False
    """Whether it trains the medium alone: the split stage starts it after the light
    field's warm-up (``light_warmup``), and forward mode (the medium is the ground truth)
    leaves it out."""
    reads_voxels: bool = False
    """Whether it reads the step's voxel media (:meth:`StepContext.voxel_media`): a prior
    that only the split stage 2 can have."""

    def __init__(self, name: str, schedule: WeightSchedule):
        self.name, self.schedule = name, schedule

    def weight(self, step: int, progress: float) -> float:
        """The weight at ``step`` and run progress ``progress`` in [0, 1]."""
        return self.schedule(step, progress)

    def loss(self, batch: dict, context: StepContext) -> torch.Tensor:
        """The unweighted loss on fresh samples and the ray ``batch``, over the step's
        ``context.scenes``."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, {self.schedule!r})"


def objective_class(target: Any, key: str) -> type[Objective]:
    """``target`` (what a ``_target_`` names, or a factory of it) as the
    :class:`Objective` subclass it is; anything else is refused naming ``key``
    (``losses.objectives.photo``)."""
    unit = getattr(target, "func", target)  # a functools.partial: its class
    if isinstance(unit, type) and issubclass(unit, Objective):
        return unit
    what = getattr(unit, "__qualname__", type(unit).__name__)
    raise ConfigError(f"{key} names {what}, which is not an objective: an entry of "
                      "losses.objectives has `_target_: <module>.<Class>` of a subclass of "
                      "nrt.losses.objective.Objective and `_partial_: true` (the stage "
                      "builds it with its weight).")


def build_objectives(weights: Mapping[str, Any],
                     factories: Mapping[str, Callable[..., Objective]],
                     starts_at: Mapping[str, float] | None = None, hint: str = ""
                     ) -> dict[str, Objective]:
    """The objectives ``factories`` (name -> a unit's factory, from ``losses.objectives``)
    builds, each with the weight ``weights`` gives its name, in the order of ``weights``
    (the order the stage draws their samples in); ``starts_at`` holds warm-ups by name. A
    weight for no objective, an objective without a weight and a factory of anything but
    an :class:`Objective` are refused naming the key (``hint`` ends the first message)."""
    unknown = sorted(set(weights) - set(factories))
    if unknown:
        raise ConfigError(f"losses.weights has unknown objectives {unknown}; the objectives "
                          f"are {list(factories)} (losses.objectives){hint}.")
    unweighted = [name for name in factories if name not in weights]
    if unweighted:
        raise ConfigError(f"losses.objectives.{unweighted[0]} has no weight: give it one "
                          f"(losses.weights.{unweighted[0]}=<weight>; 0 keeps it off), or "
                          f"remove it (~losses.objectives.{unweighted[0]}).")
    for name, factory in factories.items():
        objective_class(factory, f"losses.objectives.{name}")
    starts_at = starts_at or {}
    return {name: factories[name](name=name, schedule=WeightSchedule(
                value, starts_at.get(name, 0.0), f"losses.weights.{name}"))
            for name, value in weights.items()}


def scene_mean(scenes: torch.Tensor,
                loss_of: Callable[[int, torch.Tensor], torch.Tensor]) -> torch.Tensor:
    """The mean over items of a loss computed scene by scene: ``sum_k (n_k / n)
    loss_of(k, mask_k)``, with ``scenes`` (n,) each item's scene (a position in the step's
    ``Scenes``) and ``loss_of`` a mean over the items of ``mask_k``."""
    total = torch.zeros(())
    for k in scenes.unique().tolist():
        mask = scenes == k
        total = total + mask.float().mean() * loss_of(k, mask)
    return total
