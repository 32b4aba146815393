"""The benchmarks' shared helpers: the EA start of a benchmark is the newest *finished* EA
run on the same photos; a run killed before its end is never taken for one, nor read as a
finished run's results; a resumed run's validations are read across its CSV logs."""

from __future__ import annotations

import os
import time

import pytest

from benchmarks.common import ea_runs, newest_checkpoint, unfinished_run_error, validation_rows
from nrt.run_dirs import LAST_CKPT, write_run_info

pytestmark = pytest.mark.unit


def ea_run(out, name: str, dataset: str, finished_step: int | None, age_s: float):
    run = out / "default" / "ea" / name
    (run / LAST_CKPT).parent.mkdir(parents=True)
    (run / LAST_CKPT).write_text("a checkpoint")
    stamp = time.time() - age_s
    os.utime(run / LAST_CKPT, (stamp, stamp))
    write_run_info(run, dataset_dir=f"/data/{dataset}", finished_step=finished_step)
    return run


def test_the_newest_finished_run_on_the_same_photos_is_the_start(tmp_path, monkeypatch):
    monkeypatch.setenv("NRT_OUTPUT_DIR", str(tmp_path))
    old = ea_run(tmp_path, "old", "default-aaa", 1500, age_s=300)
    ea_run(tmp_path, "killed", "default-aaa", None, age_s=10)  # newest, but killed
    ea_run(tmp_path, "other_photos", "default-bbb", 1500, age_s=5)
    assert newest_checkpoint("default", "default-aaa") == (old / LAST_CKPT).resolve()
    assert [r.name for r in ea_runs("default", "default-aaa")] == ["killed", "old"]
    assert newest_checkpoint("default", "default-ccc") is None


def test_a_killed_run_is_refused_as_results_with_the_way_to_continue_it(tmp_path) -> None:
    assert "holds no run.json" in unfinished_run_error(tmp_path)
    killed = ea_run(tmp_path, "killed", "default-aaa", None, age_s=0)
    problem = unfinished_run_error(killed)
    assert "did not reach its end" in problem and f"resume={killed / LAST_CKPT}" in problem
    assert unfinished_run_error(ea_run(tmp_path, "done", "default-aaa", 1500, age_s=0)) is None


def write_csv(path, rows: list[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    keys = sorted({k for r in rows for k in r})
    path.write_text("\n".join([",".join(keys)] + [",".join(str(r.get(k, "")) for k in keys)
                                                   for r in rows]) + "\n")


def test_a_resumed_runs_validations_continue_in_its_resumed_log(tmp_path) -> None:
    """A run killed after step 5499's validation, resumed from a checkpoint at step 5400,
    logged again from step 5400 into csv/resumed-<time>/: the validations read are the
    first log's up to 4999, then the resumed log's, each step once, the re-run one kept."""
    def val(step: int, mse: float) -> dict:
        return {"step": step, "val/mse_sigma_t_x100": mse}
    write_csv(tmp_path / "csv" / "metrics.csv",
              [val(0, 30.0), {"step": 100, "train/loss": 1.0}, val(4999, 25.0), val(5499, 9.0)])
    write_csv(tmp_path / "csv" / "resumed-2026-01-02_00-00-00" / "metrics.csv",
              [{"step": 5400, "train/loss": 0.5}, val(5499, 24.0), val(8999, 20.0)])
    write_csv(tmp_path / "csv" / "resumed-2026-01-01_00-00-00" / "metrics.csv",
              [val(5499, 99.0)])  # an older resume, replaced by the newer one
    rows = validation_rows(tmp_path)
    assert [(r["step"], r["val/mse_sigma_t_x100"]) for r in rows] \
        == [(0, 30.0), (4999, 25.0), (5499, 24.0), (8999, 20.0)]
