"""Config mistakes through the real command line: every one ends with a one-paragraph
``nrt: error:`` naming the key (and the fix), exit status 2, no traceback, nothing written
(:mod:`nrt.cli.config_errors`). Mistakes a component judges (values out of range) are
covered in ``test_rte_paper_stage.py``."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from conftest import compose_config

from nrt.cli.checks import check_arguments
from nrt.errors import ConfigError

MISTAKES = [  # (command, overrides, what the message must say)
    ("train", ("foo=1",), "foo=1: the config has no key 'foo'"),
    ("train", ("model.nonexistent=3",), "model.nonexistent=3: the config has no key"),
    ("train", ("scnee=default",), "did you mean 'scene'?"),
    ("train", ("stage=foo",), "its options are dpt, ea, forward, rte"),
    ("train", ("stage=rte", "model/light_field=nope"), "its options are sh_grid, siren"),
    ("train", ("model/medium=voxel",), "no config group 'model/medium'"),
    ("train", ("experiment=rte_paper",), "goes with stage=rte or stage=forward"),
    ("train", ("foo==1",), "cannot read the override 'foo==1'"),
    ("train", ("~model.nope",), "~model.nope: the config has no key 'model.nope'"),
    ("train", ("stage=rte", "init=none", "model.lr.light=${nope}"),
     "model.lr.light: Interpolation key 'nope' not found"),
    ("train", ("stage=rte", "init=none", "+model.extra=1"), "unexpected keyword argument 'extra'"),
    ("data", ("scene.nope=1",), "scene.nope=1: the config has no key"),
    ("train", ("stage=rte", "model.lr=0.01"),
     "model.lr=0.01: must be a mapping, not a single value. Its entries are light, medium: "
     "set each entry: model.lr.light=0.01 model.lr.medium=0.01."),
    ("train", ("stage=rte", "init=none", "~model.lr.medium"),
     "one learning rate per part, light, medium; medium missing"),
]


@pytest.mark.parametrize(("command", "overrides", "needle"), MISTAKES,
                         ids=[" ".join(m[1]) for m in MISTAKES])
def test_config_mistakes_end_in_one_paragraph_and_status_2(tmp_path, command, overrides,
                                                           needle):
    out = tmp_path / "out"
    out.mkdir()
    cmd = [sys.executable, "-m", f"nrt.cli.{command}", "preset=tiny",
           f"paths.data_dir={tmp_path / 'datasets'}", *overrides]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run(cmd, env={**env, "NRT_OUTPUT_DIR": str(out)}, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "HYDRA_FULL_ERROR" not in proc.stderr
    message = proc.stderr.split("nrt: error: ", 1)[-1]
    assert "nrt: error: " in proc.stderr and needle in message, proc.stderr[-3000:]
    assert "\n" not in message.strip(), message  # one paragraph
    assert list(out.iterdir()) == [] and not (tmp_path / "datasets").exists()


SHAPE_MISTAKES = [  # overrides of nrt-train, what check_arguments must say
    (("stage=rte", "experiment=rte_paper", "model.lr=0.01"),
     "Its entries are light, medium, density: set each entry: model.lr.light=0.01"),
    (("stage=ea", "model.lr={a:1}"), "model.lr={a: 1}: must be a single value, not a mapping. "
                                     "The default is model.lr=0.01."),
    (("stage=ea", "model.field=3"), "Its entries are hidden, layers, geo_features"),
    (("stage=dpt", "model.resolutions=8"), "give a list of one: model.resolutions=[8]"),
    (("stage=rte", "model.sun=5"), "model.sun=5: must be a mapping or null"),
    (("stage=rte", "model.samples=null"), "model.samples=null: must be a mapping, not null"),
    (("stage=rte", "model.weights=1"), "model.weights.photo=1 model.weights.transport=1"),
    (("stage=rte", "model.light_field=3"),
     "It is the config group model/light_field: choose an option with model/light_field="),
    (("stage=rte", "model.medium.resolutions=4"), "model.medium.resolutions=[4]"),
    (("stage=rte", "callbacks.rerender_evaluation.spp=[4]"),
     "callbacks.rerender_evaluation.spp=[4]: must be a single value, not a list"),
    (("stage=ea", "mode=generative", "scene=family", "model.members=[4]"),
     "model.members=[4]: must be a single value"),
]
"""A value of the wrong shape for a component's constructor (the TypeError deep in training
that ``model.lr=0.01`` gave stage 2 before), judged from the config alone; the two CLI
cases above show that it ends as ``nrt: error:`` with status 2 before any data."""


@pytest.mark.parametrize(("overrides", "needle"), SHAPE_MISTAKES,
                         ids=[" ".join(m[0]) for m in SHAPE_MISTAKES])
def test_values_of_the_wrong_shape_are_refused_with_the_fix(overrides, needle):
    from hydra import compose, initialize_config_dir

    from nrt.cli.common import CONFIG_DIR

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base="1.3"):
        cfg = compose("train", ["preset=tiny", *overrides], return_hydra_config=True)
    choices = dict(cfg.hydra.runtime.choices)
    with pytest.raises(ConfigError) as info:
        check_arguments(cfg, choices)
    assert needle in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("overrides", [
    ("stage=ea",), ("stage=rte",), ("stage=forward",), ("stage=dpt",),
    ("stage=rte", "experiment=rte_paper"), ("stage=forward", "experiment=rte_paper"),
    ("stage=rte", "experiment=rte_paper", "model/medium=grid"),
    ("stage=rte", "model/light_field=sh_grid", "model/medium=voxel"),
    ("stage=ea", "mode=generative", "scene=family"), ("stage=rte", "preset=paper")])
def test_every_default_composition_has_the_shapes_its_constructors_take(overrides):
    cfg = compose_config("train", ["preset=tiny", *overrides])
    check_arguments(cfg)
