"""Stage 1's density field and stage 2's light field and medium are components chosen by
config group (``model/density_field=<name>``, ``model/light_field=<name>``,
``model/medium=<name>``; :mod:`nrt.stages.components`): every such config builds
with the stage or formulation it belongs to and is refused with a ``ConfigError`` naming its
group by the others; the default compositions build the very modules they built before the
groups existed; checkpoints record them as configs and load."""

from __future__ import annotations

from pathlib import Path

import hydra
import pytest
import torch
from hydra.errors import InstantiationException
from omegaconf import OmegaConf

from nrt.cli.common import CONFIG_DIR
from nrt.errors import ConfigError, NrtError
from nrt.stages.paper_rte import PaperRTEStage
from nrt.stages.rte import RTEStage
from tests.conftest import compose_config, saved_checkpoint

pytestmark = pytest.mark.integration

FORMULATIONS = {"split": (), "paper": ("experiment=rte_paper",)}
"""Stage 2's formulations: the default (split) stage and the paper's."""

GENERATIVE = ("scene=family", "mode=generative")
"""Stage 1 over a scene family: the density field built with the codes' ``latent_dim``."""


def stage2(*stages: str) -> dict[str, tuple[str, ...]]:
    """The compositions of ``stages`` in both stage-2 formulations."""
    return {f"{formulation} {stage}": (f"stage={stage}", *extra)
            for formulation, extra in FORMULATIONS.items() for stage in stages}


def build(*overrides: str):
    """The model of ``preset=tiny init=none`` and ``overrides``, as nrt-train builds it; a
    component's own ``ConfigError`` unwrapped from Hydra's exception (as the CLI does)."""
    cfg = compose_config("train", ["preset=tiny", "init=none", *overrides])
    try:
        return cfg, hydra.utils.instantiate(cfg.model, _convert_="all")
    except InstantiationException as exc:
        raise exc.__cause__ from None


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / "model" / group).glob("*.yaml"))


@pytest.mark.parametrize(("group", "attribute", "compositions"), [
    ("density_field", "field", {"single": ("stage=ea",), "generative": ("stage=ea", *GENERATIVE)}),
    ("light_field", "light", stage2("rte", "forward")),
    ("medium", "medium", stage2("rte")),  # forward mode builds no medium: the truth is given
])
def test_every_component_config_builds_with_its_stage(group, attribute, compositions):
    """Each file of ``conf/model/<group>/`` composed with every stage (and formulation, and
    mode) that builds it: where it fits, the stage holds an object of the config's
    ``_target_``; where it does not, the refusal is a ``ConfigError`` naming
    ``model/<group>``; and every file fits at least one composition (a new representation
    is one module and one such file, and this test covers it without changes)."""
    names = options(group)
    assert {"density_field": {"hash_grid"}, "light_field": {"sh_grid", "siren"},
            "medium": {"voxel", "siren", "grid"}}[group] <= set(names)
    for name in names:
        fits = set()
        for composition, overrides in compositions.items():
            try:
                cfg, model = build(*overrides, f"model/{group}={name}")
            except ConfigError as exc:
                assert f"model/{group}" in str(exc), str(exc)
                continue
            built = getattr(model, attribute)
            target = OmegaConf.select(cfg, f"model.{group}._target_")
            assert f"{type(built).__module__}.{type(built).__qualname__}" == target
            fits.add(composition)
        assert fits, f"conf/model/{group}/{name}.yaml builds with no stage"
    if group == "density_field":  # generative mode hands the field the codes' dimension
        assert build(*compositions["generative"])[1].field.latent_dim == 4


SPLIT_STATE = {
    "light.coefficients": (12, 12, 12, 27), "light.uncollided": (12, 12, 12, 27),
    "light.bbox": (2, 3), "light.radiance_scale": (), "medium.g_shared": (),
    "medium.bbox": (2, 3), "medium.offsets": (6,), "medium.density": (16, 16, 16, 1),
    "medium.modulation.values": (4, 4, 4, 6), "medium.modulation.unit_box": (2, 3)}
PAPER_STATE = {
    "light.bbox": (2, 3), "light.radiance_scale": (),
    "light.net.linears.0.weight": (64, 6), "light.net.linears.0.bias": (64,),
    "light.net.linears.1.weight": (64, 64), "light.net.linears.1.bias": (64,),
    "light.net.linears.2.weight": (64, 64), "light.net.linears.2.bias": (64,),
    "light.net.out.weight": (3, 64), "light.net.out.bias": (3,), "medium.g_shared": (),
    "medium.bbox": (2, 3), "medium.offsets": (6,),
    "medium.modulation.linears.0.weight": (32, 3), "medium.modulation.linears.0.bias": (32,),
    "medium.modulation.linears.1.weight": (32, 32), "medium.modulation.linears.1.bias": (32,),
    "medium.modulation.out.weight": (6, 32), "medium.modulation.out.bias": (6,)}
