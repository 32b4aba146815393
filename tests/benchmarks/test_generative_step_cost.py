"""benchmarks/generative_step_cost.py: the rows still to run are those neither in the table
(under the same setting) nor asking for more members a step than the family has, and each
row names a profile's largest components, largest first."""

from __future__ import annotations

import pytest

from benchmarks.generative_step_cost import SETTINGS, largest, pending

pytestmark = pytest.mark.unit


def test_rows_already_in_the_table_or_above_k_are_not_run():
    rows = [{"preset": "cpu", "members": "4", "per_step": "all"},
            {"preset": "cpu", "members": "8", "per_step": "2"},
            {"preset": "tiny", "members": "4", "per_step": "2"}]
    assert pending(rows, "cpu", 4, ["all", "2", "8"]) == ["2"]  # 8 > K = 4
    assert pending(rows, "cpu", 8, ["all", "2", "8"]) == ["all", "8"]
    assert pending(rows, "tiny", 4, ["all", "2"]) == ["all"]
    assert pending(rows, "tiny", 16, ["all", "2"]) == ["all", "2"]  # another K: its own rows
    assert pending([], "cpu", 2, ["all", "1", "2", "3"]) == ["all", "1", "2"]


def test_each_setting_has_rows_of_its_own():
    """A row without a setting is the default's; another setting's rows do not count."""
    rows = [{"preset": "cpu", "members": "16", "per_step": "all"},
            {"preset": "cpu", "setting": "default", "members": "16", "per_step": "2"},
            {"preset": "cpu", "setting": "dim16_free_offsets", "members": "16", "per_step": "2"}]
    assert pending(rows, "cpu", 16, ["all", "2"]) == []
    assert pending(rows, "cpu", 16, ["all", "2"], "dim16_free_offsets") == ["all"]
    assert set(SETTINGS) >= {"default", "dim16_free_offsets"} and SETTINGS["default"] == []


def test_the_largest_components_come_first():
    report = {"components": [{"component": "data", "ms": 2.0},
                             {"component": "medium", "ms": 48.1},
                             {"component": "uncollided", "ms": 37.8},
                             {"component": "light_field", "ms": 31.84}]}
    assert largest(report) == "medium 48.1; uncollided 37.8; light_field 31.8"
    assert largest(report, 1) == "medium 48.1"
