"""The step profiler (``benchmarks.profile_step``): a stage-2 profile at ``tiny`` names every
component of the step, its rows account for the whole profiled step and nothing twice, the
rest no scope claims stays under a tenth of the step, and the roofline's probes measure."""

from __future__ import annotations

import json
import re

import pytest
import torch

from benchmarks.profile_step import FRAMEWORK, STAGE_COMPONENTS, main
from tests.conftest import single_scene_ea_checkpoint

pytestmark = pytest.mark.integration

OBJECTIVES = ("photo", "transport", "extinction_prior")
"""Stage 2's objectives at its defaults (conf/losses/rte.yaml)."""


def test_a_stage_2_profile_accounts_for_the_whole_step(tmp_path, tiny_dataset, capsys):
    torch.manual_seed(0)
    ea_ckpt = single_scene_ea_checkpoint(tmp_path / "ea.ckpt")
    report = main(["--preset", "tiny", "--stage", "rte", "--steps", "2", "--warmup", "1",
                   "--ea-ckpt", str(ea_ckpt), "--probe-seconds", "0.1",
                   "--json", str(tmp_path / "profile.json"),
                   f"paths.data_dir={tiny_dataset.parent}"])
    printed = capsys.readouterr().out
    assert json.loads((tmp_path / "profile.json").read_text()) == report

    rows = {row["component"]: row for row in report["components"]}
    named = STAGE_COMPONENTS["rte"] + [f"objective/{o}" for o in OBJECTIVES] + FRAMEWORK
    assert set(named) <= set(rows), sorted(set(named) - set(rows))
    assert all(row["ms"] >= 0 and row["label"] in printed for row in rows.values())
    # the rows are the profiled step's wall time, none counted twice (the Lightning loop's
    # row is the remainder, so it would go negative)
    assert sum(row["share"] for row in rows.values()) == pytest.approx(1.0, abs=1e-9)
    assert sum(row["ms"] for row in rows.values()) == pytest.approx(
        report["step_ms"]["profiled"], rel=1e-6)
    shares = [float(m) for m in re.findall(r"^(?!total).*?([\d.]+)%$", printed, re.M)]
    assert len(shares) == len(rows) and sum(shares) == pytest.approx(100.0, abs=0.05 * len(rows))

    # the objectives run (the photos' too, past its warm-up at the pinned progress) and the
    # components under them take time
    for name in ("photo", "transport"):
        assert report["objectives"][name]["forward_ms"] > 0
        assert report["objectives"][name]["backward_ms"] > 0
    for name in ("medium", "light_field", "ray_marching", "sky_light", "compositing"):
        assert rows[name]["ms"] > 0, name
    assert rows["medium"]["backward_ms"] > 0  # backward nodes go to their forward's scope

    unattributed = report["unattributed"]
    assert "unattributed rest" in printed and 0 <= unattributed["share"] < 0.10
    assert unattributed["ms"] == rows["unattributed"]["ms"]

    roofline = report["roofline"]
    assert roofline["gemm_probe"]["gflops"] > 0 and roofline["bandwidth_probe"]["gbs"] > 0
    assert roofline["flops_per_step"] > 0 and roofline["bytes_per_step"] > 0
    assert report["step_ms"]["unprofiled"] > 0
    assert report["machine"]["torch_threads"] == torch.get_num_threads()
