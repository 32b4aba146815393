"""The quickstart-spend benchmark: each option's stages compose at its preset with its
overrides, and the options differ from the quickstart in the one way their names say."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from benchmarks.common import compose_train
from benchmarks.quickstart_spend import options

pytestmark = pytest.mark.unit


def budget(preset: str, stage: str, overrides: list[str]) -> tuple:
    """(stage-1 steps, stage-2 steps, photo width) of the composed run."""
    cfg = compose_train([f"stage={stage}", f"preset={preset}", *overrides])
    return (OmegaConf.select(cfg, "budget.ea.steps"), OmegaConf.select(cfg, "budget.rte.steps"),
            OmegaConf.select(cfg, "scene.cameras.width"))


def test_each_option_changes_only_what_its_name_says():
    chosen = options("cpu", "cpu_fine", rte_steps=2500, ea_steps=3000)
    quick = {stage: budget("cpu", stage, []) for stage in ("ea", "rte")}
    got = {name: {stage: budget(preset, stage, ea if stage == "ea" else rte)
                  for stage in ("ea", "rte")} for name, (preset, ea, rte) in chosen.items()}
    assert got["as_is"] == quick
    assert got["rte_steps"]["rte"][1] == 2500 and got["rte_steps"]["ea"] == quick["ea"]
    assert got["ea_steps"]["ea"][0] == 3000 and got["ea_steps"]["rte"] == quick["rte"]
    assert got["fine"]["ea"][2] == 2 * quick["ea"][2]  # 128 x 128 photos against 64 x 64