PAPER_PARAMETER_SUM = 155.56965890563424
"""Sum of the paper model's parameters built after ``torch.manual_seed(0)`` (``preset=tiny
init=none``), measured at commit b04eadf, before the light field and medium were config
groups: the same random draws in the same order give the same sum."""


@pytest.mark.parametrize(("formulation", "state"), [("split", SPLIT_STATE),
                                                     ("paper", PAPER_STATE)])
def test_default_compositions_build_the_modules_of_before(formulation, state):
    """State-dict names and shapes (checkpoints of before keep loading), parameters in the
    optimizer's order, and for the paper's SIRENs the initial values (the same draws)."""
    torch.manual_seed(0)
    _, model = build("stage=rte", *FORMULATIONS[formulation])
    assert {k: tuple(v.shape) for k, v in model.state_dict().items()} == state
    params = [name for name, _ in model.named_parameters()]
    assert params == [k for k in state if k in params]
    if formulation == "paper":
        total = sum(float(p.detach().double().sum()) for p in model.parameters())
        assert total == pytest.approx(PAPER_PARAMETER_SUM, rel=1e-9)


STAGE_2 = {RTEStage: "split", PaperRTEStage: "paper"}


@pytest.mark.parametrize("cls", list(STAGE_2), ids=lambda c: c.__name__)
def test_checkpoints_record_components_as_configs_and_load(tmp_path: Path, cls):
    """A checkpoint records the components as configs (plain data, no pickled code) that
    ``load_from_checkpoint`` rebuilds into the same state; the split stage's medium resizes
    its grid to the resolution the checkpoint reached. One whose components lack a
    ``_target_`` (not of this checkpoint format) is refused naming the key."""
    torch.manual_seed(0)
    _, model = build("stage=rte", *FORMULATIONS[STAGE_2[cls]])
    if cls is RTEStage:
        model.medium.follow_schedule(0.5, None)  # 4 -> 8 cells, as at 40% of a run
        assert model.medium.resolution == 8
    with torch.no_grad():
        for p in model.parameters():
            p.normal_()
    new = dict(model.hparams)
    assert new["light_field"]["_target_"] and new["medium"]["_partial_"] is True
    loaded = cls.load_from_checkpoint(saved_checkpoint(tmp_path / "new.ckpt", model, new),
                                      map_location="cpu")
    for group in ("light_field", "medium"):
        assert dict(loaded.hparams)[group] == new[group]
    for key, value in model.state_dict().items():
        torch.testing.assert_close(loaded.state_dict()[key], value, msg=key)
    keywords = {k: v for k, v in new["light_field"].items() if k != "_target_"}
    old = saved_checkpoint(tmp_path / "old.ckpt", model, {**new, "light_field": keywords})
    with pytest.raises(ConfigError, match="model.light_field has no `_target_`"):
        cls.load_from_checkpoint(old, map_location="cpu")


@pytest.mark.parametrize("version", [None, 0, 1, 3, "x"])
def test_a_checkpoint_of_another_format_is_refused(tmp_path: Path, version):
    """A checkpoint records nrt's checkpoint format; one of another (older or unknown) or of
    none is refused with the version and the fix, both where nrt loads a stage and on a
    resume: nrt converts no checkpoint."""
    from nrt.stages.checkpoints import CHECKPOINT_FORMAT, FORMAT_KEY, load_stage

    _, model = build("stage=rte", *FORMULATIONS["split"])
    stamped: dict = {}
    model.on_save_checkpoint(stamped)
    assert stamped == {FORMAT_KEY: CHECKPOINT_FORMAT}
    path = saved_checkpoint(tmp_path / "other.ckpt", model)
    assert isinstance(load_stage(RTEStage, path), RTEStage)  # this format loads
    saved = torch.load(path, weights_only=True)
    if version is None:
        del saved[FORMAT_KEY]
        message = "records no checkpoint format: an nrt older than format 2 wrote it"
    else:
        saved[FORMAT_KEY] = version
        age = "an older" if version in (0, 1) else "another"
        message = f"has checkpoint format {version!r}, written by {age} nrt"
    torch.save(saved, path)
    with pytest.raises(NrtError, match=message) as refused:
        load_stage(RTEStage, path)
    assert "Train the stage again" in str(refused.value) and str(path) in str(refused.value)
    with pytest.raises(NrtError, match=message):
        model.on_load_checkpoint({k: v for k, v in saved.items() if k != "state_dict"})


def test_a_run_folder_of_an_unknown_stage_is_refused(tmp_path: Path):
    """nrt-eval reads a run's stage class from its saved config: a class this nrt does not
    have (a run of an earlier nrt) is refused naming the run and the fix."""
    import json

    from nrt.evaluation.runs import open_run, run_grids

    (tmp_path / ".hydra").mkdir()
    (tmp_path / "run.json").write_text(json.dumps(
        {"stage": "rte", "scene": "default", "dataset_dir": "d", "environments": ["sky0"]}))
    OmegaConf.save({"scene": {"effects": {"phase": "hg"}},
                    "model": {"_target_": "nrt.modules.rte_split.SplitRTEModule"}},
                   tmp_path / ".hydra" / "config.yaml")
    (tmp_path / "checkpoints").mkdir()
    (tmp_path / "checkpoints" / "last.ckpt").write_bytes(b"")
    with pytest.raises(NrtError, match="which this nrt does not have"):
        run_grids(open_run(tmp_path), 8)


