"""The GPU smoke benchmark's bookkeeping: a stage's row from its run folder (steps, seconds,
the cap, peak memory, property MSE from start to end) and the photos the full paper
preset adds to the memory that --cpu-memory measures."""

from __future__ import annotations

import csv
import json
from types import SimpleNamespace

import pytest

from benchmarks.gpu_smoke import photo_bytes, stage_row, views

pytestmark = pytest.mark.unit


def test_a_stage_row_reads_its_run(tmp_path):
    (tmp_path / "run.json").write_text(json.dumps(
        {"finished_step": 100, "final_metrics": {"time/wall_s": 150.0}}))
    (tmp_path / "csv").mkdir()
    rows = [{"step": 0, "val/mse_sigma_t_x100": 9.5},
            {"step": 1, "memory/peak_cuda_gib": 3.25, "memory/peak_rss_gib": 4.0},
            {"step": 2, "memory/peak_cuda_gib": 7.5, "memory/peak_rss_gib": 4.5},
            {"step": 100, "val/mse_sigma_t_x100": 2.25}]
    keys = sorted({k for r in rows for k in r})
    with open(tmp_path / "csv" / "metrics.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=keys)
        writer.writeheader()
        writer.writerows(rows)
    row = stage_row("rte", tmp_path, cap_s=150.0)
    assert row.startswith("| rte | 100 (capped) | 150.0 | 1.500 | 7.50 | 4.50 | - | - |")
    assert "9.500 -> 2.250" in row
    assert "(capped)" not in stage_row("rte", tmp_path, cap_s=200.0)


def test_the_full_preset_holds_more_photos_than_the_reduced_one():
    args = SimpleNamespace(views=4, test_views=2, spp=4)
    full, small = photo_bytes([]), photo_bytes(views(args))
    pixels = 256 * 256 * 3 * 4  # float32 RGB at the paper preset's size
    assert full % pixels == 0 and small == (4 + 2) * 2 * pixels  # two training skies
    assert full > 50 * small
