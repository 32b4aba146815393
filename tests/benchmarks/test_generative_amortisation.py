"""benchmarks/generative_amortisation.py: a generative run's rows carry both stages' seconds
at each validation; the summary finds when its mean first reaches the single-scene runs'
mean end, and says so where it never does."""

from __future__ import annotations

import json

import pytest
from torch.utils.tensorboard import SummaryWriter

from benchmarks.common import append_rows, read_table, validation_rows
from benchmarks.generative_amortisation import FIELDS, SIGMA_T, summary
from tests.benchmarks.test_generative_stage1 import write_log

pytestmark = pytest.mark.unit


def single(member: int, start: float, end: float, stage1_s: float, stage2_s: float) -> dict:
    return {"kind": "single", "preset": "cpu", "seed": 0, "member": member, "step": 1500,
            "stage1_s": stage1_s, "stage2_s": stage2_s, "sigma_t_start": start,
            "sigma_t": end}


def generative(step: int, stage2_s: float, mean: float) -> dict:
    return {"kind": "generative", "preset": "cpu", "seed": 0, "member": "", "step": step,
            "stage1_s": 300.0, "stage2_s": stage2_s, "sigma_t_start": 40.0, "sigma_t": mean}


def test_the_time_to_reach_is_the_first_validation_at_or_below_the_single_runs_mean(
        tmp_path) -> None:
    table = tmp_path / "rows.csv"
    # single runs: mean end 20, total (100 + 400) + (150 + 350) = 1000 s
    append_rows(table, FIELDS, [single(0, 30.0, 15.0, 100, 400),
                                single(1, 50.0, 25.0, 150, 350)])
    # the generative mean: 40 at 0 s, 21 at 200 s, 20 at 400 s (reached: 300 + 400 = 700 s),
    # then 18
    append_rows(table, FIELDS, [generative(1000, 400.0, 20.0), generative(0, 0.0, 40.0),
                                generative(500, 200.0, 21.0), generative(1500, 600.0, 18.0)])
    line = summary(read_table(table)).splitlines()[2]
    assert line == ("| cpu | 0 | default / default | 40.0 -> 20.0 | 1000 | 40.0 -> 18.0 "
                    "| 700 | 0.70 |")


def test_a_generative_run_that_never_reaches_it_reports_its_best(tmp_path) -> None:
    table = tmp_path / "rows.csv"
    append_rows(table, FIELDS, [single(0, 30.0, 10.0, 100, 400)])
    append_rows(table, FIELDS, [generative(0, 0.0, 40.0), generative(500, 200.0, 12.5),
                                generative(1000, 400.0, 14.0)])
    line = summary(read_table(table)).splitlines()[2]
    assert line == ("| cpu | 0 | default / default | 30.0 -> 10.0 | 500 | 40.0 -> 14.0 "
                    "| not reached (best 12.5 at 500 s) | - |")


def test_each_generative_run_is_a_line_against_the_same_single_runs(tmp_path) -> None:
    """Two generative runs of one seed (the default, a named stage-2 configuration) each
    get their line, both against the one set of single-scene runs."""
    table = tmp_path / "rows.csv"
    append_rows(table, FIELDS, [single(0, 30.0, 10.0, 100, 400)])
    append_rows(table, FIELDS, [generative(0, 0.0, 40.0), generative(500, 200.0, 12.5)])
    other = {"stage1": "latent_dim16", "config": "two_a_step"}
    append_rows(table, FIELDS, [{**generative(0, 0.0, 40.0), **other},
                                {**generative(500, 100.0, 9.0), **other}])
    lines = summary(read_table(table)).splitlines()[2:]
    assert lines == ["| cpu | 0 | default / default | 30.0 -> 10.0 | 500 | 40.0 -> 12.5 "
                     "| not reached (best 12.5 at 500 s) | - |",
                     "| cpu | 0 | latent_dim16 / two_a_step | 30.0 -> 10.0 | 500 | 40.0 -> 9.0 "
                     "| 400 | 0.80 |"]


def test_validation_rows_carry_the_training_seconds_from_either_log(tmp_path) -> None:
    """From the CSV log and from TensorBoard alike, each validation holds the seconds logged
    at its step (a training row's later seconds do not leak in)."""
    records = [(0, 0.0, 40.0), (500, 210.5, 30.0), (1000, 420.25, 25.0)]
    csv_run, tb_run = tmp_path / "csv_run", tmp_path / "tb_run"
    write_log(csv_run, [row for step, s, mean in records
                        for row in ({"step": step, "time/wall_s": s, SIGMA_T: mean},
                                    {"step": step + 1, "time/wall_s": s + 1.0,
                                     "train/loss": 0.1})])
    writer = SummaryWriter(str(tb_run / "tensorboard"))
    for step, s, mean in records:
        writer.add_scalar(SIGMA_T, mean, step)
        writer.add_scalar("time/wall_s", s, step)
        writer.add_scalar("time/wall_s", s + 1.0, step + 1)
    writer.close()
    (tb_run / "run.json").write_text(json.dumps({}))
    for run in (csv_run, tb_run):
        rows = validation_rows(run)
        assert [(r["step"], r["time/wall_s"], r[SIGMA_T]) for r in rows] == \
            [(float(step), pytest.approx(s), pytest.approx(mean)) for step, s, mean in records]
