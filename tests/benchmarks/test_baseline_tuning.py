"""The tuning tool: every configuration of its rounds is well formed, a hybrid stage-2
configuration (stage 2, then the path tracer from stage 2's grids) is described and checked
before anything trains, and blind scenes are refused."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from benchmarks.baseline_tuning import CONFIGS, describe, run_config

pytestmark = pytest.mark.unit
ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("stage", sorted(CONFIGS))
def test_every_configuration_is_a_list_of_overrides_or_a_hybrid(stage):
    for name, configs in yaml.safe_load(CONFIGS[stage].read_text()).items():
        for config in configs.values():
            if isinstance(config, dict):  # only stage 2's rounds hold hybrids
                assert stage == "rte" and 0 < config["then_dpt"] < 1, (name, config)
                assert set(config) <= {"overrides", "then_dpt", "dpt_overrides"}, config
            else:
                assert isinstance(config, list) and all(isinstance(o, str) for o in config)


def test_a_hybrid_is_described_by_both_parts():
    assert describe(["model.lr.medium=0.01"]) == "model.lr.medium=0.01"
    text = describe({"overrides": ["a=1"], "then_dpt": 0.25, "dpt_overrides": ["b=2"]})
    assert text == "a=1 then stage=dpt for 25% of the time b=2"


@pytest.mark.parametrize(("stage", "share", "message"), [
    ("rte", 1.0, "then_dpt=1.0"), ("rte", 0, "then_dpt=0"), ("dpt", 0.5, "--stage rte")])
def test_a_malformed_hybrid_stops_before_training(stage, share, message):
    args = argparse.Namespace(stage=stage, every_s=10.0, preset="tiny", out=Path("unused"))
    with pytest.raises(SystemExit, match=message.replace("-", r"\-")):
        run_config(args, "default", Path("no.ckpt"), 60.0, {"then_dpt": share})


@pytest.mark.slow  # 7-8 s: the benchmark run as a command
def test_blind_scenes_are_refused():
    proc = subprocess.run([sys.executable, "-m", "benchmarks.baseline_tuning", "--stage", "rte",
                           "--scenes", "default,heldout2"], cwd=ROOT, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2 and "heldout2" in proc.stderr and "tuning" in proc.stderr
