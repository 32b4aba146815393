"""The benchmarks' shared helpers: the EA start of a benchmark is the newest *finished* EA
run on the same photos; a run killed before its end is never taken for one, nor read as a
finished run's results."""

from __future__ import annotations

import os
import time

import pytest

from benchmarks.common import ea_runs, newest_checkpoint, unfinished_run_error
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
