"""benchmarks/ddp_equivalence.py: two ranks draw half the preset's per-step counts each,
and the summary's verdict compares the difference of the means with the seeds' spread."""

from __future__ import annotations

import pytest

from benchmarks.ddp_equivalence import halved, summary
from tests.conftest import compose_config

pytestmark = pytest.mark.unit


def test_two_ranks_draw_half_of_every_per_step_count() -> None:
    budget = compose_config("train", ["preset=tiny"]).budget
    assert halved("ea") == [f"budget.ea.rays_per_batch={budget.ea.rays_per_batch // 2}"]
    rte = dict(o.split("=") for o in halved("rte"))
    assert rte["budget.rte.photo_rays"] == str(budget.rte.photo_rays // 2)
    assert rte["budget.rte.transport_points"] == str(budget.rte.transport_points // 2)
    assert int(rte["budget.rte.rays_per_batch"]) >= int(rte["budget.rte.photo_rays"])


def test_the_verdict_compares_the_difference_of_the_means_with_the_spread() -> None:
    def rows(two: list[float]) -> list[dict]:
        return [{"stage": "ea", "processes": p, "seed": s, "val/psnr": v, "val/density_corr": 0.9}
                for p, values in ((1, [30.0, 31.0, 32.0]), (2, two)) for s, v in enumerate(values)]

    near, far = summary(rows([30.5, 31.5, 32.5])), summary(rows([35.0, 36.0, 37.0]))
    psnr_near = next(line for line in near if "val/psnr" in line)
    psnr_far = next(line for line in far if "val/psnr" in line)
    assert "difference +0.5, within the seed spread" in psnr_near, psnr_near
    assert "difference +5, outside the seed spread" in psnr_far, psnr_far
