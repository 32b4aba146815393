"""The paper's evaluation at CPU scale (``benchmarks.paper_tables``): the benchmark sets
follow the paper's recipe on seeds nothing was tuned on, every planned run composes, the
tables are redrawn from the recorded files alone, and the command runs end to end at
``tiny``."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from benchmarks.common import SCENES
from benchmarks.paper_tables import (
    load_sets,
    planned_runs,
    read_results,
    redraw,
    scene_name,
    scene_overrides,
    time_left,
)
from nrt.data.spec import resolve_scene
from tests.conftest import ROOT, compose_config

pytestmark = pytest.mark.integration

SETS = load_sets()


def _set_scenes():
    for set_name, spec in SETS["sets"].items():
        for scene in spec["scenes"]:
            yield set_name, spec["phase"], scene


def test_the_sets_follow_the_recipe_on_seeds_never_tuned_on():
    """1-4 elements, coefficients up to 5 per unit length, g = 0 in the isotropic set and
    per element in [-0.5, 0.5] in the anisotropic one; no seed of the sets is a seed of a
    scene any default was chosen on (or of the blind scenes)."""
    used = {int(o.split("=")[1]) for overrides in SCENES.values() for o in overrides
            if o.startswith("scene.seed=")} | {0}
    seeds = [scene["seed"] for _, _, scene in _set_scenes()]
    assert len(set(seeds)) == len(seeds) and not used & set(seeds)
    gs = []
    for set_name, phase, scene in _set_scenes():
        cfg = compose_config("dataset", ["preset=tiny", *scene_overrides(set_name, phase, scene)])
        spec = resolve_scene(OmegaConf.to_container(cfg.scene, resolve=True))
        elements = spec["medium"]["elements"]
        assert 1 <= len(elements) == scene["elements"] <= 4
        for e in elements:
            sigma_t = np.add(e["sigma_a"], e["sigma_s"])
            assert sigma_t.max() <= 5.0 + 1e-9 and sigma_t.min() > 0
            if phase == "varying_hg":
                gs.append(e["g"])
            else:
                assert e["g"] == 0.0
    assert all(-0.5 <= g <= 0.5 for g in gs) and len({round(g, 6) for g in gs}) == len(gs)


def test_every_planned_run_composes():
    """Each method and ablation of the sets file, on a scene of each set, is a valid
    ``nrt-train`` command line (composition as the CLI does it)."""
    runs = planned_runs(SETS, {"iso": 1, "aniso": 1}, 1, list(SETS["ablations"]))
    assert len(runs) == 2 * len(SETS["methods"]) + len(SETS["ablations"])
    iso = len(SETS["methods"]) + len(SETS["ablations"])  # the ablated scene's runs come first
    assert {r[0] for r in runs[:iso]} == {"iso"} and {r[0] for r in runs[iso:]} == {"aniso"}
    for set_name, scene, _, overrides in runs:
        phase = SETS["sets"][set_name]["phase"]
        cfg = compose_config("train", ["preset=cpu", *overrides,
                                       *scene_overrides(set_name, phase, scene)])
        assert cfg.scene.name == scene_name(set_name, scene["seed"])
        assert cfg.scene.effects.phase == phase


def _record(data: Path, set_name: str, scene: str, method: str, sigma_t: float,
            code: str = "abc1234") -> None:
    folder = data / set_name / scene
    folder.mkdir(parents=True, exist_ok=True)
    (folder / f"{method}.csv").write_text("wall_s,sigma_a,sigma_s,sigma_t,g\n0,1,2,9,\n"
                                          f"10,1,2,{sigma_t},\n")
    metrics = {"mse_sigma_a_x100": 1.0, "mse_sigma_s_x100": 2.0, "mse_sigma_t_x100": sigma_t,
               "psnr_novel": 30.0, "ssim_novel": 0.9, "lpips_novel": 0.1,
               "psnr_noise_floor_novel": 40.0}
    (folder / f"{method}.json").write_text(json.dumps({
        "set": set_name, "scene": scene, "seed": 1, "method": method, "budget_s": 10.0,
        "preset": "tiny", "seconds": 10.0, "steps": 50, "curve_points": 2, "learns_g": False,
        "code": code, "metrics": metrics}))


def test_tables_are_redrawn_from_the_recorded_files(tmp_path):
    """Table 1 has a row per scene and method and the mean ± std over scenes; the paper's
    numbers stand beside it marked not comparable; Table 3 holds only the ablated scenes,
    stage 2's row beside each ablation; each table names the commits its rows ran on."""
    data = tmp_path / "data"
    for scene, (rte, dpt) in {"paper_iso_1": (2.0, 6.0), "paper_iso_2": (4.0, 8.0)}.items():
        _record(data, "iso", scene, "rte", rte)
        _record(data, "iso", scene, "dpt", dpt)
    _record(data, "iso", "paper_iso_1", "single_stage", 5.0, code="def5678 + changes")
    assert set(read_results(data)["iso"]) == {"paper_iso_1", "paper_iso_2"}
    redraw(data, tmp_path / "figures", SETS)
    table1 = (data / "table1.md").read_text()
    assert "| **mean ± std, 2 scenes** | stage 2 (nrt) | 1.000 ± 0.000 | 2.000 ± 0.000 | " \
        "3.000 ± 1.414 |" in table1
    assert "| **mean ± std, 2 scenes** | path tracing (baseline) | 1.000 ± 0.000 | " \
        "2.000 ± 0.000 | 7.000 ± 1.414 |" in table1
    assert "not comparable" in table1 and "| 0.87 | 4.06 | 6.88 |" in table1
    table3 = (data / "table3.md").read_text()
    assert "paper_iso_2" not in table3 and "| paper_iso_1 | single stage" in table3
    assert table1.endswith("\nCode: abc1234.\n")  # every row's commit, once
    assert table3.endswith("\nCode: abc1234, def5678 + changes.\n")
    rows = (data / "table1.csv").read_text().splitlines()
    assert len(rows) == 1 + 4 and rows[0].startswith("scene,method,mse_sigma_a_x100")
    assert not (data / "table2.md").exists()


