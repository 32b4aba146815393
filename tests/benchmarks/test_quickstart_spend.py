"""The quickstart-spend benchmark: each option's stages compose at its preset with its
overrides, and the options differ from the quickstart in the one way their names say."""

from __future__ import annotations

import csv

import pytest
from omegaconf import OmegaConf

from benchmarks.common import compose_train
from benchmarks.quickstart_spend import COLUMNS, options, write_table

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


def test_the_default_preset_is_the_fine_one():
    """``nrt-train`` with no preset runs the quickstart's ``cpu_fine``: 128 x 128 photos and
    1024 photo rays, where ``cpu`` has 64 x 64 and 512."""
    default, cpu = compose_train(["stage=rte"]), compose_train(["stage=rte", "preset=cpu"])
    assert (default.scene.cameras.width, default.budget.rte.photo_rays) == (128, 1024)
    assert (cpu.scene.cameras.width, cpu.budget.rte.photo_rays) == (64, 512)


def test_a_row_from_before_a_column_keeps_its_values_and_gets_it_blank(tmp_path):
    old = {k: "1" for k in COLUMNS if k != "start_sigma_t_x100"}
    new = {**old, "option": "fine", "start_sigma_t_x100": "9.34"}
    write_table(tmp_path / "t.csv", [old, new])
    rows = list(csv.DictReader((tmp_path / "t.csv").open()))
    assert list(rows[0]) == COLUMNS
    assert rows[0]["start_sigma_t_x100"] == "" and rows[0]["option"] == "1"
    assert rows[1]["start_sigma_t_x100"] == "9.34" and rows[1]["option"] == "fine"
