"""The equal-time benchmark's start: a reused stage-2 run lends its scene and EA checkpoint,
and bad arguments stop it with exit status 2 before anything trains."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.dpt_vs_rte import reused_start
from tests.conftest import ROOT

pytestmark = pytest.mark.e2e


def test_a_reused_run_lends_its_scene_and_ea_checkpoint(tmp_path):
    (tmp_path / "run.json").write_text(json.dumps(
        {"stage": "rte", "scene": "heldout3", "ea_ckpt": "/runs/ea/last.ckpt"}))
    assert reused_start(tmp_path) == ("heldout3", "/runs/ea/last.ckpt")


def _benchmark(args: list[str], output_dir: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "NRT_OUTPUT_DIR": str(output_dir)}
    return subprocess.run([sys.executable, "-m", "benchmarks.dpt_vs_rte", *args], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.slow  # 4 s: the benchmark run as a command
def test_a_folder_without_run_json_is_refused(tmp_path):
    proc = _benchmark(["--rte-run", str(tmp_path)], tmp_path)
    assert proc.returncode == 2
    assert "no run.json" in proc.stderr and str(tmp_path) in proc.stderr


@pytest.mark.slow  # 4 s: the benchmark run as a command
def test_a_scene_without_ea_checkpoint_is_refused_naming_the_fix(tmp_path):
    proc = _benchmark(["--scene", "heldout3", "--preset", "tiny"], tmp_path)
    assert proc.returncode == 2
    assert "nrt-train stage=ea scene=heldout3" in proc.stderr
    assert not list(tmp_path.glob("*/dpt/*"))  # nothing trained
