"""Sweeps through Hydra's launchers (the ``scale`` extra): the jobs run in processes of
their own, each in its own folder of the one sweep folder, on their share of the cores;
and a sweep survives a job that is killed: run again with ``resume=true``, or in its own
folder as a cluster re-queues it (``NRT_SWEEP_DIR``), the killed job continues from its
checkpoint and the finished one is left as it is."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest
import torch

from nrt.run_dirs import LAST_CKPT, RUN_FILE, SWEEP_ENV, SWEEP_FILE
from tests.conftest import kill_after_checkpoint, multirun, multirun_command

pytestmark = pytest.mark.e2e

CORES = len(os.sched_getaffinity(0))
SWEEP = ("budget.ea.steps=20", "seed=0,1", "budget.val_every=10", "budget.checkpoint_every=10")


@pytest.mark.slow  # two 20-step EA jobs at once (~15 s)
@pytest.mark.parametrize(("plugin", "launcher", "threads"), [
    # nrt's preset of Hydra's joblib launcher, 2 jobs at once (NRT_JOBS)
    ("hydra_joblib_launcher", ("hydra/launcher=nrt_joblib",), max(1, CORES // 2)),
    ("hydra_submitit_launcher", ("hydra/launcher=submitit_local",
                                 "hydra.launcher.cpus_per_task=1",
                                 "hydra.launcher.timeout_min=10"), 1),
], ids=["nrt_joblib", "submitit_local"])
def test_a_sweep_runs_its_jobs_in_processes_of_their_own(tmp_path, tiny_dataset, plugin,
                                                         launcher, threads):
    pytest.importorskip(f"hydra_plugins.{plugin}")
    proc = multirun(tmp_path, tiny_dataset.parent, *SWEEP, *launcher, env={"NRT_JOBS": "2"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    (sweep,) = (tmp_path / "multirun").iterdir()  # one sweep folder for all jobs
    jobs = sorted(p for p in sweep.iterdir() if p.is_dir() and not p.name.startswith("."))
    assert [p.name for p in jobs] == ["0", "1"]
    sweeper = int(sweep.name.rsplit("-", 1)[1])  # <time>-<pid> of the sweep's process
    for seed, job in enumerate(jobs):
        info = json.loads((job / RUN_FILE).read_text())
        assert info["finished_step"] == 20 and Path(info["exports"]["density_grid"]).is_file()
        (own,) = info["ranks"]
        assert own["pid"] != sweeper and own["threads"] == threads
        overrides = (job / ".hydra" / "overrides.yaml").read_text()
        assert f"seed={seed}" in overrides


KILLED = ("budget.ea.steps=20,200", "budget.val_every=100", "budget.checkpoint_every=10")
"""A short job (done in 20 steps) and a long one (200), run one after the other."""


def killed_sweep(out: Path, data_root: Path, env: dict) -> tuple[Path, Path]:
    """:data:`KILLED` killed once the long job saved a checkpoint before its end: the
    finished job's folder and the killed one's."""
    cmd, base = multirun_command(out, data_root, *KILLED)
    proc = subprocess.Popen(cmd, env={**base, **env}, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    kill_after_checkpoint(proc, out, f"multirun/*/1/{LAST_CKPT}", 10, 200)
    (sweep,) = (out / "multirun").iterdir()
    done, killed = sweep / "0", sweep / "1"
    assert json.loads((done / RUN_FILE).read_text())["finished_step"] == 20
    assert not (killed / "density_grid.npz").exists()
    return done, killed


def stamps(job: Path) -> dict[Path, int]:
    return {p: p.stat().st_mtime_ns for p in (job / LAST_CKPT, job / RUN_FILE,
                                              job / "density_grid.npz")}


@pytest.mark.slow  # 220 EA steps in a sweep, killed, and the rest (~40 s)
@pytest.mark.parametrize("again", ["resume=true", "re-queued"])
def test_a_sweep_survives_a_killed_job(tmp_path, tiny_dataset, again):
    """``resume=true``: a new sweep whose jobs continue in the earlier jobs' folders.
    ``re-queued``: the same sweep started again in its own folder, as submitit re-queues a
    preempted job (same sweep folder, same job numbers, no ``resume``)."""
    data = tiny_dataset.parent
    env = {SWEEP_ENV: str(tmp_path / "multirun" / "first")} if again == "re-queued" else {}
    done, killed = killed_sweep(tmp_path, data, env)
    before = stamps(done)
    extra = ("resume=true",) if again == "resume=true" else ()
    proc = multirun(tmp_path, data, *KILLED, *extra, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert stamps(done) == before  # the finished job is left as it is
    saved = torch.load(killed / LAST_CKPT, weights_only=False, map_location="cpu")
    assert saved["global_step"] == 200
    info = json.loads((killed / RUN_FILE).read_text())
    assert info["finished_step"] == 200 and Path(info["exports"]["density_grid"]).is_file()
    assert list(killed.glob("csv/resumed-*/metrics.csv"))  # beside the first start's
    jobs = sorted(p.parent.parent for p in tmp_path.glob(f"multirun/*/*/{LAST_CKPT}"))
    assert jobs == [done, killed]  # no new job folder
    others = [p for p in (tmp_path / "multirun").iterdir() if p != done.parent]
    assert [sorted(c.name for c in p.iterdir()) for p in others] == \
        ([[SWEEP_FILE]] if again == "resume=true" else [])