def test_the_ea_field_is_a_density_field_with_an_optional_code():
    """Stage 2 reads stage 1 through :class:`DensityField`: the EA field has its members,
    and ``density(x)`` without a code equals ``density(x, None)`` for a single scene."""
    from nrt.modules.fields.ea_field import EAField
    from nrt.modules.fields.protocols import DensityField, members

    field = EAField(hash_grid={"levels": 2, "log2_table_size": 8})
    assert all(hasattr(field, name) for name in members(DensityField))
    x = torch.rand(5, 3) * 2 - 1
    torch.testing.assert_close(field.density(x), field.density(x, None))
    assert field.density(x).shape == (5,)


def test_an_unknown_coupling_key_is_refused_with_the_known_ones():
    """A misspelt ``model.coupling`` key (added with ``+``, so Hydra lets it through) would
    otherwise be ignored silently: the stage refuses it and names the keys it knows."""
    with pytest.raises(ConfigError, match=r"unknown keys \['adjiont'\].*'adjoint'"):
        build("stage=rte", "+model.coupling.adjiont=true")


@pytest.mark.parametrize("mode", ["single", "generative"])
def test_stage_1_checkpoints_record_the_density_field_and_load(tmp_path: Path, mode):
    """A stage-1 checkpoint records its density field as a config and loads into the same
    field: the same density, to the bit, at random points (under a member's code in
    generative mode), through ``load_from_checkpoint`` and the loaders stage 2 uses."""
    from nrt.errors import NrtError
    from nrt.stages.ea import build_density_field, density_field_factory, load_ea_field
    from nrt.stages.generative_ea import load_generative_ea

    torch.manual_seed(0)
    cfg, model = build("stage=ea", *(GENERATIVE if mode == "generative" else ()))
    with torch.no_grad():
        for p in model.parameters():
            p.normal_(0, 0.1)
    new = dict(model.hparams)
    assert new["density_field"]["_target_"] == cfg.model.density_field._target_
    x = torch.rand(256, 3) * 2 - 1
    code = model.codes[1].expand(256, -1) if mode == "generative" else None
    expected = model.field.density(x, code)
    path = saved_checkpoint(tmp_path / "ea.ckpt", model, new)
    loaded = type(model).load_from_checkpoint(path, map_location="cpu")
    assert dict(loaded.hparams)["density_field"] == new["density_field"]
    assert torch.equal(loaded.field.density(x, code), expected)
    if mode == "single":
        assert torch.equal(load_ea_field(str(path)).density(x), expected)
        return
    with pytest.raises(NrtError, match="generative EA run"):
        load_ea_field(str(path))
    config, field, codes, _ = load_generative_ea(str(path))
    assert torch.equal(codes, model.codes) and torch.equal(field.density(x, code), expected)
    # generative stage 2 records that config and rebuilds the field from it
    rebuilt = build_density_field(density_field_factory(config), 4)
    rebuilt.load_state_dict(field.state_dict())
    assert torch.equal(rebuilt.density(x, code), expected)


def test_a_density_field_without_density_is_refused_naming_its_group():
    """A ``model/density_field`` whose target builds but lacks the protocol's ``density``
    (here a module that takes any keywords) ends in a ``ConfigError`` naming the group and
    the missing member, not in an ``AttributeError`` in the first training step."""
    with pytest.raises(ConfigError, match=r"model/density_field: Identity lacks \['bbox', "
                                          r"'density'\]"):
        build("stage=ea", "model.density_field._target_=torch.nn.Identity")


@pytest.mark.parametrize(("overrides", "stages", "trained"), [
    ((), ("ea", "rte", "dpt"), [0, 1]),  # the default scene: two skies train, sky2 is novel
    (("preset=tiny",), ("ea", "rte", "dpt"), [0, 1]),  # the tests' scene: the same skies
    (("experiment=rte_paper",), ("rte",), [0]),  # the paper's light field: one sky
    ((), ("forward",), [0]),  # the solver check under the first sky
])
def test_stages_train_on_the_scene_s_training_skies(overrides, stages, trained):
    """``scene.environments.train`` decides the photos every stage trains on (stage 1, stage
    2 and the baseline alike); the default scene renders a third sky that none trains on."""
    for stage in stages:
        cfg = compose_config("train", [f"stage={stage}", *overrides])
        assert list(cfg.data.environments) == trained, stage
    default = compose_config("train", [])
    assert list(default.scene.environments.sky_seeds) == [0, 1, 2]
