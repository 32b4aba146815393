"""benchmarks/generative_stage1.py: a run's row holds every member's last logged density
correlation in member order, the table resumes, and the summary is computed from the CSV."""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest

from benchmarks.common import append_rows, read_table
from benchmarks.generative_stage1 import FIELDS, run_row, single_row, summary
from tests.conftest import ROOT

pytestmark = pytest.mark.unit


def write_log(run, rows: list[dict]) -> None:
    (run / "csv").mkdir(parents=True)
    keys = sorted({k for r in rows for k in r})
    with open(run / "csv" / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)


def test_a_row_holds_every_members_last_correlation_in_member_order(tmp_path) -> None:
    members = {f"val/density_corr_member{k}": 0.5 for k in range(11)}  # 10 sorts before 2
    last = {f"val/density_corr_member{k}": 0.80 + 0.01 * k for k in range(11)}
    write_log(tmp_path, [{**members, "val/psnr": 20.0, "time/wall_s": 5.0},
                         {"train/loss": 0.1},  # a training row: validation keys empty
                         {**last, "val/psnr": 31.5, "time/wall_s": 29.8}])
    row = run_row(tmp_path, "latent_input", "tiny", 2)
    assert row["corr_members"].split(";") == [f"{0.80 + 0.01 * k:.4f}" for k in range(11)]
    assert float(row["corr_min"]) == pytest.approx(0.80)
    assert float(row["corr_mean"]) == pytest.approx(0.85)
    assert row["psnr"] == "31.500" and row["train_s"] == "29.8"
    assert row["overrides"] == "mode.latent.input=true mode.latent.ea_steps_scale=1"


def test_the_single_scene_reference_row_holds_one_run_per_member_in_order(tmp_path) -> None:
    runs = []
    for k, corr in enumerate((0.91, 0.88, 0.95)):
        run = tmp_path / f"member{k}"
        write_log(run, [{"val/density_corr": 0.1, "val/psnr": 20.0, "time/wall_s": 1.0},
                        {"val/density_corr": corr, "val/psnr": 30.0 + k,
                         "time/wall_s": 10.0 + k}])
        runs.append(run)
    row = single_row(runs, "cpu", 1)
    assert row["corr_members"] == "0.9100;0.8800;0.9500"
    assert row["corr_min"] == "0.8800"
    assert float(row["corr_mean"]) == pytest.approx(0.9133, abs=1e-4)
    assert row["psnr"] == "31.000" and row["train_s"] == "33.0"
    assert (row["config"], row["preset"], row["seed"]) == ("single", "cpu", 1)


def test_the_summary_gives_mean_and_spread_per_configuration(tmp_path) -> None:
    table = tmp_path / "rows.csv"
    base = {"preset": "tiny", "corr_members": "", "train_s": "30", "overrides": ""}
    for seed, (config, mean, worst, psnr) in enumerate(
            [("default", 0.80, 0.70, 31.0), ("default", 0.84, 0.78, 33.0),
             ("latent_input", 0.87, 0.85, 32.0)]):
        append_rows(table, FIELDS, [{**base, "config": config, "seed": seed,
                                     "corr_mean": mean, "corr_min": worst, "psnr": psnr}])
    assert len(read_table(table)) == 3
    lines = summary(read_table(table)).splitlines()
    assert lines[2] == "| default | tiny | 2 | 0.820 ± 0.028 | 0.700 | 32.000 ± 1.414 |"
    assert lines[3] == "| latent_input | tiny | 1 | 0.870 ± 0.000 | 0.850 | 32.000 ± 0.000 |"


@pytest.mark.slow  # 4 s: the benchmark run as a command
def test_an_unknown_configuration_stops_before_training(tmp_path) -> None:
    proc = subprocess.run([sys.executable, "-m", "benchmarks.generative_stage1",
                           "--configs", "latent_inptu", "--table", str(tmp_path / "t.csv")],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and "unknown configuration 'latent_inptu'" in proc.stderr
    assert not (tmp_path / "t.csv").exists()
