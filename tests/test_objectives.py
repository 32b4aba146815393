"""The objective units of :mod:`nrt.losses.objective`: each has the name users write in
``losses.weights``, a weight schedule (constant, a linear ramp over steps, off until a
share of the run) and a loss; a stage builds them from its config in the config's order
and refuses names it has no unit for. The stages' training with them is tested in
tests/test_rte_paper_stage.py and tests/test_rte_split_stage.py."""

from __future__ import annotations

import hydra
import numpy as np
import pytest
from conftest import compose_config

from nrt.errors import ConfigError
from nrt.losses.objective import WeightSchedule, build_objectives
from nrt.losses.photo import PhotoObjective
from nrt.losses.transport import TransportObjective
from nrt.modules.stages.rte import PAPER_OBJECTIVES
from nrt.modules.stages.rte_split import SPLIT_OBJECTIVES

PAPER = "experiment=rte_paper"


@pytest.mark.parametrize(("overrides", "units"), [
    (("stage=rte",), SPLIT_OBJECTIVES),
    (("stage=forward",), SPLIT_OBJECTIVES),
    (("stage=rte", PAPER), PAPER_OBJECTIVES),
    (("stage=forward", PAPER), PAPER_OBJECTIVES),
])
def test_the_configs_weights_name_the_stages_units(overrides, units):
    """``losses.weights`` of every stage-2 config names the units of its formulation, in
    their order, each unit with its own name."""
    cfg = compose_config("train", ["preset=tiny", *overrides])
    assert list(cfg.losses.weights) == [unit.name for unit in units]
    assert len({unit.name for unit in units}) == len(units) and all(u.name for u in units)


def test_a_constant_weight_holds_at_every_step_and_progress():
    schedule = WeightSchedule(70)
    assert {schedule(step, p) for step in (0, 1, 10**6) for p in (0.0, 0.5, 1.0)} == {70.0}


@pytest.mark.parametrize("ramp", [[0.0, 1.0, 10], [2, 0.5, 4], [1.0, 3.0, 1]])
def test_a_ramp_is_linear_over_its_steps_then_constant(ramp):
    """``[start, end, ramp_steps]`` against linear interpolation, before and after its end."""
    start, end, steps = ramp
    schedule = WeightSchedule(ramp)
    got = [schedule(step, 0.0) for step in range(3 * steps + 2)]
    want = np.interp(np.arange(3 * steps + 2), [0, steps], [start, end])
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_a_warm_up_keeps_the_weight_off_until_its_share_of_the_run():
    """``starts_at``: 0 while the run's progress is below it, then the schedule's value
    (the ramp counted from step 0, as the split stage's photo weight after light_warmup)."""
    constant, ramp = WeightSchedule(1.0, starts_at=0.25), WeightSchedule([0, 1, 10], 0.5)
    assert [constant(100, p) for p in (0.0, 0.2499, 0.25, 0.6, 1.0)] == [0, 0, 1, 1, 1]
    assert (ramp(5, 0.4999), ramp(5, 0.5), ramp(20, 1.0)) == (0.0, 0.5, 1.0)


@pytest.mark.parametrize("value", ["abc", [1, 2], [1, 2, "x"], True, None, float("nan"),
                                   [0, float("inf"), 10]])
def test_a_weight_that_is_neither_number_nor_ramp_is_refused(value):
    with pytest.raises(ConfigError, match=r"losses\.weights\.photo=.*a weight is a finite"):
        WeightSchedule(value, key="losses.weights.photo")


def test_build_objectives_keeps_the_configs_order_and_the_warm_ups():
    """Units come in the order of ``losses.weights`` (the order their samples are drawn
    in), each with its name and schedule; a warm-up applies to the objective it names."""
    built = build_objectives({"transport": 1.0, "photo": [0, 1, 4]}, SPLIT_OBJECTIVES,
                             {"photo": 0.25})
    assert list(built) == ["transport", "photo"]
    assert isinstance(built["photo"], PhotoObjective) and built["photo"].name == "photo"
    assert isinstance(built["transport"], TransportObjective)
    assert built["transport"].weight(0, 0.0) == 1.0
    assert (built["photo"].weight(2, 0.1), built["photo"].weight(2, 0.3)) == (0.0, 0.5)


def test_an_unknown_objective_is_refused_naming_the_formulations_objectives():
    with pytest.raises(ConfigError, match=r"unknown objectives \['rte'\]; the objectives are "
                                          r"\['photo', 'transport'\] \(hint\)"):
        build_objectives({"photo": 1.0, "rte": 1.0}, SPLIT_OBJECTIVES, hint=" (hint)")


@pytest.mark.parametrize(("overrides", "names"), [
    (("stage=rte",), ["photo", "transport"]),
    (("stage=forward", "losses.weights.photo=1.0"), ["transport"]),
    (("stage=rte", PAPER, "losses.weights.vre=[0,70,100]"), ["rte", "bc", "obs", "vre"]),
])
def test_the_stages_hold_their_objectives_by_name(overrides, names):
    """The stage built from its config holds one unit per weighted objective; forward mode
    (the medium is the ground truth) drops the photo objective even when weighted."""
    cfg = compose_config("train", ["preset=tiny", "init=none", *overrides])
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    assert list(model.objectives) == names
    assert [unit.name for unit in model.objectives.values()] == names
    if "vre" in names:
        assert [model.objectives["vre"].weight(s, 0.0) for s in (0, 50, 200)] == [0, 35, 70]
