"""The objective units of :mod:`nrt.losses.objective`, chosen by config: ``losses.objectives``
names each stage's units (``_target_``, ``_partial_: true``) under the names users write in
``losses.weights``; a unit has a weight schedule (constant, a linear ramp over steps, off
until a share of the run) and a loss; a stage builds them in the order of the weights,
records their configs in its checkpoints and refuses names and targets it cannot build. The
stages' training with them is tested in tests/stages/test_rte_paper_stage.py and
tests/stages/test_rte_split_stage.py."""

from __future__ import annotations

import functools
from pathlib import Path

import hydra
import numpy as np
import pytest
import torch
from hydra.errors import InstantiationException
from omegaconf import OmegaConf

from nrt.cli.checks import check_mode, check_objectives
from nrt.errors import ConfigError
from nrt.losses.boundary import BoundaryObjective
from nrt.losses.extinction_prior import ExtinctionPrior
from nrt.losses.objective import Objective, WeightSchedule, build_objectives
from nrt.losses.observation import ObservationObjective
from nrt.losses.photo import PhotoObjective
from nrt.losses.rte import RTEObjective
from nrt.losses.transport import TransportObjective
from nrt.losses.vre import VREObjective
from tests.conftest import GENERATIVE_FAMILY, compose_config, saved_checkpoint

pytestmark = pytest.mark.unit

PAPER = "experiment=rte_paper"
SPLIT_UNITS = {"photo": PhotoObjective, "transport": TransportObjective,
               "extinction_prior": ExtinctionPrior}
PAPER_UNITS = {"rte": RTEObjective, "bc": BoundaryObjective, "obs": ObservationObjective,
               "vre": VREObjective}

STAGES = {  # every stage x mode that has objectives: its overrides and its units by name
    "rte": (("stage=rte",), SPLIT_UNITS),
    "forward": (("stage=forward",), SPLIT_UNITS),
    "rte_paper": (("stage=rte", PAPER), PAPER_UNITS),
    "forward_paper": (("stage=forward", PAPER), PAPER_UNITS),
    "rte_generative": (("stage=rte", *GENERATIVE_FAMILY[1:]), SPLIT_UNITS),
}


def build(*overrides: str):
    """The model of ``preset=tiny init=none`` and ``overrides`` as nrt-train builds it, a
    component's own error unwrapped from Hydra's (as the CLI does)."""
    cfg = compose_config("train", ["preset=tiny", "init=none", *overrides])
    try:
        return hydra.utils.instantiate(cfg.model, _convert_="all")
    except InstantiationException as exc:
        raise exc.__cause__ from None


@pytest.mark.parametrize("stage", list(STAGES))
def test_every_stage_and_mode_names_its_units_in_its_config(stage):
    """``losses.objectives`` of every stage x mode names its formulation's units, each under
    the name its weight has, and the model receives them; the check nrt-train makes before
    anything is built resolves each to its class (and the generative mode's to units that
    take a family)."""
    overrides, units = STAGES[stage]
    cfg = compose_config("train", ["preset=tiny", *overrides])
    assert list(cfg.losses.objectives) == list(cfg.losses.weights) == list(units)
    given = OmegaConf.to_container(cfg.model.objectives, resolve=True)
    assert {name: (entry["_target_"], entry["_partial_"]) for name, entry in given.items()} == {
        name: (f"{unit.__module__}.{unit.__name__}", True) for name, unit in units.items()}
    # an objective's keywords are its sample counts and settings, numbers from the preset,
    # or null for a setting that is off (the extinction prior's saturation)
    assert all(isinstance(v, int | float | str | bool | None) for entry in given.values()
               for v in entry.values())
    assert check_objectives(cfg) == units
    check_mode(cfg)


@pytest.mark.parametrize("stage", ["ea", "dpt"])
def test_stages_without_units_have_no_objectives_to_check(stage):
    """Stage 1 (one photometric loss) and the path-tracing baseline have no units."""
    cfg = compose_config("train", ["preset=tiny", f"stage={stage}"])
    assert "objectives" not in cfg.losses and check_objectives(cfg) == {}


