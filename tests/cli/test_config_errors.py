"""Config mistakes through the real command line: every one ends with a one-paragraph
``nrt: error:`` naming the key (and the fix), exit status 2, no traceback, nothing written
(:mod:`nrt.cli.config_errors`). Mistakes a component judges (values out of range) are
covered in ``test_rte_paper_stage.py``."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from nrt.cli.checks import check_arguments
from nrt.errors import ConfigError
from nrt.run_dirs import LAST_CKPT, SWEEP_FILE, earlier_job
from tests.conftest import cli_in_process, compose_config, multirun

pytestmark = pytest.mark.e2e

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
    ("train", ("stage=dpt", "budget.dpt.spp_final=0"), "budget.dpt.spp_final=0: must be a whole"),
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
    """In the test's process (:func:`cli_in_process`); one case also as a command of its
    own (:func:`test_a_config_mistake_in_a_real_process`)."""
    out = tmp_path / "out"
    out.mkdir()
    proc = cli_in_process(command, "preset=tiny", f"paths.data_dir={tmp_path / 'datasets'}",
                          *overrides, env={"NRT_OUTPUT_DIR": str(out)})
    assert_one_paragraph(proc, needle)
    assert list(out.iterdir()) == [] and not (tmp_path / "datasets").exists()


def assert_one_paragraph(proc: subprocess.CompletedProcess, needle: str) -> None:
    """Status 2, one paragraph after ``nrt: error:`` that says ``needle``, no traceback."""
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and "HYDRA_FULL_ERROR" not in proc.stderr
    message = proc.stderr.split("nrt: error: ", 1)[-1]
    assert "nrt: error: " in proc.stderr and needle in message, proc.stderr[-3000:]
    assert "\n" not in message.strip(), message  # one paragraph


def test_a_config_mistake_in_a_real_process(tmp_path):
    """The same refusal from ``python -m nrt.cli.train`` as a process of its own."""
    out = tmp_path / "out"
    out.mkdir()
    cmd = [sys.executable, "-m", "nrt.cli.train", "preset=tiny",
           f"paths.data_dir={tmp_path / 'datasets'}", "foo=1"]
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    proc = subprocess.run(cmd, env={**env, "NRT_OUTPUT_DIR": str(out)}, capture_output=True,
                          text=True, timeout=300)
    assert_one_paragraph(proc, "foo=1: the config has no key 'foo'")
    assert list(out.iterdir()) == [] and not (tmp_path / "datasets").exists()


SHAPE_MISTAKES = [  # overrides of nrt-train, what check_arguments must say
    (("stage=rte", "experiment=rte_paper", "model.lr=0.01"),
     "Its entries are light, medium, density: set each entry: model.lr.light=0.01"),
    (("stage=ea", "model.lr={a:1}"), "model.lr={a: 1}: must be a single value, not a mapping. "
                                     "The default is model.lr=0.01."),
    (("stage=ea", "model.density_field=3"),
     "It is the config group model/density_field: choose an option with model/density_field="),
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


# The matching rule is unit-tested in the fast tier; this one starts a sweep.
@pytest.mark.slow
def test_resume_in_a_multirun_without_earlier_jobs_is_a_clear_error(tmp_path):
    """``nrt-train -m ... resume=true`` where no earlier job has the overrides: the first
    job says so (and how to continue with other values) before any data, status 2, and
    the sweep leaves no folder."""
    proc = multirun(tmp_path / "out", tmp_path / "datasets", "seed=0,1", "resume=true")
    assert proc.returncode == 2, proc.stderr[-3000:]
    message = proc.stderr.split("nrt: error: ", 1)[-1]
    assert "resume=true in a multirun continues each job" in message and "job 0" in message
    assert "exclude_keys=[resume,<key>]" in message and "\n" not in message.strip()
    assert not (tmp_path / "out").exists()
    assert not (tmp_path / "datasets").exists()


def test_earlier_job_is_the_newest_with_the_same_overrides(tmp_path):
    """A job matches on its task overrides without the excluded keys, in any order, only
    with a checkpoint, never in the sweep being run; the newest checkpoint wins."""
    def job(sweep: str, num: int, overrides: list[str], ckpt: bool = True) -> Path:
        folder = tmp_path / "multirun" / sweep / str(num)
        (folder / ".hydra").mkdir(parents=True)
        OmegaConf.save(OmegaConf.create(overrides), folder / ".hydra" / "overrides.yaml")
        if ckpt:
            (folder / LAST_CKPT).parent.mkdir()
            (folder / LAST_CKPT).write_text(sweep)
        return folder

    old = job("a", 0, ["stage=ea", "seed=1", "budget.ea.steps=20"])
    job("a", 1, ["stage=ea", "seed=0", "budget.ea.steps=20"])
    job("b", 0, ["stage=ea", "seed=1", "budget.ea.steps=20"], ckpt=False)
    current = job("c", 0, ["seed=1", "stage=ea", "budget.ea.steps=20"])
    wanted = ["seed=1", "budget.ea.steps=40", "stage=ea", "resume=true"]
    base = tmp_path / "multirun"
    assert earlier_job(base, wanted, exclude_sweep=base / "c") is None  # steps differ
    keys = ("resume", "budget.ea.steps")
    assert earlier_job(base, wanted, keys, exclude_sweep=base / "c") == old
    assert earlier_job(base, wanted, keys) == current  # newest, when its sweep is not running
    assert earlier_job(base, ["stage=ea", "seed=2"], keys) is None


@pytest.mark.slow
def test_resume_in_a_multirun_continues_each_job_in_its_own_folder(tmp_path, tiny_dataset):
    """A sweep of two seeds, then the same sweep with resume=true and more steps (the steps
    key excluded from the match): each job continues in its own folder to the new step
    count, with its own seed, and no new job folder appears."""
    out, sweep = tmp_path / "out", ("seed=0,1", "budget.val_every=20", "logger=[csv]")
    first = multirun(out, tiny_dataset.parent, *sweep, "budget.ea.steps=20")
    assert first.returncode == 0, first.stderr[-3000:]
    jobs = sorted(p.parent.parent for p in out.glob(f"multirun/*/*/{LAST_CKPT}"))
    assert len(jobs) == 2
    again = multirun(out, tiny_dataset.parent, *sweep, "budget.ea.steps=30", "resume=true",
                     "hydra.job.config.override_dirname.exclude_keys=[resume,budget.ea.steps]")
    assert again.returncode == 0, again.stderr[-3000:]
    assert sorted(p.parent.parent for p in out.glob(f"multirun/*/*/{LAST_CKPT}")) == jobs
    for job in jobs:
        saved = torch.load(job / LAST_CKPT, weights_only=False, map_location="cpu")
        assert saved["global_step"] == 30
        first_seed = [o for o in OmegaConf.load(job / ".hydra" / "overrides.yaml")
                      if o.startswith("seed=")]
        resumed = OmegaConf.load(next(job.glob(".hydra/resumed-*/overrides.yaml")))
        assert [o for o in resumed if o.startswith("seed=")] == first_seed
        assert list(job.glob("csv/resumed-*/metrics.csv"))
    new_sweeps = [p for p in (out / "multirun").iterdir() if p != jobs[0].parent]
    assert [sorted(c.name for c in p.iterdir()) for p in new_sweeps] == [[SWEEP_FILE]]
