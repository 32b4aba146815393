"""benchmarks/generative_samples.py: a row holds the members' start from stage 2's first
validation and their reconstructions from ``nrt-sample``'s report, member by member; the
table round-trips and its summary shows every run."""

from __future__ import annotations

import pytest

from benchmarks.common import read_table
from benchmarks.generative_samples import FIELDS, append_rows, sample_row, summary
from tests.benchmarks.test_generative_stage1 import write_log
from tests.benchmarks.test_generative_stage2 import K, validation

pytestmark = pytest.mark.unit


def report(recon_sigma_t: list[float]) -> dict:
    """An ``nrt-sample`` metrics.json of K members, listed out of member order, with the
    fold's figures and FID of every reference under both skies."""
    members = [{"member": k, "name": f"family_seed{k}", "mse_sigma_t_x100": recon_sigma_t[k],
                "mse_sigma_s_x100": 0.5 * recon_sigma_t[k]} for k in reversed(range(K))]
    metrics = {"n_samples": 16.0, "fold_steps": 2000.0, "fold_start": 2.97, "fold_end": 0.40,
               "fold_s": 60.0, "wall_s": 400.0}
    for i, col in enumerate(("train", "novel")):
        for j, ref in enumerate(("", "_truth", "_recon")):
            metrics[f"fid_{col}_illumination{ref}"] = 50.0 + 10 * i + j
    return {"metrics": metrics, "members": members}


def test_a_row_compares_each_members_reconstruction_with_its_own_start(tmp_path) -> None:
    # starts 10, 20, 30 (validation(0, 10.0): member k at 10 (k + 1)); the last member ends
    # above its start, so 2 of 3 are below and the worst ratio is its 33 / 30
    write_log(tmp_path, [validation(0, 10.0), validation(19, 4.0)])
    row = sample_row(tmp_path, report([5.0, 10.0, 33.0]), "latent_dim16",
                     "two_a_step_dim16_free_offsets", "cpu", 2)
    assert row["sigma_t_start"] == f"{20.0:.4f}" and row["sigma_t_recon"] == f"{16.0:.4f}"
    assert row["sigma_s_start"] == f"{40.0:.4f}" and row["sigma_s_recon"] == f"{8.0:.4f}"
    assert row["members_below_start"] == 2 and row["worst_recon_over_start"] == "1.1000"
    assert (row["fid_train"], row["fid_train_truth"], row["fid_novel_recon"]) \
        == ("50.000", "51.000", "62.000")
    assert row["fold_steps"] == 2000 and row["sample_s"] == "460.0" and row["n"] == 16


def test_a_run_without_a_fold_records_none(tmp_path) -> None:
    write_log(tmp_path, [validation(0, 10.0)])
    metrics = report([1.0, 2.0, 3.0])
    for key in ("fold_steps", "fold_start", "fold_end", "fold_s"):
        del metrics["metrics"][key]
    row = sample_row(tmp_path, metrics, "latent_dim16", "two_a_step_dim16", "cpu", 0)
    assert row["fold_steps"] == 0 and row["fold_end"] == "nan" and row["sample_s"] == "400.0"


def test_the_table_round_trips_and_the_summary_shows_every_run(tmp_path) -> None:
    write_log(tmp_path, [validation(0, 10.0)])
    table = tmp_path / "samples.csv"
    for seed in (0, 1):
        append_rows(table, FIELDS, [sample_row(tmp_path, report([5.0, 10.0, 33.0]),
                                               "latent_dim16", "long", "cpu", seed)])
    rows = read_table(table)
    assert [r["seed"] for r in rows] == ["0", "1"] and set(rows[0]) == set(FIELDS)
    lines = summary(rows).splitlines()
    assert len(lines) == 4
    assert "| 20.0 -> 16.0 | 2 | 1.10 | 50.0 / 60.0 | 51.0 / 61.0 | 52.0 / 62.0 |" in lines[2]
