"""The fused kernels' equal-results benchmark: each kernel names a stage and switches that
nrt-train has, and a row keeps what the run's ``run.json`` measured."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from benchmarks.common import compose_train, run_finals
from benchmarks.fused_equal import KERNELS
from nrt.run_dirs import write_run_info

pytestmark = pytest.mark.unit


@pytest.mark.parametrize("kernel", sorted(KERNELS))
def test_each_kernels_switches_are_boolean_keys_of_its_stage(kernel):
    stage, switches, _, _ = KERNELS[kernel]
    cfg = compose_train([f"stage={stage}", "preset=tiny"])
    assert switches and all(isinstance(OmegaConf.select(cfg, s, throw_on_missing=True), bool)
                            for s in switches)


def test_a_row_holds_the_runs_steps_seconds_and_metrics(tmp_path):
    write_run_info(tmp_path, finished_step=1500, final_metrics={
        "time/wall_s": 193.398, "val/psnr": 33.83686, "val/density_corr": 0.92466,
        "val/density_rel_err": 0.36497, "train/loss": 0.001})
    assert run_finals(tmp_path, KERNELS["hash_grid"][3]) == {
        "steps": 1500, "train_s": 193.4, "psnr_heldout": 33.8369, "density_corr": 0.9247,
        "density_rel_err": 0.365}
