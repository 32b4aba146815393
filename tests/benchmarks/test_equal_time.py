"""What an equal-time record carries besides its scores: the SHA-256 of the EA weights it
started from (equal for equal weights whatever else the checkpoint files hold, different
for any changed weight) and the machine's speed, and the comparison alternates the methods'
order between realisations so that a drift of the machine's speed favours none."""

from __future__ import annotations

from argparse import Namespace
from pathlib import Path

import pytest
import torch

import benchmarks.fair_comparison as fair_comparison
from benchmarks.equal_time import weights_sha256
from benchmarks.machine_probe import machine_speed

pytestmark = pytest.mark.unit


def _checkpoint(path: Path, state: dict, step: int) -> Path:
    torch.save({"state_dict": state, "global_step": step, "loops": {"wall_s": step * 0.1}},
               path)
    return path


def test_the_weights_hash_sees_the_weights_and_nothing_else(tmp_path):
    state = {"field.w": torch.randn(4, 3), "field.b": torch.zeros(3),
             "field.mask": torch.tensor([True, False]), "codes": torch.arange(6).reshape(2, 3)}
    a = weights_sha256(_checkpoint(tmp_path / "a.ckpt", state, 10))
    b = weights_sha256(_checkpoint(tmp_path / "b.ckpt", dict(reversed(state.items())), 99))
    assert a == b and len(a) == 64  # other loop state, other key order: the same weights
    changed = {**state, "field.w": state["field.w"].clone()}
    changed["field.w"][1, 2] = torch.nextafter(changed["field.w"][1, 2], torch.tensor(1e9))
    assert weights_sha256(_checkpoint(tmp_path / "c.ckpt", changed, 10)) != a  # one ulp
    renamed = {("field.v" if k == "field.w" else k): v for k, v in state.items()}
    assert weights_sha256(_checkpoint(tmp_path / "d.ckpt", renamed, 10)) != a


def test_the_machine_probe_measures_both_rates():
    speed = machine_speed(seconds=0.05)
    assert speed["gemm_gflops"] > 0 and speed["bandwidth_gbs"] > 0
    assert speed["cores"] >= 1 and speed["torch_threads"] >= 1 and speed["host"]


def test_the_methods_order_alternates_between_realisations(tmp_path, monkeypatch):
    order = []

    def fake_run(path, stage, overrides, ckpt, *args):
        order.append((path.parent.parent.name, path.parent.name, path.name))
        return {"metrics": {"mse_sigma_t_x100": 1.0, "mse_sigma_s_x100": 1.0},
                "curve_points": 1, "steps": 1}

    # the order logic alone: training and stage 1 are the real commands' (slow tier)
    monkeypatch.setattr(fair_comparison, "run_method", fake_run)
    monkeypatch.setattr(fair_comparison, "ea_checkpoint", lambda *a: tmp_path / "ea.ckpt")
    (tmp_path / "heldout" / "photo1").mkdir(parents=True)
    (tmp_path / "heldout" / "photo1" / "dpt.json").write_text("{}")  # done already
    fair_comparison.run_all(Namespace(
        methods="rte,dpt,rte_paper", scenes="default,heldout", photo_seeds="0,1",
        photo_variant="auto", paper_on="default", given_to_all=[], budget_s=1.0, every_s=1.0,
        preset="tiny", data=tmp_path, out=tmp_path / "runs"))
    assert order == [("default", "photo0", "rte"), ("default", "photo0", "dpt"),
                     ("default", "photo0", "rte_paper"), ("default", "photo1", "rte_paper"),
                     ("default", "photo1", "dpt"), ("default", "photo1", "rte"),
                     ("heldout", "photo0", "rte"), ("heldout", "photo0", "dpt"),
                     ("heldout", "photo1", "rte")]
