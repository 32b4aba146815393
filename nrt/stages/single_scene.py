"""The single scene of the split stage 2 (:class:`SingleScene`, the default scene source of
:mod:`nrt.stages.scene_source`): the stage's one medium, lit by the light field of each
training sky (:class:`~nrt.stages.sky_lights.SkyLights`), and the density the medium starts
from (:class:`~nrt.stages.start.DensityStart`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from nrt.modules.fields.protocols import ScatteredLightField, VoxelisedMedium
from nrt.stages.start import DensityStart
from nrt.stages.uncollided import UncollidedCache

if TYPE_CHECKING:
    from nrt.stages.rte import RTEStage

FITS = ("The split stage (stage=rte, stage=forward) takes model/light_field=sh_grid and "
        "model/medium=voxel; the SIREN light field and the siren or grid media belong to the "
        "paper's formulation (experiment=rte_paper)")


class SingleScene:
    """One scene: the ``stage``'s medium (as transport reads it,
    :meth:`~nrt.stages.rte.RTEStage.transport_medium`) paired with the light field of each
    training environment, in the order of the stage's illuminations. The medium starts from
    ``init`` (the stage's ``density``), baked into it once the datamodule is known."""

    LIGHT_PROTOCOL = ScatteredLightField
    MEDIUM_PROTOCOL = VoxelisedMedium
    FITS = FITS

    def __init__(self, stage: RTEStage):
        self.stage = stage
        self.start = DensityStart(stage.hparams.density)
        self.baked = False
        """Whether the medium holds its start (baked, or loaded with a checkpoint's state)."""

    # ------------------------------------------------------------- the pairs
    def pairs(self, batch: dict | None = None) -> list[tuple[Any, ScatteredLightField]]:
        medium = self.stage.transport_medium()
        return [(medium, light) for light in self.stage.env_lights]

    def uncollided_due(self, cache: UncollidedCache, step: int) -> list[tuple[int, bool]]:
        """Every sky's light on the cache's schedule."""
        if not cache.due(step):
            return []
        return [(i, not cache.fresh) for i in range(len(self.stage.env_lights))]

    def scene_of(self, batch: dict) -> torch.Tensor | None:
        """Each ray's environment among the training ones (``env``); None with one."""
        if len(self.stage.env_lights) == 1:
            return None
        return self.stage.sky_lights.scenes_of(batch["env"])

    def view_pair(self, batch: dict) -> tuple[Any, ScatteredLightField]:
        """The medium, and the light field of the view's environment (``env``)."""
        return self.stage.transport_medium(), self.stage.sky_lights.of_env(int(batch["env"]))

    def fresh_voxels(self) -> list:
        return [self.stage.medium.voxels()]

    def backward_media(self, backward) -> None:
        """Nothing: the objectives backpropagate into the medium themselves."""

    # --------------------------------------------------------------- training
    def priors(self) -> dict[str, torch.Tensor]:
        return {}

    def step_metrics(self) -> dict[str, torch.Tensor]:
        return {}

    def param_groups(self) -> list[dict]:
        return []

    def member_parameters(self) -> list:
        return []

    def setup(self, datamodule) -> None:
        """Bake the start into a learned medium (:meth:`DensityStart.bake`), unless it holds
        one already (a resumed run loads the same values)."""
        if self.stage.learns_medium and self.start.bakes and not self.baked:
            self.start.bake(self.stage.medium, datamodule.ground_truth)
            self.baked = True

    def on_load_checkpoint(self, checkpoint: dict) -> None:
        """The baked start comes with the state (no EA field needed)."""
        self.baked = True

    def settings(self) -> dict:
        return {}

    # ------------------------------------------------------- grids and export
    def property_grids(self, resolution: int) -> dict[str, torch.Tensor] | None:
        """The learned medium on R^3 cells; None in forward mode."""
        return self.stage.medium.grids(resolution) if self.stage.learns_medium else None

    def member_property_grids(self, member: int, resolution: int) -> None:
        return None

    def export(self, run_dir: Path, resolution: int | None) -> dict[str, str]:
        """Nothing beside the stage's own ``medium_grids.npz``."""
        return {}
