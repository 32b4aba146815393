"""``benchmarks.step_speed``: two settings timed side by side, each run in its own process,
summarised per stage with the speed-up of B over A, every round kept with the code's
commit."""

from __future__ import annotations

import json
import math

import pytest

from benchmarks.step_speed import main

pytestmark = [pytest.mark.e2e, pytest.mark.slow]


def test_two_settings_are_timed_alternately_and_compared(tmp_path, tiny_dataset, capsys):
    data = f"paths.data_dir={tiny_dataset.parent}"
    table = main(["--stages", "ea", "--preset", "tiny", "--rounds", "1", "--steps", "2",
                  "--warmup", "1", "--a", data, "--b", f"{data} budget.ea.samples_per_ray=8",
                  "--json", str(tmp_path / "speed.json")])
    report = json.loads((tmp_path / "speed.json").read_text())
    assert [(r["setting"].endswith("=8"), r["round"]) for r in report["rounds"]] == [
        (False, 0), (True, 0)]  # A, then B (with more rounds: A B A B)
    assert all(r["ms"] > 0 and math.isfinite(r["first_s"]) for r in report["rounds"])
    assert set(report["code"]) == {"A", "B"} and report["code"]["A"] == report["code"]["B"]
    mean = {b: next(r["ms"] for r in report["rounds"] if r["setting"].endswith("=8") == b)
            for b in (False, True)}
    assert f"| {mean[False] / mean[True]:.2f}x |" in table
    assert table in capsys.readouterr().out
