"""Config mistakes through the real command line: every one ends with a one-paragraph
``nrt: error:`` naming the key (and the fix), exit status 2, no traceback, nothing written
(:mod:`nrt.cli.config_errors`). Mistakes a component judges (values out of range) are
covered in ``test_rte_paper_stage.py``."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

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
