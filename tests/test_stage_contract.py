"""Every stage keeps the contract of :mod:`nrt.modules.stages.stage` that callbacks, evaluation
and the CLI rely on (they no longer probe stages for what they offer)."""

from __future__ import annotations

import hydra
import pytest
from conftest import compose_config

from nrt.modules.stages.stage import Stage

STAGES = {  # a medium (property grids)? g scored (the default scene's phase is hg)?
    ("ea",): (False, True),
    ("ea", "mode=generative", "scene=family"): (False, True),
    ("rte", "init=none"): (True, True),
    ("rte", "init=none", "experiment=rte_paper"): (True, True),
    ("forward",): (False, True),
    ("forward", "experiment=rte_paper"): (False, True),
    ("dpt",): (True, False),  # phase=hg: dpt keeps the one g fixed
}


@pytest.mark.parametrize(("overrides", "expected"), list(STAGES.items()),
                         ids=[" ".join(k) for k in STAGES])
def test_every_stage_keeps_the_contract(overrides, expected):
    stage, *rest = overrides
    cfg = compose_config("train", [f"stage={stage}", "preset=tiny", *rest])
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    assert isinstance(model, Stage)
    learns_medium, learns_g = expected
    assert model.effects == ({} if stage == "ea" else dict(cfg.scene.effects))
    assert model.learns_g == learns_g
    # outside a trainer: no data, no progress, the requested or fallback resolution
    assert model.datamodule() is None and model.ground_truth() is None
    assert model.progress() == 0.0 and model.grid_resolution(None, 7) == 7
    grids = model.property_grids(4)
    if learns_medium:  # in the ground truth's layout, whatever the stage's own grids
        assert grids["sigma_a"].shape == (4, 4, 4, 3) and grids["g"].shape == (4, 4, 4)
        assert model.medium_bbox().shape == (2, 3)
    else:
        assert grids is None