@pytest.mark.parametrize(("stage", "built"), [
    ("rte", ["photo", "transport", "extinction_prior"]),
    ("forward", ["transport"]),  # the photo objective and the prior train the medium alone
    ("rte_paper", ["rte", "bc", "obs", "vre"]),
    ("forward_paper", ["rte", "bc", "obs", "vre"]),
])
def test_the_stages_build_their_units_and_record_their_configs(stage, built):
    """The stage built from its config holds one unit of the configured class per weighted
    objective, under its name, and records the configs (plain data) in its
    hyperparameters."""
    overrides, units = STAGES[stage]
    model = build(*overrides)
    assert list(model.objectives) == built
    assert all(type(unit) is units[name] and unit.name == name
               for name, unit in model.objectives.items())
    recorded = dict(model.hparams)["objectives"]
    assert {name: (entry["_target_"], entry["_partial_"]) for name, entry in recorded.items()} \
        == {name: (f"{unit.__module__}.{unit.__name__}", True) for name, unit in units.items()}


def test_forward_mode_leaves_out_a_weighted_photo_objective():
    model = build("stage=forward", "losses.weights.photo=1.0")
    assert list(model.objectives) == ["transport"]


def test_a_ramped_weight_reaches_its_unit():
    model = build("stage=rte", PAPER, "losses.weights.vre=[0,70,100]")
    assert [model.objectives["vre"].weight(s, 0.0) for s in (0, 50, 200)] == [0, 35, 70]


def test_a_new_unit_is_a_class_and_a_config_entry(tmp_path: Path):
    """A unit the package does not know, given by config alone (its ``_target_``, its
    keywords, its weight), is built and used by the stage and recorded for
    ``load_from_checkpoint``; here a second transport objective under another name."""
    model = build("stage=rte", "+losses.objectives.again._target_="
                  "nrt.losses.transport.TransportObjective",
                  "+losses.objectives.again._partial_=true", "+losses.objectives.again.points=64",
                  "+losses.objectives.again.samples=4", "+losses.weights.again=0.5")
    assert list(model.objectives) == ["photo", "transport", "extinction_prior", "again"]
    assert isinstance(model.objectives["again"], TransportObjective)
    assert model.objectives["again"].weight(0, 1.0) == 0.5
    loaded = reload(model, dict(model.hparams), tmp_path / "again.ckpt")
    assert list(loaded.objectives) == ["photo", "transport", "extinction_prior", "again"]


def reload(model, hparams: dict, path: Path):
    """``model`` saved with ``hparams`` as a checkpoint and loaded back; the checkpoint
    holds plain data only (``torch.load(weights_only=True)`` reads it)."""
    torch.load(saved_checkpoint(path, model, hparams), weights_only=True)
    return type(model).load_from_checkpoint(path, map_location="cpu")


@pytest.mark.parametrize("stage", ["rte", "rte_paper"])
def test_a_checkpoint_loads_the_objectives_it_records(tmp_path: Path, stage):
    """A checkpoint records its objectives' configs and loads those units; one without
    ``objectives`` (not of this checkpoint format) is refused naming the key."""
    overrides, units = STAGES[stage]
    model = build(*overrides)
    new = dict(model.hparams)
    loaded = reload(model, new, tmp_path / "new.ckpt")
    assert {n: type(u) for n, u in loaded.objectives.items()} == units
    assert dict(loaded.hparams)["objectives"] == new["objectives"]
    old = {k: v for k, v in new.items() if k != "objectives"}
    with pytest.raises(ConfigError, match="losses.objectives is missing"):
        reload(model, old, tmp_path / "old.ckpt")


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


FACTORIES = {"photo": functools.partial(PhotoObjective, rays=8, vre_samples=4),
             "transport": functools.partial(TransportObjective, points=8, samples=4)}


