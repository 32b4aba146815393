"""Every stage keeps the contract of :mod:`nrt.stages.stage` that callbacks, evaluation
and the CLI rely on (they do not probe stages for what they offer); every stage x scene x
preset combination composes, passes the config checks and builds (a scene that differs from
an earlier one only in its medium, at the tiny preset alone)."""

from __future__ import annotations

import hydra
import pytest
import torch
from omegaconf import OmegaConf

from nrt.cli.checks import check_arguments, check_budget, check_mode
from nrt.cli.common import CONFIG_DIR
from nrt.stages.stage import Stage
from tests.conftest import compose_config, saved_checkpoint

pytestmark = pytest.mark.integration

STAGES = {  # a medium (property grids)? g scored (the default scene's phase is hg)?
    ("ea",): (False, True),
    ("ea", "mode=generative", "scene=family"): (False, True),
    ("rte", "init=none"): (True, True),
    ("rte", "init=none", "experiment=rte_paper"): (True, True),
    ("forward",): (False, True),
    ("forward", "experiment=rte_paper"): (False, True),
    ("dpt",): (True, True),  # phase=hg: dpt learns the one g, as stage 2 does
    ("dpt", "model.phase_g=0.3"): (True, False),  # a given g is not scored
}


@pytest.mark.parametrize(("overrides", "expected"), list(STAGES.items()),
                         ids=[" ".join(k) for k in STAGES])
def test_every_stage_keeps_the_contract(overrides, expected):
    stage, *rest = overrides
    cfg = compose_config("train", [f"stage={stage}", "preset=tiny", *rest])
    model = hydra.utils.instantiate(cfg.model, _convert_="all")
    assert isinstance(model, Stage)
    learns_medium, learns_g = expected
    assert model.effects == ({} if stage == "ea" else dict(cfg.scene.effects))
    assert model.learns_g == learns_g
    # outside a trainer: no data, no progress, the requested or fallback resolution
    assert model.datamodule() is None and model.ground_truth() is None
    assert model.progress() == 0.0 and model.grid_resolution(None, 7) == 7
    grids = model.property_grids(4)
    if learns_medium:  # in the ground truth's layout, whatever the stage's own grids
        assert grids["sigma_a"].shape == (4, 4, 4, 3) and grids["g"].shape == (4, 4, 4)
        assert model.medium_bbox().shape == (2, 3)
    else:
        assert grids is None


def options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONFIG_DIR / group).glob("*.yaml"))


MODELS = [(s,) for s in options("stage")] + [
    ("rte", "experiment=rte_paper"), ("forward", "experiment=rte_paper")]
"""Every stage, and stage 2 in both formulations."""


def builds_like_an_earlier_scene(scene: str) -> bool:
    """Whether ``scene`` differs from an earlier scene file (in name order, ``default``
    first) only in its name, seed and medium: the values a stage is not built from, so the
    presets build it as they build that scene."""
    def shape(name: str) -> dict:  # the scene file over default.yaml, which they all extend
        merged = OmegaConf.merge(OmegaConf.load(CONFIG_DIR / "scene" / "default.yaml"),
                                 OmegaConf.load(CONFIG_DIR / "scene" / f"{name}.yaml"))
        return {k: v for k, v in OmegaConf.to_container(merged).items()
                if k not in ("defaults", "name", "seed", "medium")}
    scenes = ["default", *(s for s in options("scene") if s not in ("default", "family"))]
    earlier = scenes[:scenes.index(scene)]
    return any(shape(scene) == shape(other) for other in earlier)


BUILT_LIKE_AN_EARLIER_SCENE = {scene for scene in options("scene")
                               if scene != "family" and builds_like_an_earlier_scene(scene)}

COMBINATIONS = [(model, scene, preset) for model in MODELS
                for scene in options("scene") if scene != "family"
                for preset in options("preset")
                if preset == "tiny" or scene not in BUILT_LIKE_AN_EARLIER_SCENE] + [
    (("ea", "mode=generative"), "family", preset) for preset in options("preset")] + [
    (("rte", "mode=generative"), "family", preset) for preset in options("preset")]


@pytest.fixture(scope="module")
def ea_checkpoint(tmp_path_factory):
    """Stage-1 checkpoints (untrained) for the stages that start from one: ``(preset,
    generative) -> path``; a single-scene one at ``tiny`` serves every preset, a generative
    one holds the family's K codes of its preset."""
    saved: dict[tuple[str, bool], str] = {}

    def make(preset: str, generative: bool) -> str:
        key = (preset if generative else "tiny", generative)
        if key not in saved:
            extra = ["mode=generative", "scene=family"] if generative else []
            cfg = compose_config("train", ["stage=ea", f"preset={key[0]}", *extra])
            model = hydra.utils.instantiate(cfg.model, _convert_="all")
            path = tmp_path_factory.mktemp("ea") / "last.ckpt"
            saved_checkpoint(path, model)
            saved[key] = str(path)
        return saved[key]

    return make


@pytest.mark.slow
@pytest.mark.parametrize(("model", "scene", "preset"), COMBINATIONS,
                         ids=[f"{' '.join(m)}-{s}-{p}" for m, s, p in COMBINATIONS])
def test_every_stage_scene_and_preset_composes_and_builds(model, scene, preset,
                                                          ea_checkpoint):
    """Each combination of conf/stage, conf/scene and conf/preset (both stage-2
    formulations; the generative mode's stages on the family; a scene that builds like an
    earlier one at ``tiny`` only) passes the checks nrt-train
    makes before any data and builds its stage, as nrt-train does once the EA checkpoint
    is resolved (~0.5 s each)."""
    stage, *rest = model
    ckpt = ea_checkpoint(preset, "mode=generative" in rest)
    cfg = compose_config("train", [f"stage={stage}", f"scene={scene}", f"preset={preset}",
                                   f"init.ea_ckpt={ckpt}", *rest])
    check_budget(cfg)
    check_mode(cfg)
    check_arguments(cfg)
    built = hydra.utils.instantiate(cfg.model, _convert_="all")
    assert isinstance(built, Stage)
    assert all(torch.isfinite(p).all() for p in built.parameters())
