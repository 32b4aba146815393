"""What the split stage 2 (:class:`~nrt.stages.rte.RTEStage`) trains on: its scene source
(:class:`SceneSource`), the (medium, light) pairs of a step and what belongs to them.

The stage is one; its source is what differs between training one scene and a family of
scenes: :class:`~nrt.stages.single_scene.SingleScene` (the default: the stage's medium lit
by the light field of each training sky) and :class:`~nrt.stages.family.SceneFamily`
(``mode=generative``: one medium and one light per family member, decoded from latent
codes). A source is chosen by ``model.scenes``, a config with ``_target_`` and
``_partial_: true`` (null: the single scene); the stage builds its light field and medium
against the source's protocols, then calls the factory with itself (``factory(stage)``).

Media in the pairs are as transport reads them (composed voxels, or the ground truth in
forward mode); lights are scattered-light fields (:mod:`nrt.modules.fields.protocols`).
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from pathlib import Path
from typing import Any, ClassVar, Protocol

import torch

from nrt.errors import ConfigError
from nrt.stages.components import as_factory
from nrt.stages.single_scene import SingleScene
from nrt.stages.uncollided import UncollidedCache


class SceneSource(Protocol):
    """The (medium, light) pairs a split stage-2 step trains on, and what the stage asks of
    them besides: validation's pair, extra losses and optimiser groups, set-up, the learned
    media as grids and the export."""

    LIGHT_PROTOCOL: ClassVar[type]
    """The protocol the stage's light field keeps (``model/light_field``)."""
    MEDIUM_PROTOCOL: ClassVar[type]
    """The protocol the stage's medium keeps (``model/medium``)."""
    FITS: ClassVar[str]
    """Which light fields and media fit, for the stage's refusal of one that does not."""

    def pairs(self, batch: dict) -> list[tuple[Any, Any]]:
        """The (medium, light) pairs of a training step on the ray ``batch``, with gradient
        to what they are made of; called once a step, first."""

    def scene_of(self, batch: dict) -> torch.Tensor | None:
        """Each ray's pair (B,), an index into :meth:`pairs`; None where there is one pair."""

    def uncollided_due(self, cache: UncollidedCache, step: int) -> list[tuple[int, bool]]:
        """The step's pairs (positions in :meth:`pairs`) whose light's uncollided cache is
        refreshed at ``step``, each with whether it is its first refresh (replaced, not
        blended); ``cache`` keeps the schedule."""

    def view_pair(self, batch: dict) -> tuple[Any, Any]:
        """The (medium, light) pair that renders a held-out view (``batch``: ``env``, and a
        family's ``member``)."""

    def fresh_voxels(self) -> list:
        """The learned media as the step's priors read them: composed anew (a graph of their
        own, for an objective that reads them after another's backward has freed the
        step's), or the leaves that :meth:`pairs` handed out (:meth:`backward_media`)."""

    def backward_media(self, backward: Callable[[torch.Tensor], None]) -> None:
        """After every objective's backward of a step: backpropagate (by ``backward``) what
        they left on media that :meth:`pairs` handed out as leaves; nothing for a source
        whose objectives reach the parameters directly."""

    def priors(self) -> dict[str, torch.Tensor]:
        """Losses on the source's own parameters by name, which the stage backpropagates
        while a medium objective runs and logs as ``train/<name>``; {} for none."""

    def step_metrics(self) -> dict[str, torch.Tensor]:
        """Values the stage logs each step as ``train/<name>``; {} for none."""

    def param_groups(self) -> list[dict]:
        """Adam's groups of the source's own parameters, after the stage's."""

    def member_parameters(self) -> list[tuple[torch.nn.Parameter, int, int]]:
        """Parameters (of any group) that hold one block per member, as (parameter, members,
        member axis), for Adam to step each block only on its member's steps
        (:class:`~nrt.stages.member_adam.MemberAdam`); [] for none."""

    def setup(self, datamodule) -> None:
        """Once the datamodule is attached and the stage has set its boxes and skies."""

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """Before the stage loads ``checkpoint``'s state."""

    def settings(self) -> dict:
        """Keywords of the factory, learned at the start of a run, that checkpoints record
        beside the config (``model.scenes``) to rebuild the source; {} for none."""

    def property_grids(self, resolution: int) -> dict[str, torch.Tensor] | None:
        """:meth:`Stage.property_grids <nrt.stages.stage.Stage.property_grids>`."""

    def member_property_grids(self, member: int, resolution: int
                              ) -> dict[str, torch.Tensor] | None:
        """:meth:`Stage.member_property_grids
        <nrt.stages.stage.Stage.member_property_grids>`."""

    def export(self, run_dir: Path, resolution: int | None) -> dict[str, str]:
        """Files written into ``run_dir`` beside the stage's own export, at ``resolution``
        cells per axis (None: the ground truth's, else 64); name -> path."""


CLASS_MEMBERS = ("LIGHT_PROTOCOL", "MEDIUM_PROTOCOL", "FITS")
"""What the stage reads of a source's class before it builds the source."""


def scene_source_factory(scenes: Any) -> functools.partial:
    """``model.scenes`` as a source's factory: None is the single scene; a config or a
    partial (:func:`~nrt.stages.components.as_factory`) of a class with
    :data:`CLASS_MEMBERS`."""
    if scenes is None:
        return functools.partial(SingleScene)
    factory = as_factory(scenes, "scenes", home="conf/mode_stage/<mode>_rte.yaml")
    missing = [name for name in CLASS_MEMBERS if not hasattr(factory.func, name)]
    if missing:
        raise ConfigError(f"model.scenes: {getattr(factory.func, '__name__', factory.func)} "
                          f"lacks {missing}; a scene source is a class that names the "
                          "protocols of its light field and medium (nrt/stages/scene_source.py).")
    return factory