def test_build_objectives_keeps_the_weights_order_and_the_warm_ups():
    """Units come in the order of ``losses.weights`` (the order their samples are drawn
    in), each with its name and schedule; a warm-up applies to the objective it names."""
    built = build_objectives({"transport": 1.0, "photo": [0, 1, 4]}, FACTORIES,
                             {"photo": 0.25})
    assert list(built) == ["transport", "photo"]
    assert isinstance(built["photo"], PhotoObjective) and built["photo"].name == "photo"
    assert isinstance(built["transport"], TransportObjective)
    assert built["transport"].weight(0, 0.0) == 1.0
    assert (built["photo"].weight(2, 0.1), built["photo"].weight(2, 0.3)) == (0.0, 0.5)


@pytest.mark.parametrize(("weights", "factories", "message"), [
    ({"photo": 1.0, "rte": 1.0}, FACTORIES,
     r"losses\.weights has unknown objectives \['rte'\]; the objectives are \['photo', "
     r"'transport'\] \(losses\.objectives\) \(hint\)"),
    ({"photo": 1.0}, FACTORIES, r"losses\.objectives\.transport has no weight"),
    ({"photo": 1.0}, {"photo": functools.partial(torch.nn.Linear)},
     r"losses\.objectives\.photo names Linear, which is not an objective"),
    ({"photo": 1.0}, {"photo": functools.partial(Objective.weight)},
     r"losses\.objectives\.photo names Objective\.weight, which is not an objective"),
])
def test_build_objectives_refuses_what_it_cannot_build(weights, factories, message):
    with pytest.raises(ConfigError, match=message):
        build_objectives(weights, factories, hint=" (hint)")


@pytest.mark.parametrize(("overrides", "message"), [
    (("+losses.weights.foo=1",), r"unknown objectives \['foo'\]"),
    ((PAPER, "+losses.weights.photo=1"), r"unknown objectives \['photo'\]"),
    (("~losses.weights.transport",), r"losses\.objectives\.transport has no weight"),
    (("losses.objectives.photo._target_=nrt.losses.photo.photo_loss",),
     r"losses\.objectives\.photo names photo_loss, which is not an objective"),
    (("losses.objectives.photo._target_=nrt.losses.samplers.DensityPointSampler",),
     r"losses\.objectives\.photo names DensityPointSampler, which is not an objective"),
])
def test_the_stage_refuses_objectives_it_cannot_build_naming_the_key(overrides, message):
    """Built from the config (as nrt-train does, before any data is loaded): a weight of no
    objective, an objective without weight, a target that is no objective."""
    with pytest.raises(ConfigError, match=message):
        build("stage=rte", *overrides)


@pytest.mark.parametrize(("overrides", "message"), [
    (("losses.objectives.photo._target_=nrt.losses.photo.Nope",),
     r"losses\.objectives\.photo\._target_=nrt\.losses\.photo\.Nope: cannot import it"),
    (("losses.objectives.photo._target_=nrt.losses.samplers.DensityPointSampler",),
     r"losses\.objectives\.photo names DensityPointSampler, which is not an objective"),
    (("losses.objectives.photo=1",), r"losses\.objectives\.photo=1: an objective is a "
                                     r"config with `_target_"),
    (("~losses.objectives.photo._partial_",), r"losses\.objectives\.photo lacks `_partial_"),
    (("stage=rte", PAPER, *GENERATIVE_FAMILY[1:]),
     r"losses\.objectives\.rte \(nrt\.losses\.rte\.RTEObjective\) takes one scene"),
])
def test_nrt_train_refuses_an_objective_config_before_anything_is_built(overrides, message):
    """The checks nrt-train makes on the config alone: a target that cannot be imported or
    is no objective, an entry that is no config or not partial, and in the generative mode
    a unit that takes one scene, each naming the key under ``losses.objectives``."""
    cfg = compose_config("train", ["preset=tiny", "stage=rte", *overrides])
    with pytest.raises(ConfigError, match=message):
        check_objectives(cfg)
        check_mode(cfg)


def test_the_extinction_prior_refuses_a_stage_without_voxels():
    """The extinction prior reads the split stage's voxel medium; given to the paper's
    formulation by config it stops with an error naming its key."""
    model = build("stage=rte", PAPER)
    prior = ExtinctionPrior("extinction_prior", WeightSchedule(1.0))
    with pytest.raises(ConfigError, match=r"losses\.weights\.extinction_prior"):
        prior.loss({}, model.step_context([]))