def test_the_time_left_counts_the_runs_to_do_and_the_scenes_still_to_prepare(tmp_path):
    """Runs whose record exists count nothing; each run to do (and the current one) counts
    the timed runs' mean; each other scene without any record counts the new scenes'
    mean render and EA time once measured, and is named apart before."""
    runs = planned_runs(SETS, {"iso": 2, "aniso": 1}, 0, [], ["rte", "dpt"])
    assert [(r[0], r[1]["seed"], r[2]) for r in runs] == [
        ("iso", 7001, "rte"), ("iso", 7001, "dpt"), ("iso", 7002, "rte"),
        ("iso", 7002, "dpt"), ("aniso", 8001, "rte"), ("aniso", 8001, "dpt")]
    record = tmp_path / "iso" / "paper_iso_7002" / "rte.json"
    record.parent.mkdir(parents=True)
    record.write_text("{}")  # 7002 is prepared and its rte run done
    later = runs[1:]  # the current run: 7001's rte
    assert time_left(later, tmp_path, "paper_iso_7001", [600.0], [300.0], 600.0) == \
        "55 min left (with the renders and EA runs of 1 new scene)"  # 5 runs, 1 scene
    assert time_left(later, tmp_path, "paper_iso_7001", [], [], 540.0) == \
        "55 min left, and the renders and EA runs of 1 new scene"  # (540 + 120) x 5
    assert time_left(runs[5:], tmp_path, "paper_aniso_8001", [600.0], [], 600.0) == \
        "20 min left"


@pytest.mark.slow
def test_the_command_runs_two_scenes_end_to_end_at_tiny(tmp_path):
    """Two scenes (one of each set), stage 2 for a few training seconds (the baseline's
    runs share the same unit, ``benchmarks.equal_time``, tested through fair_comparison's
    and stage=dpt's tests): the records, the kept slices of each set's first scene, a
    resumed run that trains nothing, the tables and figures."""
    env = {**os.environ, "NRT_OUTPUT_DIR": str(tmp_path / "outputs")}
    data = tmp_path / "data"
    cmd = [sys.executable, "-m", "benchmarks.paper_tables", "run", "--iso", "1", "--aniso", "1",
           "--ablation-scenes", "0", "--methods", "rte", "--preset", "tiny", "--budget-s", "4",
           "--every-s", "2", "--ea-steps", "20", "--data", str(data),
           "--out", str(tmp_path / "runs")]
    proc = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "[1/2]" in proc.stdout and "min left" in proc.stdout
    results = read_results(data)
    assert set(results["iso"]["paper_iso_7001"]) == {"rte"}
    assert results["aniso"]["paper_aniso_8001"]["rte"]["learns_g"]
    assert not results["iso"]["paper_iso_7001"]["rte"]["learns_g"]  # isotropic: no g
    assert len(results["iso"]["paper_iso_7001"]["rte"]["code"]) >= 7  # the commit it ran
    for set_name, scene in (("iso", "paper_iso_7001"), ("aniso", "paper_aniso_8001")):
        assert {p.name for p in (data / set_name / scene).glob("*.npz")} == \
            {"rte.npz", "ground_truth.npz"}
    again = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert again.returncode == 0 and again.stdout.count("done already") == 2
    proc = subprocess.run([sys.executable, "-m", "benchmarks.paper_tables", "redraw", "--data",
                           str(data), "--figures", str(tmp_path / "figures")], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (data / "table1.md").is_file() and (data / "table2.md").is_file()
    assert len(list((tmp_path / "figures").glob("paper_tables_slices_*.png"))) == 2
